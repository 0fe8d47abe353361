#!/usr/bin/env bash
# Fine-tune probe: the slot inference alone. The 12,500-step controls trained 8 more
# minutes with every field, composer and centre head all but frozen (lr 1e-7) and the
# encoder and slot decoder at 4e-4 (enc_lr_scale=4000); seeds 0 and 1 side by side.
set -u
cd /work/wt_probe
PY=/work/main/.venv/bin/python
echo "start $(date -u +%H:%M:%S)"
for seed in 0 1; do
  if [ $seed = 0 ]; then src=/work/runs/ctl_s0/runs/d0154b1382db5c06; data=/work/data0
  else src=/work/runs/ctl_s1/runs/d948a8155cd8e562; data=/work/data1; fi
  $PY -m benchmark.tools.recipe train-eval --data $data/cpu/clevr567/train --test $data/cpu/clevr567/test --minutes ${MIN:-8} --init-from $src --threads 1 --eval-every 0 --grid-scenes 6 --seed $seed --lr 1e-7 --train-set enc_lr_scale=4000 --out /work/runs/plr_enc_s${seed} > /work/logs/plr_enc_s${seed}.log 2>&1 &
done
wait
echo "all done $(date -u +%H:%M:%S)"
