#!/bin/bash
# The fifth device job behind BENCHMARKS.md (issue 9), one GPU: the env's own recent actions as
# retrieval candidates (recent_candidates), their speed at batch 1 / 16 / 256 against the same
# fixed budget without them and HeiSD-auto with them (one replay, one run), then their
# closed-loop success rates (compare experiments/results/evals50/eval50_heisd).
# Run in the background and poll:   setsid nohup bash experiments/benchmarks_gpu_5.sh [R] &
cd "$(dirname "$0")/.."  # repo root
R=${1:-data/res5}; mkdir -p "$R"
T="top_k=4,depth=2,total_tokens=8"
export JAX_COMPILATION_CACHE_DIR="$R/jax_cache"
date > "$R/start"
# 1. speed at batch 1, 16 and 256: fixed budgets with 0 / 4 recent candidates (4 or 2 retrieved), auto with 4.
python -m experiments.bench_methods --suites=all --batch_sizes=1,16,256 --record_envs=256 --steps=160 --reps=3 \
  --cost_cache="$R/costs" --out="$R/bench_recent.json" --plot="$R/bench_recent.png" \
  --methods="ar;heisd:budget=fixed,$T;heisd:budget=fixed,$T,recent_candidates=4;heisd:budget=fixed,$T,recent_candidates=4,n_candidates=2;heisd:recent_candidates=4" \
  > "$R/bench_recent.log" 2>&1
touch "$R/bench.done"
# 2. closed-loop success with 4 recent candidates, all 50 initial states per task.
python -m experiments.evaluate --suites=all --episodes=50 --num_envs=1000 --method=heisd --budget=fixed \
  --top_k=4 --depth=2 --total_tokens=8 --recent_candidates=4 --out="$R/eval50_heisd_recent4.json" \
  > "$R/eval50_heisd_recent4.log" 2>&1
touch "$R/all.done"
