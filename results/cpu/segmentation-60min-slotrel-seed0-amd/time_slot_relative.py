"""Step cost of ``ModelConfig.slot_relative`` on the cpu recipe's model (detached centres).

Both models from the same weights, one training step each in turn (interleaved), 2 threads.
Run from the repository root:
    .venv/bin/python results/cpu/segmentation-60min-slotrel-seed0-amd/time_slot_relative.py 11

time_slot_relative.json beside it was written by the first form of this script (the same
loop, inlined), where "ratio" is the one number slot_relative / recipe.
"""

import json
import sys

import torch

from benchmark.tools.speedbench import compare_train_steps, make_batch
from svorf.model import SVORF
from svorf.train import run_configs

torch.set_num_threads(2)
mcfg, tcfg = run_configs("cpu", "clevr567")
models = {}
for name, rel in (("recipe", False), ("recipe+slot_relative", True)):
    torch.manual_seed(0)
    m = SVORF(mcfg.replace(slot_relative=rel)).train()
    m.set_progress(0.9)
    models[name] = m
models["recipe+slot_relative"].load_state_dict(models["recipe"].state_dict())
batch = make_batch(mcfg, tcfg.batch_scenes, tcfg.rays_per_scene)
repeats = int(sys.argv[1]) if len(sys.argv) > 1 else 15
print(json.dumps(compare_train_steps(models, batch, repeats=repeats), indent=1))
