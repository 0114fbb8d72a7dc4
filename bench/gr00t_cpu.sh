#!/usr/bin/env bash
# GR00T N1.7 on CPU against upstream lerobot in one run (bench/vla_cpu.sh says what it measures).
# Usage: bench/gr00t_cpu.sh [--iterations N] [--warmup N] [--ref-iterations N] [--checkpoint DIR]
exec "$(dirname "$0")/vla_cpu.sh" --family gr00t_n17 "$@"
