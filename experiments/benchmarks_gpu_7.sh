#!/bin/bash
# The seventh device job behind BENCHMARKS.md (issue 9), one GPU: does the auto budget gain from
# choosing among fewer options (AR and the 4x2x8 tree, with or without retrieval) than the
# default grid (also 8x4x32)? One replay at batch 1 and 16 (at 256 every option but AR is
# dominated either way); the default grid's cost tables are the fifth job's, copied to $C.
cd "$(dirname "$0")/.."  # repo root
R=${1:-data/res7}; C=${2:-data/res5/costs}; mkdir -p "$R"
T="top_k=4,depth=2,total_tokens=8"
export JAX_COMPILATION_CACHE_DIR="$R/jax_cache"
python -m experiments.bench_methods --suites=all --batch_sizes=1,16 --record_envs=256 --steps=160 --reps=3 \
  --cost_cache="$C" --out="$R/bench_trees.json" \
  --methods="ar;heisd:budget=fixed,$T;heisd;heisd:budget_trees=4x2x8" > "$R/bench_trees.log" 2>&1
