#!/usr/bin/env bash
# Runs experiments.build_target on a leased GPU machine (the `device` tool) in the background
# and brings its results back under $OUT, across several calls of at most 10 minutes each:
#
#   bash experiments/gpu_build_target.sh start [build_target flags...]   # launch (returns at once)
#   bash experiments/gpu_build_target.sh poll SECONDS                   # wait, report, pack results
#
# `start` installs the carried mujoco wheels (.whl/, see the device tool's README) and starts
# the build in its own process session, so it outlives the call. `poll` waits until the build
# ends or SECONDS pass, prints the log's tail and build.json, and packs what is finished (the
# latest policy, drafter, datastore, evaluation, build.json, logs) into $OUT/stack.tar.part-*
# (15 MiB parts): unpack here with `cat stack.tar.part-* | tar x`.
set -u
WORK=/tmp/heisd_build
SITE=/tmp/site
export PYTHONPATH=$SITE PYTHONUNBUFFERED=1
case "${1:-}" in
  start)
    shift
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target $SITE .whl/*.whl || exit 1
    mkdir -p $WORK
    setsid nohup python3 -m experiments.build_target --work=$WORK/work "$@" > $WORK/build.log 2>&1 < /dev/null &
    echo $! > $WORK/pid
    sleep 20
    tail -n 20 $WORK/build.log
    ;;
  poll)
    end=$(( $(date +%s) + ${2:-500} ))
    while [ "$(date +%s)" -lt "$end" ] && kill -0 "$(cat $WORK/pid)" 2>/dev/null; do sleep 10; done
    kill -0 "$(cat $WORK/pid)" 2>/dev/null && echo "RUNNING" || echo "ENDED"
    tail -c 6000 $WORK/build.log
    nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv,noheader
    W=$WORK/work
    cat $W/build.json 2>/dev/null
    latest=$(ls -d $W/vla[0-9]* 2>/dev/null | sort -V | tail -n 1)
    items=(build.json logs)
    [ -n "$latest" ] && [ -d "$latest/0" ] && items+=("$(basename "$latest")")
    for f in drafter datastore eval_ar.json; do [ -e "$W/$f" ] && items+=("$f"); done
    (cd $W && tar cf - "${items[@]}" 2>/dev/null) | split -b 15M - "$OUT/stack.tar.part-"
    ls -la "$OUT"
    ;;
  *)
    echo "usage: $0 start [flags] | poll SECONDS" >&2
    exit 2
    ;;
esac
