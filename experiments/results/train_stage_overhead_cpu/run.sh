# usage: TREE=<checkout> bash run.sh TAG -- three train stages chained as a build chains them, one persistent
# cache: stage 1 on A (label std 2, 4 steps at lr 5e-4), stage 2 on A,B from stage 1's policy (std 2, 3 steps
# at lr 2.5e-4), stage 3 on A,B,B from stage 2's (std 0.6). Prints each stage's wall time and the time to its
# first logged step (compile, one step, the held-out evaluation).
set -e
T=/tmp/ovh/$1; cd ${TREE:-/work/main}; rm -rf $T; mkdir -p $T
export JAX_COMPILATION_CACHE_DIR=$T/cache
stage() {  # N DEMOS FLAGS...
  n=$1 demos=$2; shift 2; s=$(date +%s.%N)
  python3 -m experiments.train --model=vla --demos=$demos --out=$T/run$n --batch_size=16 --log_every=1 --image_shift=2 \
    --compute_dtype=bfloat16 --export=$T/vla$n "$@" > $T/log$n 2>&1
  e=$(date +%s.%N); echo "stage $n: $(echo "$e - $s" | bc) s; first step $(grep -o '"step": 1,.*elapsed_s": [0-9.]*' $T/log$n | grep -o '[0-9.]*$') s"
}
stage 1 /tmp/ovh/A --steps=4 --lr=5e-4 --warmup_steps=2 --label_sigma_bins=2
stage 2 /tmp/ovh/A,/tmp/ovh/B --init=$T/vla1 --steps=3 --lr=2.5e-4 --warmup_steps=1 --label_sigma_bins=2
stage 3 /tmp/ovh/A,/tmp/ovh/B,/tmp/ovh/B --init=$T/vla2 --steps=3 --lr=2.5e-4 --warmup_steps=1 --label_sigma_bins=0.6
ls $T/cache | sed 's/-[0-9a-f]*-cache$//' | sort | uniq -c | tr '\n' ' '; echo
