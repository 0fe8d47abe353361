#!/usr/bin/env bash
# Fine-tune probe of rays anywhere in their pixel (TrainConfig.pixel_jitter=SIDE: each
# training ray passes through a uniform point of a SIDE x SIDE square around its pixel
# centre, the target still the pixel's colour, so the fields are fitted to the pixel's area
# rather than to its centre): the current recipe's 60-minute models (each seed on its own
# scenes) trained 10 more minutes, seeds 0 and 1 side by side (1 thread each). The control
# arms are the `ctrl` arms of results/cpu/probe-coarse-samples/probe.sh (same start, same
# settings). Then `diagnose`.
# Set SRC0/SRC1 (the 60-minute run folders) and DATA0/DATA1 for your machine.
set -u
cd "$(dirname "$0")/../../.."  # the repository root
runs=${RUNS:-/work/runs}; logs=${LOGS:-/work/logs}; side=${SIDE:-1.0}; tag=${TAG:-pj1}
src0=${SRC0:-$(ls -d $runs/cw_60_s0/runs/91582c784e682827/)}
src1=${SRC1:-$(ls -d $runs/cw_60_s1/runs/*/)}
data0=${DATA0:-/work/wt_l1/data}; data1=${DATA1:-data}
echo "start $(date -u +%T)"
for seed in 0 1; do
  src=$src0; data=$data0
  if [ $seed = 1 ]; then src=$src1; data=$data1; fi
  .venv/bin/python -m benchmark.tools.recipe train-eval --data $data/cpu/clevr567/train \
    --test $data/cpu/clevr567/test --minutes ${MIN:-10} --init-from $src --threads 1 \
    --eval-every 0 --grid-scenes 6 --seed $seed --model-set slot_locality=0.5 \
    --model-set slot_locality_narrow=null --model-set 'photo_l1=[0.0,0.0]' \
    --train-set "pixel_jitter=$side" --out $runs/p43_${tag}_s$seed \
    > $logs/p43_${tag}_s$seed.log 2>&1 &
done
wait
echo "trained $(date -u +%T)"
for seed in 0 1; do
  data=$data0; [ $seed = 1 ] && data=$data1
  .venv/bin/python -m benchmark.tools.recipe diagnose $runs/p43_${tag}_s$seed \
    --test $data/cpu/clevr567/test > $logs/p43_${tag}_s${seed}_diag.log 2>&1 &
done
wait
echo "done $(date -u +%T)"
