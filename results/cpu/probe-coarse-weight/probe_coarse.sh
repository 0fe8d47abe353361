#!/usr/bin/env bash
# Fine-tune probe of the coarse pass's loss weight (ModelConfig.coarse_loss_weight, 1.0 in
# every scale): the recipe's 60-minute models (photo_l1 included; each seed on its own
# scenes) trained 10 more minutes with the coarse-pass photometric term at weight 0.1
# (mip-NeRF's), seeds 0 and 1 side by side (1 thread each). The control arms are those of
# results/cpu/probe-salient-fade/probe_fade.sh (same start, same settings, weight 1.0).
# Then `diagnose`.
set -u
cd "$(dirname "$0")/../../.."  # the repository root
runs=${RUNS:-/work/runs}; logs=${LOGS:-/work/logs}; w=${WEIGHT:-0.1}
echo "start $(date -u +%H:%M:%S)"
for seed in 0 1; do
  if [ $seed = 0 ]; then
    src=${SRC0:-$runs/l1_s0/runs/6ffc2ae90e183614}; data=${DATA0:-/work/wt_l1/data}
  else
    src=${SRC1:-$runs/l1_s1/runs/79fb7674bbce8029}; data=${DATA1:-data}
  fi
  .venv/bin/python -m benchmark.tools.recipe train-eval --data $data/cpu/clevr567/train --test $data/cpu/clevr567/test --minutes ${MIN:-10} --init-from $src --threads 1 --eval-every 0 --grid-scenes 6 --seed $seed --model-set slot_locality=0.5 --model-set slot_locality_narrow=null --model-set 'photo_l1=[0.0,0.0]' --model-set coarse_loss_weight=$w --out $runs/cw_s${seed} > $logs/cw_s${seed}.log 2>&1 &
done
wait
echo "trained $(date -u +%H:%M:%S)"
for seed in 0 1; do
  data=$([ $seed = 0 ] && echo ${DATA0:-/work/wt_l1/data} || echo ${DATA1:-data})
  .venv/bin/python -m benchmark.tools.recipe diagnose $runs/cw_s${seed} --test $data/cpu/clevr567/test > $logs/cw_s${seed}_diag.log 2>&1
done
echo "all done $(date -u +%H:%M:%S)"
