#!/usr/bin/env bash
# After avp.sh: the benchmark's novel-view report of each run (its 0.999 average, the
# recipe's), then `diagnose` of the optimizer's weights and each probe, seeds side by side.
set -u
cd /work/wt_probe
P=/work/main/.venv/bin/python
for s in 0 1; do
  (A="--scale cpu --datasets clevr567 --steps 35000 --seed $s --data /work/data$s --out /work/runs/avp_s$s --no-progress"
   OMP_NUM_THREADS=1 $P -m benchmark.cli run nvs $A --no-train > /work/runs/avp_s$s.nvs.log 2>&1
   R=$(ls -d /work/runs/avp_s$s/runs/*/ | head -1)
   for w in raw ema0.9995 ema0.9998 tail0.8 tail0.9; do
     $P -m benchmark.tools.recipe diagnose $R --test /work/data$s/cpu/clevr567/test --threads 1 --weights $w > /work/runs/avp_s$s.diag-$w.log 2>&1
   done
   echo "seed $s done $(date -u +%H:%M:%S)") &
done
wait
