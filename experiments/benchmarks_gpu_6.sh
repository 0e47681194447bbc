#!/bin/bash
# The sixth device job behind BENCHMARKS.md (issue 9), one GPU: the auto budget with and without
# forgetting a passing slow phase (BudgetConfig.forget), against AR and the fixed 4x2x8 budget,
# all with heisd's default 4 recent candidates, at batch 1 / 16 / 256 in one replay. The cost
# tables are the fifth job's (same device kind, model, batch and candidates), copied to $C.
cd "$(dirname "$0")/.."  # repo root
R=${1:-data/res6}; C=${2:-data/res5/costs}; mkdir -p "$R"
T="top_k=4,depth=2,total_tokens=8"
export JAX_COMPILATION_CACHE_DIR="$R/jax_cache"
python -m experiments.bench_methods --suites=all --batch_sizes=1,16,256 --record_envs=256 --steps=160 --reps=3 \
  --cost_cache="$C" --out="$R/bench_forget.json" --plot="$R/bench_forget.png" \
  --methods="ar;heisd:budget=fixed,$T;heisd:budget_forget=0;heisd" > "$R/bench_forget.log" 2>&1
