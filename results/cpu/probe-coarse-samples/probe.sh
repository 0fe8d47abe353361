#!/usr/bin/env bash
# Fine-tune probes on top of the recipe with coarse_loss_weight=0.1: the recipe's 60-minute
# models (each seed on its own scenes) trained 10 more minutes, per seed, in three arms:
# the recipe (control), a still smaller coarse weight (0.03), and twice the coarse samples
# per ray (n_coarse 16 -> 32). Each pair (seeds 0 and 1) runs side by side, 1 thread each.
# Then `diagnose` every arm. Run from anywhere; set SRC0/SRC1 (the 60-minute run folders)
# and DATA0/DATA1 (folders holding cpu/clevr567/{train,test}) for your machine.
set -u
cd "$(dirname "$0")/../../.."  # the repository root
runs=${RUNS:-/work/runs}; logs=${LOGS:-/work/logs}
src0=${SRC0:-$(ls -d $runs/cw_60_s0/runs/*/)}; src1=${SRC1:-$(ls -d $runs/cw_60_s1/runs/*/)}
data0=${DATA0:-/work/wt_l1/data}; data1=${DATA1:-data}
arm() { # seed name extra-args...
  local seed=$1 name=$2; shift 2
  local src=$src0 data=$data0
  if [ "$seed" = 1 ]; then src=$src1; data=$data1; fi
  .venv/bin/python -m benchmark.tools.recipe train-eval --data $data/cpu/clevr567/train \
    --test $data/cpu/clevr567/test --minutes ${MIN:-10} --init-from $src --threads 1 \
    --eval-every 0 --grid-scenes 6 --seed $seed --model-set slot_locality=0.5 \
    --model-set slot_locality_narrow=null --model-set 'photo_l1=[0.0,0.0]' "$@" \
    --out $runs/p39_${name}_s$seed > $logs/p39_${name}_s$seed.log 2>&1
}
diag() { # seed name
  local data=$data0; [ "$1" = 1 ] && data=$data1
  .venv/bin/python -m benchmark.tools.recipe diagnose $runs/p39_$2_s$1 \
    --test $data/cpu/clevr567/test > $logs/p39_$2_s$1_diag.log 2>&1
}
echo "start $(date -u +%T)"
for name in ctrl cw003 nc32; do
  case $name in
    ctrl) x=() ;;
    cw003) x=(--model-set coarse_loss_weight=0.03) ;;
    nc32) x=(--model-set n_coarse=32) ;;
  esac
  arm 0 $name "${x[@]}" & arm 1 $name "${x[@]}" & wait
  echo "$name trained $(date -u +%T)"
done
for name in ctrl cw003 nc32; do diag 0 $name & diag 1 $name & wait; done
echo "done $(date -u +%T)"
