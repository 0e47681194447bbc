#!/bin/bash
# Device job (issue 9): per-kernel traces of the decode at batch 256 and 1,024.
#   bash experiments/trace_gpu_job.sh RESULTS_DIR
cd "$(dirname "$0")/.."
R=${1:-results_trace}; mkdir -p "$R"
export JAX_COMPILATION_CACHE_DIR="$R/jax_cache"
date > "$R/start"
python -m experiments.trace_decode --batch_sizes=256,1024 --tree=4x2x8 --reps=5 --trace_calls=2 --top=25 \
  --trace_dir=/tmp/heisd_trace --hlo_dir="$R/hlo" --out="$R/trace_decode.json" > "$R/trace_decode.log" 2>&1
touch "$R/trace.done"
