#!/usr/bin/env bash
# Weight-average probes: the cpu recipe + TrainConfig.average_probes (ema0.9995, ema0.9998,
# tail0.8, tail0.9) at 35,000 steps, seeds 0 and 1 side by side (1 torch thread each), from
# the worktree /work/wt_probe (the recipe with the probes added). The same script resumes.
set -u
cd /work/wt_probe
P=/work/main/.venv/bin/python
echo "start $(date -u +%H:%M:%S)"
for s in 0 1; do
  OMP_NUM_THREADS=1 $P -m benchmark.cli run segmentation --scale cpu --datasets clevr567 --steps 35000 --seed $s --data /work/data$s --out /work/runs/avp_s$s --no-progress > /work/runs/avp_s$s.seg.log 2>&1 &
done
wait
echo "trained $(date -u +%H:%M:%S)"
