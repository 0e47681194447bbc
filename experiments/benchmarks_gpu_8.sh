#!/bin/bash
# The eighth device job behind BENCHMARKS.md (issue 9), one GPU: the auto budget with and without
# its 10% margin over AR (BudgetConfig.margin), against AR and the fixed 4x2x8 budget, at batch 1
# and 16 in one replay (at 256 and 1,024 every drafting option is dominated either way). The
# cost tables are the fifth job's, copied to $C.
cd "$(dirname "$0")/.."  # repo root
R=${1:-data/res8}; C=${2:-data/res5/costs}; mkdir -p "$R"
T="top_k=4,depth=2,total_tokens=8"
export JAX_COMPILATION_CACHE_DIR="$R/jax_cache"
python -m experiments.bench_methods --suites=all --batch_sizes=1,16 --record_envs=256 --steps=160 --reps=3 \
  --cost_cache="$C" --out="$R/bench_margin.json" \
  --methods="ar;heisd:budget=fixed,$T;heisd:budget_margin=0;heisd" > "$R/bench_margin.log" 2>&1
