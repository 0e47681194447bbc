#!/bin/bash
# The device job behind BENCHMARKS.md "HeiSD (issue 6)": demos -> datastore -> calibration ->
# bench_methods -> closed-loop evals. Run in the background on the GPU machine (setsid nohup
# bash experiments/heisd_gpu_job.sh &), poll data/res/*.done, fetch data/res and data/datastore.
cd "$(dirname "$0")/.."  # repo root
R=data/res; mkdir -p $R data
TREE="top_k=4,depth=2,total_tokens=8"
date > $R/start
if [ ! -f data/datastore/boundary.json ]; then
python -m experiments.collect_demos --suites=all --episodes_per_task=75 --num_envs=1500 --action_noise=0.15 --out=data/demos > $R/collect.log 2>&1
python -m experiments.build_datastore --demos=data/demos --out=data/datastore --overwrite > $R/build.log 2>&1
python -m experiments.calibrate_boundary --demos=data/demos --datastore=data/datastore --settings=$TREE > $R/calibrate.log 2>&1
fi
touch $R/phase1.done
python -m experiments.bench_methods --suites=all --batch_sizes=1,256 --record_envs=256 --steps=100 --reps=3 \
  --datastore=data/datastore --out=$R/bench_methods.json \
  --methods="ar;drafter:acceptance=token_relaxed,relax_bins=9,$TREE;retrieval:$TREE;heisd:$TREE;heisd:acceptance=strict,$TREE" > $R/bench_methods.log 2>&1
touch $R/bench.done
ev() { python -m experiments.evaluate --suites=all --episodes=10 --num_envs=400 --datastore=data/datastore --out=$R/eval_$1.json "${@:2}" > $R/eval_$1.log 2>&1; }
ev ar --method=ar
ev heisd --method=heisd --top_k=4 --depth=2 --total_tokens=8
ev drafter --method=drafter --acceptance=token_relaxed --relax_bins=9 --top_k=4 --depth=2 --total_tokens=8
ev retrieval --method=retrieval --top_k=4 --depth=2 --total_tokens=8
ev boundary --method=heisd --retrieval_acceptance=token_relaxed --noskip --top_k=4 --depth=2 --total_tokens=8
ev skip --method=heisd --retrieval_acceptance=token_relaxed --top_k=4 --depth=2 --total_tokens=8
touch $R/all.done
