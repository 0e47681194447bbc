#!/bin/bash
# The second device job behind BENCHMARKS.md: the last ablation rungs (issue 6), the closed-loop
# relax_bins sweep (issue 5), HeiSD with the automatic budget (issue 9) and the evaluator's
# throughput (issue 7). Run in the background on the GPU machine and poll:
#   setsid nohup bash experiments/benchmarks_gpu_2.sh [R] &
# Results land in R (default data/res2) as they finish; *.done marks each phase.
cd "$(dirname "$0")/.."  # repo root
R=${1:-data/res2}; mkdir -p "$R"
TREE="top_k=4,depth=2,total_tokens=8"
T="--top_k=4 --depth=2 --total_tokens=8"
# Compiled programs are shared between processes (phase 1 compiles what phase 3 times).
export JAX_COMPILATION_CACHE_DIR="$R/jax_cache"
date > "$R/start"

# 0. The cost table of HeiSD-auto at 16 envs, alone on the GPU (phase 1 and 2 reuse it).
python - "$R/costs" > "$R/calibrate16.log" 2>&1 <<'EOF'
import sys
import envs  # noqa: F401
from envs import tasks
from envs.env import TabletopEnv
from heisd_jax import methods
policy = methods.make_policy("heisd", TabletopEnv(tasks.get_tasks("all")), batch_size=16, cost_cache=sys.argv[1])
print(policy.meta["cost_table"].report())
EOF
touch "$R/calibrate.done"

# 1. Closed-loop success rates, all at once (only their success rates count; their timings
#    overlap), and the throughput benchmark's compiles (persistent cache, timed in phase 3).
export XLA_PYTHON_CLIENT_PREALLOCATE=false
ev() { python -m experiments.evaluate --episodes=10 --num_envs=400 --cost_cache="$R/costs" \
         --out="$R/eval_$1.json" "${@:2}" > "$R/eval_$1.log" 2>&1; }
ev skip --suites=all --method=heisd --budget=fixed --retrieval_acceptance=token_relaxed $T &
ev heisd --suites=all --method=heisd --budget=fixed $T &
ev heisd_auto16 --suites=all --method=heisd --num_envs=16 &
for r in 0 3 6 15; do
  ev "drafter_r$r" --suites=goal --method=drafter --acceptance=token_relaxed --relax_bins=$r $T &
done
for b in 1 64 256 1024; do
  python -m experiments.bench_throughput --method=ar --suites=spatial --batch_sizes=$b --episodes=1 \
    --seq_episodes=1 > "$R/warm_throughput_$b.log" 2>&1 &
done
wait
unset XLA_PYTHON_CLIENT_PREALLOCATE
touch "$R/evals.done"

# 2. Per-action speed on recorded closed-loop steps at batch 1, 16, 256 (alone): the
#    relax_bins sweep and HeiSD-auto against AR in one run.
DR="drafter:acceptance=token_relaxed,$TREE,relax_bins"
python -m experiments.bench_methods --suites=all --batch_sizes=1,16,256 --record_envs=256 --steps=40 --reps=3 \
  --cost_cache="$R/costs" --out="$R/bench_r.json" \
  --methods="ar;$DR=0;$DR=3;$DR=6;$DR=9;$DR=15;heisd" > "$R/bench_r.log" 2>&1
touch "$R/bench.done"

# 3. Policy-in-the-loop throughput of the batched evaluator vs a sequential loop (alone).
python -m experiments.bench_throughput --method=ar --suites=spatial --batch_sizes=1,64,256,1024 --episodes=16 \
  --seq_episodes=16 --out="$R/throughput.json" > "$R/throughput.log" 2>&1
touch "$R/all.done"
