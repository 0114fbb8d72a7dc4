#!/usr/bin/env bash
# SmolVLA on CPU against upstream lerobot in one run (bench/vla_cpu.sh says what it measures).
# Usage: bench/smolvla_cpu.sh [--iterations N] [--warmup N] [--ref-iterations N] [--checkpoint DIR]
exec "$(dirname "$0")/vla_cpu.sh" --family smolvla "$@"
