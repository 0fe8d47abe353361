"""Step cost of ``ModelConfig.slot_relative`` on the cpu recipe's model (detached centres).

Both models from the same weights, one training step each in turn (interleaved), 2 threads.
Run from the repository root:
    .venv/bin/python results/cpu/segmentation-60min-slotrel-seed0-amd/time_slot_relative.py 11
"""

import json
import statistics
import sys

import torch

from benchmark.tools.speedbench import make_batch, time_interleaved, train_step
from svorf.model import SVORF
from svorf.train import run_configs

torch.set_num_threads(2)
mcfg, tcfg = run_configs("cpu", "clevr567")
models = []
for rel in (False, True):
    torch.manual_seed(0)
    m = SVORF(mcfg.replace(slot_relative=rel)).train()
    m.set_progress(0.9)
    models.append(m)
models[1].load_state_dict(models[0].state_dict())
batch = make_batch(mcfg, tcfg.batch_scenes, tcfg.rays_per_scene)
repeats = int(sys.argv[1]) if len(sys.argv) > 1 else 15
steps = [lambda m=m: train_step(m, batch) for m in models]
med = [statistics.median(t) for t in time_interleaved(steps, repeats=repeats, warmup=3)]
report = {
    "batch_scenes": tcfg.batch_scenes,
    "rays_per_scene": tcfg.rays_per_scene,
    "threads": 2,
    "repeats": repeats,
    "median_s": {"recipe": med[0], "recipe+slot_relative": med[1]},
    "ratio": med[1] / med[0],
}
print(json.dumps(report, indent=1))
