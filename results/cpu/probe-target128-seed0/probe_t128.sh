#!/bin/bash
# The 60-minute probe of TrainConfig.target_size=128 (seed 0), from the repository root.
# 1. The cpu scale's 1,000 CLEVR-567 training scenes rendered at 128x128 (the same scenes
#    and render settings; the folder the benchmark uses for such a split), about 24 minutes:
generate --preset clevr567 --split train --n 1000 --resolution 128 --samples 16 --seed 0 \
  --out data/cpu-128px/clevr567/train --no-progress
# 2. The cpu recipe with finer targets, alone on both cores, scored on the 64x64 test split:
python -m benchmark.tools.recipe train-eval --data data/cpu-128px/clevr567/train \
  --test data/cpu/clevr567/test --out runs/t128_s0 --minutes 60 --seed 0 --eval-every 5000 \
  --train-set target_size=128
python -m benchmark.tools.recipe diagnose runs/t128_s0 --test data/cpu/clevr567/test
