# usage: TREE=<checkout> bash run.sh TAG -- three train stages as a build runs them (A; A,B from stage 1; A,B,B from stage 2), one persistent cache; wall time of each and of its first logged step
set -e
T=/tmp/ovh/$1; cd ${TREE:-/work/main}; rm -rf $T; mkdir -p $T
export JAX_COMPILATION_CACHE_DIR=$T/cache
for spec in "1 /tmp/ovh/A" "2 /tmp/ovh/A,/tmp/ovh/B --init=$T/vla1" "3 /tmp/ovh/A,/tmp/ovh/B,/tmp/ovh/B --init=$T/vla2"; do set -- $spec
  s=$(date +%s.%N)
  python3 -m experiments.train --model=vla --demos=$2 $3 --out=$T/run$1 --steps=3 --batch_size=16 --warmup_steps=1 --log_every=1 --label_sigma_bins=0.6 --image_shift=2 --compute_dtype=bfloat16 --export=$T/vla$1 > $T/log$1 2>&1
  e=$(date +%s.%N); echo "stage $1: $(echo "$e - $s" | bc) s; $(grep -o '"step": 1,.*elapsed_s": [0-9.]*' $T/log$1 | grep -o 'elapsed_s": [0-9.]*')"
done
