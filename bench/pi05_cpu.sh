#!/usr/bin/env bash
# pi0.5 on CPU against upstream lerobot in one run (bench/vla_cpu.sh says what it measures).
# Usage: bench/pi05_cpu.sh [--iterations N] [--warmup N] [--ref-iterations N] [--checkpoint DIR]
exec "$(dirname "$0")/vla_cpu.sh" --family pi05 "$@"
