#!/bin/bash
# The eleventh device job behind BENCHMARKS.md (issue 9), one GPU: a second replay of the
# tenth's batch-1 / 16 rows (run-to-run spread) and auto over AR, ar+retrieval and the 4x2x8
# tree alone. `$1` = batch sizes (default 1,16), `$2` = output directory, `$3` = cost tables
# (the tenth job's, copied there; the 4x2x8-only option list is measured fresh).
cd "$(dirname "$0")/.."  # repo root
B=${1:-1,16}; R=${2:-data/res11}; C=${3:-data/res11/costs}; mkdir -p "$R" "$C"
T="top_k=4,depth=2,total_tokens=8"
export JAX_COMPILATION_CACHE_DIR="$R/jax_cache"
python -m experiments.bench_methods --suites=all --batch_sizes="$B" --record_envs=256 --steps=160 --reps=3 \
  --cost_cache="$C" --out="$R/bench_arcont2_${B//,/_}.json" --plot="$R/bench_arcont2_${B//,/_}.png" \
  --methods="ar;heisd:budget=fixed,$T;heisd:budget=fixed,continuation=ar;heisd;heisd:budget_trees=4x2x8" \
  > "$R/bench_arcont2_${B//,/_}.log" 2>&1
