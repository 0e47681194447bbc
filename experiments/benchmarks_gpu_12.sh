#!/bin/bash
# The twelfth device job behind BENCHMARKS.md (issue 9), one GPU: the env's recent actions
# alone as candidates (n_candidates=0: no datastore query, a 24-token block instead of 48)
# against the 4 retrieved + 4 recent, both with AR after the candidates, and auto with each.
# `$1` = batch sizes (default 1,16), `$2` = output directory, `$3` = cost tables (the tenth
# job's for the default heisd; the n_candidates=0 tables are measured fresh there).
cd "$(dirname "$0")/.."  # repo root
B=${1:-1,16}; R=${2:-data/res12}; C=${3:-data/res12/costs}; mkdir -p "$R" "$C"
export JAX_COMPILATION_CACHE_DIR="$R/jax_cache"
python -m experiments.bench_methods --suites=all --batch_sizes="$B" --record_envs=256 --steps=160 --reps=3 \
  --cost_cache="$C" --out="$R/bench_recentonly_${B//,/_}.json" --plot="$R/bench_recentonly_${B//,/_}.png" \
  --methods="ar;heisd:budget=fixed,continuation=ar;heisd:budget=fixed,continuation=ar,n_candidates=0;heisd;heisd:n_candidates=0" \
  > "$R/bench_recentonly_${B//,/_}.log" 2>&1
