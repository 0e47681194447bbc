#!/bin/bash
# The ninth device job behind BENCHMARKS.md (issue 9), one GPU: issue 9's table with this
# session's defaults (heisd: 4 recent candidates, auto budget with forgetting and a 10% margin):
# AR, drafter SD, HeiSD fixed 4x2x8 and HeiSD auto at batch 1 / 16 / 256 in one replay
# (`$1` = batch sizes, default 1,16,256; the 1,024 row as a second call: `bash ... 1024`).
# The cost tables are the fifth job's, copied to $C.
cd "$(dirname "$0")/.."  # repo root
B=${1:-1,16,256}; R=${2:-data/res9}; C=${3:-data/res5/costs}; mkdir -p "$R"
T="top_k=4,depth=2,total_tokens=8"
export JAX_COMPILATION_CACHE_DIR="$R/jax_cache"
python -m experiments.bench_methods --suites=all --batch_sizes="$B" --record_envs=1024 --steps=160 --reps=3 \
  --cost_cache="$C" --out="$R/bench_final_${B//,/_}.json" --plot="$R/bench_final_${B//,/_}.png" \
  --methods="ar;drafter:acceptance=token_relaxed,relax_bins=9,$T;heisd:budget=fixed,$T;heisd" \
  > "$R/bench_final_${B//,/_}.log" 2>&1
