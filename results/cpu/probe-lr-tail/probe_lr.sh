#!/usr/bin/env bash
# Fine-tune probe: a low learning-rate tail. The 12,500-step controls trained 8 more
# minutes at lr 4e-4 (control arm) and 4e-5 (low arm), both arms of a seed side by side.
set -u
cd /work/wt_probe
PY=/work/main/.venv/bin/python
echo "start $(date -u +%H:%M:%S)"
for seed in 0 1; do
  if [ $seed = 0 ]; then src=/work/runs/ctl_s0/runs/d0154b1382db5c06; data=/work/data0
  else src=/work/runs/ctl_s1/runs/d948a8155cd8e562; data=/work/data1; fi
  for arm in ctl low; do
    lr=$([ $arm = ctl ] && echo 4e-4 || echo 4e-5)
    $PY -m benchmark.tools.recipe train-eval --data $data/cpu/clevr567/train --test $data/cpu/clevr567/test --minutes ${MIN:-8} --init-from $src --threads 1 --eval-every 0 --grid-scenes 6 --seed $seed --lr $lr --out /work/runs/plr_${arm}_s${seed} > /work/logs/plr_${arm}_s${seed}.log 2>&1 &
  done
  wait
  echo "seed $seed done $(date -u +%H:%M:%S)"
done
echo "all done $(date -u +%H:%M:%S)"
