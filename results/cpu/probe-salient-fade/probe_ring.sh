#!/usr/bin/env bash
# Second arm of the ray-sampling probe (see probe_fade.sh, whose control arms it shares):
# the recipe's 60-minute models trained 10 more minutes with "object_heavy_ring" rays
# (object-heavy rays with the salient pixels grown by one pixel), seeds 0 and 1 side by
# side (1 thread each: the same load as the pairs of probe_fade.sh). Then `diagnose`.
set -u
cd "$(dirname "$0")/../../.."  # the repository root
runs=${RUNS:-/work/runs}; logs=${LOGS:-/work/logs}
echo "start $(date -u +%H:%M:%S)"
for seed in 0 1; do
  if [ $seed = 0 ]; then
    src=${SRC0:-$runs/l1_s0/runs/6ffc2ae90e183614}; data=${DATA0:-/work/wt_l1/data}
  else
    src=${SRC1:-$runs/l1_s1/runs/79fb7674bbce8029}; data=${DATA1:-data}
  fi
  .venv/bin/python -m benchmark.tools.recipe train-eval --data $data/cpu/clevr567/train --test $data/cpu/clevr567/test --minutes ${MIN:-10} --init-from $src --threads 1 --eval-every 0 --grid-scenes 6 --seed $seed --model-set slot_locality=0.5 --model-set slot_locality_narrow=null --model-set 'photo_l1=[0.0,0.0]' --ray-sampling object_heavy_ring --out $runs/sf_s${seed}_ring > $logs/sf_s${seed}_ring.log 2>&1 &
done
wait
echo "trained $(date -u +%H:%M:%S)"
for seed in 0 1; do
  data=$([ $seed = 0 ] && echo ${DATA0:-/work/wt_l1/data} || echo ${DATA1:-data})
  .venv/bin/python -m benchmark.tools.recipe diagnose $runs/sf_s${seed}_ring --test $data/cpu/clevr567/test > $logs/sf_s${seed}_ring_diag.log 2>&1
done
echo "all done $(date -u +%H:%M:%S)"
