#!/bin/bash
# The fourth device job behind BENCHMARKS.md (issue 9), one GPU: the speed table from batch 1 to
# 1,024 after the copy-free KV cache (target passes no longer write the cache; vla.commit
# scatters the kept tokens), with fresh cost tables and a replay long enough for the auto
# budget's first tries to amortise. Run in the background and poll:
#   setsid nohup bash experiments/benchmarks_gpu_4.sh [R] &
cd "$(dirname "$0")/.."  # repo root
R=${1:-data/res4}; mkdir -p "$R"
TREE="top_k=4,depth=2,total_tokens=8"
export JAX_COMPILATION_CACHE_DIR="$R/jax_cache"
date > "$R/start"
python -m experiments.bench_methods --suites=all --batch_sizes=1,16,256,1024 --record_envs=1024 --steps=160 --reps=3 \
  --cost_cache="$R/costs" --out="$R/bench_cachefree.json" --plot="$R/bench_cachefree.png" \
  --methods="ar;drafter:acceptance=token_relaxed,relax_bins=9,$TREE;heisd:budget=fixed,$TREE;heisd" \
  > "$R/bench_cachefree.log" 2>&1
touch "$R/bench.done"
