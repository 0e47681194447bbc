#!/bin/bash
# The fifth device job behind BENCHMARKS.md (issue 9), one GPU: the env's own recent actions as
# retrieval candidates (recent_candidates), their speed at batch 1 / 16 against the same
# budgets without them, HeiSD-auto with them at 256, and their closed-loop success rates.
# Run in the background and poll:   setsid nohup bash experiments/benchmarks_gpu_5.sh [R] &
cd "$(dirname "$0")/.."  # repo root
R=${1:-data/res5}; mkdir -p "$R"
T="top_k=4,depth=2,total_tokens=8"
export JAX_COMPILATION_CACHE_DIR="$R/jax_cache"
date > "$R/start"
# 1. speed at batch 1 and 16: fixed budgets with 0 / 4 / 8 recent candidates, auto with 4.
python -m experiments.bench_methods --suites=all --batch_sizes=1,16 --record_envs=256 --steps=160 --reps=3 \
  --cost_cache="$R/costs" --out="$R/bench_recent.json" \
  --methods="ar;heisd:budget=fixed,$T;heisd:budget=fixed,$T,recent_candidates=4;heisd:budget=fixed,$T,recent_candidates=4,n_candidates=2;heisd:budget=fixed,$T,recent_candidates=8,n_candidates=2;heisd:recent_candidates=4" \
  > "$R/bench_recent.log" 2>&1
touch "$R/bench.done"
# 2. closed-loop success with 4 recent candidates (compare experiments/results/evals50/eval50_heisd).
python -m experiments.evaluate --suites=all --episodes=50 --num_envs=1000 --method=heisd --budget=fixed \
  --top_k=4 --depth=2 --total_tokens=8 --recent_candidates=4 --out="$R/eval50_heisd_recent4.json" \
  > "$R/eval50_heisd_recent4.log" 2>&1
touch "$R/eval.done"
# 3. HeiSD-auto with recent candidates at batch 256 (never below AR?).
python -m experiments.bench_methods --suites=all --batch_sizes=256 --record_envs=256 --steps=160 --reps=3 \
  --cost_cache="$R/costs" --out="$R/bench_recent_256.json" --methods="ar;heisd:recent_candidates=4" \
  > "$R/bench_recent_256.log" 2>&1
touch "$R/all.done"
