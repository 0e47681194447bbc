#!/bin/bash
# The device job behind BENCHMARKS.md "Batch-aware speculation" (issue 9) and "The HeiSD
# ablation" (issue 6), with the shipped checkpoints and datastore. Run in the background on
# the GPU machine and poll:  setsid nohup bash experiments/benchmarks_gpu.sh [R] &
# then fetch R (default data/res): bench_batch.{json,log,png}, eval_*.{json,log}.
cd "$(dirname "$0")/.."  # repo root
R=${1:-data/res}; mkdir -p "$R"
TREE="top_k=4,depth=2,total_tokens=8"
date > "$R/start"

# 1. Per-action speed of each method at batch 1..1024 on the same recorded closed-loop steps,
#    the ceiling AR / prefill in the same run (alone on the GPU: timings).
python -m experiments.bench_methods --suites=all --batch_sizes=1,16,256,1024 --record_envs=1024 --steps=50 --reps=5 \
  --cost_cache="$R/costs" --out="$R/bench_batch.json" --plot="$R/bench_batch.png" \
  --methods="ar;ar:dtype=bfloat16;drafter:acceptance=token_relaxed,relax_bins=9,$TREE;heisd:budget=fixed,$TREE;heisd" \
  > "$R/bench_batch.log" 2>&1
touch "$R/bench.done"

# 2. Closed-loop success rates (the first 10 of the 50 fixed initial states of every task),
#    four evaluations at a time (their timings overlap, so only their success rates count).
export XLA_PYTHON_CLIENT_MEM_FRACTION=0.2
ev() { python -m experiments.evaluate --suites=all --episodes=10 --num_envs=400 --cost_cache="$R/costs" \
         --out="$R/eval_$1.json" "${@:2}" > "$R/eval_$1.log" 2>&1; }
T="--top_k=4 --depth=2 --total_tokens=8"
ev ar --method=ar &
ev drafter --method=drafter --acceptance=token_relaxed --relax_bins=9 $T &
ev retrieval --method=retrieval $T &
ev boundary --method=heisd --budget=fixed --retrieval_acceptance=token_relaxed --noskip $T &
wait
ev skip --method=heisd --budget=fixed --retrieval_acceptance=token_relaxed $T &
ev heisd --method=heisd --budget=fixed $T &
ev heisd_auto --method=heisd &
ev ar_bf16 --method=ar --dtype=bfloat16 &
wait
touch "$R/all.done"
