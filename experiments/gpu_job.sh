#!/usr/bin/env bash
# Runs experiments on a leased GPU machine (the device tool), with the carried mujoco wheels.
#
#   bash experiments/gpu_job.sh -- CMD [ARGS...] [-- CMD ...]        # run each command in turn
#   bash experiments/gpu_job.sh per-gpu -- [@GPUS] CMD [ARGS...] [-- ...] # command i on GPU i, all at once
#   bash experiments/gpu_job.sh start [per-gpu] -- CMD [ARGS...] [-- ...]  # either, in the background,
#                                         from a copy of the tree in $GPU_JOB_WORK/src
#   bash experiments/gpu_job.sh poll SECONDS [PATH...]               # wait, report, pack results
#                                         (SECONDS is capped to end 40 s before the call's 600 s limit)
#   bash experiments/gpu_job.sh stop [PATH...]                        # end the job, report, pack results
#
# GPU_JOB_STEP_TIMEOUT=SECONDS (in start's environment, or the foreground's) ends any one
# command that runs longer (logged as "== timed out"), and the job goes on to the next: a
# command that hangs (say, a kernel's compile) then costs at most that much device time. It
# gets SIGTERM first and SIGKILL 10 s later: `evaluate` writes its ended episodes in between.
#
# per-gpu runs command i alone on GPU i (CUDA_VISIBLE_DEVICES=i), all at once, each with its
# own output folder $OUT/gpuI (its $OUT, its job.log) and compilation cache, and waits for all:
# the device tool counts a machine's time, not its GPUs', so a 2- or 4-GPU host runs that many
# independent measurements for the price of one. Compare speeds within one command only (each
# times its own baseline): the GPUs share the host's CPU and memory bandwidth. A command that
# begins with @GPUS (e.g. @0,1) runs on those GPUs instead, e.g. a data-parallel build on two
# of a 4-GPU host's GPUs beside two one-GPU measurements: `per-gpu -- @0,1 CMD -- @2 CMD -- @3 CMD`.
# Every `--` starts the next GPU's command (more commands than GPUs: the job does not start), so
# several commands in turn on one GPU go in one shell: `-- @3 bash -c 'CMD1; CMD2 --out=$OUT/x'`.
# A lent multi-GPU host can be taken back mid-job: poll often, naming each build's build.json.
#
# Each command's output is teed to job.log in the folder that comes back, which a command
# names as a literal $OUT (write \$OUT): $OUT itself in the foreground; for `start`, which
# returns at once and leaves the job running in its own process session across calls of at
# most 10 minutes, /tmp/gpu_job/out (emptied by each `start`: unpack what `poll` brought back
# first, and carry what a next job needs in the tree), which `poll` packs into $OUT/results-STAMP.tar.part-* (15
# MiB parts, STAMP the UTC time of packing; unpack with `cat results-STAMP.tar.part-* | tar x`): the PATHs given (relative to it; one not
# there yet is named and skipped), each build_target work folder's finished stack (build.json,
# logs, the latest complete vla*, drafter, datastore, eval_ar*.json) and every small result file
# (*.json, *.json.gz, *.log, *.png, *.txt under 2 MB, outside datasets and checkpoints), so a
# measurement's output comes back unnamed; with no PATH and no build, everything.
# A job that failed on a machine still held can be started again over what it left:
# GPU_JOB_KEEP=1 keeps /tmp/gpu_job/out, so a build_target rerun with the same --work resumes
# from its last finished stage with its datasets still there (job.log goes on).
# JAX's compilation cache persists in $GPU_JOB_WORK/jax_cache (GPU_JOB_WORK: /tmp/gpu_job)
# unless JAX_COMPILATION_CACHE_DIR is set. docs/reproduce.md has examples.
set -uo pipefail
# NVLink multicast stays off (the leased hosts' own setting, kept here for every child): a
# program that uses it can put a host's shared GPUs out of service.
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
SELF=$(realpath "$0")
cd "$(dirname "$SELF")/.."  # repo root
WORK=${GPU_JOB_WORK:-/tmp/gpu_job} SITE=/tmp/site
export PYTHONPATH=$SITE PYTHONUNBUFFERED=1 JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-$WORK/jax_cache}
usage() { echo "usage: $0 [start] [per-gpu] -- CMD [ARGS...] [-- CMD ...] | poll SECONDS [PATH...] | stop [PATH...]" >&2; exit 2; }

install() {
  [ -n "${GPU_JOB_SITE_READY:-}" ] && return
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target $SITE .whl/*.whl \
    || { echo "installing the carried wheels (.whl/*.whl) failed" >&2; exit 1; }
}

log() {  # tees into job.log, ignoring SIGTERM: a stopped command's last words reach the log
  trap '' TERM; exec tee -a "$OUT/job.log"
}

run() {  # runs the commands separated by `--` one after another; exits with the last failure
  local rc=0 cmd=() arg
  : "${OUT:?OUT must name the folder that comes back}"; mkdir -p "$OUT"
  for arg in "$@" --; do
    if [ "$arg" != "--" ]; then cmd+=("${arg//\$OUT/$OUT}"); continue; fi
    [ ${#cmd[@]} -eq 0 ] && continue
    echo "== $(date -u +%FT%TZ) ${cmd[*]}" | tee -a "$OUT/job.log"
    if [ -n "${GPU_JOB_STEP_TIMEOUT:-}" ]; then
      timeout --kill-after=10 "$GPU_JOB_STEP_TIMEOUT" "${cmd[@]}" 2>&1 | log
    else
      "${cmd[@]}" 2>&1 | log
    fi
    local s=${PIPESTATUS[0]}; [ "$s" -ne 0 ] && rc=$s
    [ "$s" -eq 124 ] || [ "$s" -eq 137 ] && [ -n "${GPU_JOB_STEP_TIMEOUT:-}" ] && \
      echo "== timed out after ${GPU_JOB_STEP_TIMEOUT}s" | tee -a "$OUT/job.log"
    echo "== exit $s" | tee -a "$OUT/job.log"
    cmd=()
  done
  return $rc
}

pack() {  # the PATHs given and a build's finished stack; with neither, everything; into $OUT
  local d=$WORK/out items=() b v f p
  for p in "$@"; do [ -e "$d/$p" ] && items+=("$p") || echo "pack: no $p (yet)"; done
  local builds; builds=$(cd "$d" && ls -d */build.json */*/build.json 2>/dev/null)  # builds, also under per-gpu's gpuI
  for b in $builds; do  # a build's checkpoint always comes back: a lost machine then costs the stages after it only
    b=${b%/build.json}; items+=("$b/build.json" "$b/logs")
    v=$(cd "$d" && for x in $(ls -d "$b"/vla[0-9]* 2>/dev/null | sort -rV); do [ -d "$x/0" ] && echo "$x" && break; done)
    [ -n "$v" ] && items+=("$v")  # the newest complete policy
    for f in drafter datastore eval_ar.json eval_ar_fresh.json; do [ -e "$d/$b/$f" ] && items+=("$b/$f"); done
  done
  if [ -z "$builds" ] && [ $# -eq 0 ]; then
    items=(.)
  else  # and every small result file (JSON, logs, plots) outside datasets and checkpoints, named or not
    local small; small=$(cd "$d" && find . \( -name 'vla[0-9]*' -o -name 'run[0-9]*' -o -name drafter -o -name datastore \
      -o -name demos -o -name fresh_demos -o -name 'dagger[0-9]*' -o -name target_rollouts -o -name 'jax_cache*' \) -prune -o -type f \
      \( -name '*.json' -o -name '*.json.gz' -o -name '*.log' -o -name '*.png' -o -name '*.txt' \) -size -2M -print)
    for f in $small; do items+=("${f#./}"); done
  fi
  [ ${#items[@]} -eq 0 ] && return 0
  # Named by the time of packing: a local folder that already holds an earlier call's parts
  # (the device tool may reuse one) cannot mix them into this archive.
  local name; name=results-$(date -u +%Y%m%dT%H%M%S).tar
  (cd "$d" && printf '%s\n' "${items[@]}" | awk '!seen[$0]++' | tar cf - --files-from=- --ignore-failed-read) \
    | split -b 15M - "$OUT/$name.part-"
  echo "packed: $name.part-* (cat $name.part-* | tar x)"
}

case "${1:-}" in
  --)
    [ $# -ge 2 ] || usage
    install; run "${@:2}"
    ;;
  per-gpu)
    [ "${2:-}" = "--" ] && [ $# -ge 3 ] || usage
    : "${OUT:?OUT must name the folder that comes back}"
    cmds=() cur="" n=0
    for arg in "${@:3}" --; do  # each command, shell-quoted, for its own `run`
      if [ "$arg" = "--" ]; then [ -n "$cur" ] && cmds+=("$cur"); cur=""; else cur+=" $(printf '%q' "$arg")"; fi
    done
    gpus=$(nvidia-smi -L 2>/dev/null | grep -c '^GPU')
    [ "${#cmds[@]}" -le "$gpus" ] || { echo "per-gpu: ${#cmds[@]} commands for $gpus GPUs" >&2; exit 2; }
    install
    for i in "${!cmds[@]}"; do
      ( eval "set -- ${cmds[$i]}"
        gpu=$i; [[ "$1" == @* ]] && { gpu=${1#@}; shift; }
        export CUDA_VISIBLE_DEVICES=$gpu OUT=$OUT/gpu$i GPU_JOB_SITE_READY=1 \
               JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR}_gpu$i
        run "$@" > /dev/null ) &
    done
    rc=0; for j in $(jobs -p); do wait "$j" || rc=$?; done
    for i in "${!cmds[@]}"; do echo "==== GPU $i"; grep -v '^W[0-9]\{4\}' "$OUT/gpu$i/job.log" | tail -c 4000; done
    exit $rc
    ;;
  start)
    { [ "${2:-}" = "--" ] && [ $# -ge 3 ]; } || { [ "${2:-}" = per-gpu ] && [ "${3:-}" = "--" ] && [ $# -ge 4 ]; } || usage
    kill -0 "$(cat "$WORK/pid" 2>/dev/null)" 2>/dev/null && { echo "a job is already running: poll it" >&2; exit 1; }
    install
    [ -n "${GPU_JOB_KEEP:-}" ] || rm -rf "$WORK/out"  # GPU_JOB_KEEP=1: resume a build in place, datasets kept
    rm -rf "$WORK/src"; mkdir -p "$WORK/out" "$WORK/src"
    # The job runs in its own copy of the tree: every call of the device tool copies the working
    # tree afresh, and a job reading the tree it replaces can find a package half there.
    tar cf - --exclude=./.git --exclude=./.whl . | tar xf - -C "$WORK/src" \
      || { echo "copying the tree to $WORK/src failed" >&2; exit 1; }
    OUT=$WORK/out GPU_JOB_SITE_READY=1 setsid nohup bash "$WORK/src/experiments/gpu_job.sh" "${@:2}" \
      > /dev/null 2>&1 < /dev/null &
    echo $! > "$WORK/pid"
    sleep "${GPU_JOB_START_WAIT:-20}"; tail -n 20 "$WORK/out/job.log" 2>/dev/null || true
    ;;
  poll|stop)
    [ -f "$WORK/pid" ] || { echo "no background job: start one first" >&2; exit 1; }
    pid=$(cat "$WORK/pid")
    if [ "$1" = poll ]; then
      [[ "${2:-}" =~ ^[0-9]+$ ]] || usage
      # The device tool ends a call at GPU_JOB_CALL_LIMIT (600) seconds, and a call cut off
      # brings nothing back: wait at most until 40 s before that, counted from the start of
      # the calling shell (a `start; poll` pair in one call spends start's time first).
      wait=$2 room=$(( ${GPU_JOB_CALL_LIMIT:-600} - 40 - $(ps -o etimes= -p $PPID 2>/dev/null || echo 0) ))
      [ "$wait" -gt "$room" ] && { wait=$(( room > 0 ? room : 0 )); echo "poll: waiting ${wait}s (the call's limit)"; }
      end=$(( $(date +%s) + wait )); shift 2
      while [ "$(date +%s)" -lt "$end" ] && kill -0 "$pid" 2>/dev/null; do sleep 10; done
    else
      shift
      # SIGTERM to the job's whole session (`timeout` puts its command in a process group of its
      # own), then up to GPU_JOB_STOP_WAIT seconds (30) for it to end: `evaluate` writes its ended
      # episodes and its speed first. Then SIGKILL to what is left.
      kill -0 "$pid" 2>/dev/null && { pkill -TERM -s "$pid"; \
        for _ in $(seq "${GPU_JOB_STOP_WAIT:-30}"); do pgrep -s "$pid" > /dev/null || break; sleep 1; done; \
        pkill -KILL -s "$pid"; echo "== stopped $(date -u +%FT%TZ)" >> "$WORK/out/job.log"; }
    fi
    kill -0 "$pid" 2>/dev/null && echo "RUNNING" || echo "ENDED"
    if [ -f "$WORK/out/job.log" ]; then tail -c 6000 "$WORK/out/job.log"
    else for f in "$WORK"/out/gpu*/job.log; do echo "==== ${f#$WORK/out/}"; grep -v '^W[0-9]\{4\}' "$f" | tail -c 3000; done
    fi  # per-gpu: each GPU's own log
    nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv,noheader
    for c in "$JAX_COMPILATION_CACHE_DIR"*; do  # what carrying compiled programs between machines would take
      [ -d "$c" ] && echo "compilation cache $(du -sm "$c" | cut -f1) MiB, largest entries (MiB): $(du -m "$c"/* 2>/dev/null \
        | sort -rn | head -3 | cut -f1 | tr '\n' ' ')"
    done
    cat "$WORK"/out/*/build.json "$WORK"/out/*/*/build.json 2>/dev/null
    pack "$@"; ls -la "$OUT"
    ;;
  *)
    usage
    ;;
esac
