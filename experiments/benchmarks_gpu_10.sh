#!/bin/bash
# The tenth device job behind BENCHMARKS.md (issue 9), one GPU: AR after the candidates
# verified in the prefill (heisd continuation=ar; the auto budget's new option ar+retrieval)
# against AR, HeiSD fixed 4x2x8 (drafter continuation) and HeiSD auto, in one replay.
# `$1` = batch sizes (default 1,16), `$2` = output directory, `$3` = recorded envs (default
# 256; 1024 for `bash ... 1024 DIR 1024`); the cost tables are measured fresh (the option
# list changed) into $2/costs; `$4` = the methods (default: the four above).
cd "$(dirname "$0")/.."  # repo root
B=${1:-1,16}; R=${2:-data/res10}; E=${3:-256}; mkdir -p "$R/costs"
T="top_k=4,depth=2,total_tokens=8"
M=${4:-"ar;heisd:budget=fixed,$T;heisd:budget=fixed,continuation=ar;heisd"}
export JAX_COMPILATION_CACHE_DIR="$R/jax_cache"
python -m experiments.bench_methods --suites=all --batch_sizes="$B" --record_envs="$E" --steps=160 --reps=3 \
  --cost_cache="$R/costs" --out="$R/bench_arcont_${B//,/_}.json" --plot="$R/bench_arcont_${B//,/_}.png" \
  --methods="$M" \
  > "$R/bench_arcont_${B//,/_}.log" 2>&1
