#!/usr/bin/env bash
# A GPU machine's check in one short run (benchmarks/gpu_check.py): at most 8 minutes,
# JSON files in OUT. Install first, in a fresh venv on the GPU machine:
#   pip install "jax[cuda12]==0.10.2" .
# usage: benchmarks/gpu_check.sh OUT [gpu_check.py options]
set -euo pipefail
out=${1:?usage: benchmarks/gpu_check.sh OUT [gpu_check.py options]}
shift
cd "$(dirname "$0")/.."
mkdir -p "$out"
{ nvidia-smi || echo "no nvidia-smi"; } > "$out/nvidia-smi.txt" 2>&1
# the parts stop starting at --budget-s (420 s by default); the timeout is the backstop
timeout 480 python benchmarks/gpu_check.py "$out" "$@" 2>&1 | tee "$out/log.txt"
