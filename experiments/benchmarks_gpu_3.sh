#!/bin/bash
# The third device job behind BENCHMARKS.md, for a host of two GPUs (nvidia-h200-x2): the HeiSD
# ablation over all 50 initial states per task (issue 6), the evaluator's throughput at 1,024
# and 2,048 envs on one and two GPUs (issue 7), and the ablation rungs' per-action speed plus
# HeiSD-auto with the format-3 cost table (issues 6 and 9). Run in the background and poll:
#   setsid nohup bash experiments/benchmarks_gpu_3.sh [R] &
# Results land in R (default data/res3) as they finish; *.done marks each phase.
cd "$(dirname "$0")/.."  # repo root
R=${1:-data/res3}; mkdir -p "$R"
TREE="top_k=4,depth=2,total_tokens=8"
T="--top_k=4 --depth=2 --total_tokens=8"
# Compiled programs are shared between processes (phase 1 compiles what phase 2 times).
export JAX_COMPILATION_CACHE_DIR="$R/jax_cache"
date > "$R/start"

# 1. Closed-loop success of the six ablation rungs, 2,000 episodes each, three per GPU at once
#    (only their success rates count; their timings overlap), and the throughput run's compiles.
export XLA_PYTHON_CLIENT_PREALLOCATE=false
ev() { CUDA_VISIBLE_DEVICES=$1 python -m experiments.evaluate --suites=all --episodes=50 --num_envs=1000 \
         --out="$R/eval50_$2.json" "${@:3}" > "$R/eval50_$2.log" 2>&1; }
ev 0 ar --method=ar &
ev 0 drafter --method=drafter --acceptance=token_relaxed --relax_bins=9 $T &
ev 0 retrieval --method=retrieval $T &
ev 1 boundary --method=heisd --budget=fixed --retrieval_acceptance=token_relaxed --noskip $T &
ev 1 skip --method=heisd --budget=fixed --retrieval_acceptance=token_relaxed $T &
ev 1 heisd --method=heisd --budget=fixed $T &
TP="--method=ar --suites=spatial --episodes=8 --seq_episodes=8"
python -m experiments.bench_throughput $TP --batch_sizes=256:1,1024:1 --compile_only > "$R/compile_a.log" 2>&1 &
python -m experiments.bench_throughput $TP --batch_sizes=1024:2,2048:2 --compile_only > "$R/compile_b.log" 2>&1 &
wait
unset XLA_PYTHON_CLIENT_PREALLOCATE
touch "$R/evals.done"

# 2. Policy-in-the-loop throughput, one and two GPUs, vs the sequential loop (alone).
python -m experiments.bench_throughput $TP --batch_sizes=256:1,1024:1,1024:2,2048:2 \
  --out="$R/throughput.json" > "$R/throughput.log" 2>&1
touch "$R/throughput.done"

# 3. Per-action speed on recorded closed-loop steps, one program per GPU (each alone on its
#    GPU): the ablation rungs at batch 1 and 256; HeiSD-auto (cost table calibrated on its idle
#    GPU) at 1, 16, 256, 1,024; then the draft round alone vs in the decode loop.
DS="heisd:budget=fixed,retrieval_acceptance=token_relaxed,$TREE"
CUDA_VISIBLE_DEVICES=0 python -m experiments.bench_methods --suites=all --batch_sizes=1,256 --record_envs=256 \
  --steps=40 --reps=3 --out="$R/bench_ablation.json" \
  --methods="ar;retrieval:$TREE;$DS,skip=false;$DS;heisd:budget=fixed,$TREE" > "$R/bench_ablation.log" 2>&1 &
CUDA_VISIBLE_DEVICES=1 python -m experiments.bench_methods --suites=all --batch_sizes=1,16,256,1024 \
  --record_envs=1024 --steps=40 --reps=3 --cost_cache="$R/costs" --out="$R/bench_auto.json" \
  --plot="$R/bench_auto.png" --methods="ar;heisd" > "$R/bench_auto.log" 2>&1 &
wait
CUDA_VISIBLE_DEVICES=0 python -m experiments.bench_round --batch_sizes=1,16,256 --trees=4x2x8/8x4x32 \
  > "$R/bench_round.log" 2>&1
touch "$R/all.done"
