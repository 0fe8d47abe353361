"""Score trained runs on one test split with the evaluation ``recipe train-eval`` ends with.

Usage: python eval_runs.py OUT_JSON TEST RUN [RUN ...]. Each run is loaded as the
benchmark loads it (its moving average where it kept one) and scored on every scene of
TEST from input view 0: FG-ARI, ARI, NV-ARI, the shuffled-slot FG-ARI, input / novel
PSNR, and the per-object failure breakdown. The same function scores every run, so the
rows compare side by side. A diagnosis, not a model.
"""

import json
import sys

import torch

from benchmark.tools.failures import failure_breakdown
from benchmark.tools.recipe import make_eval_fn
from svorf.data import MultiViewDataset
from svorf.train import load_run

torch.set_num_threads(2)
out_path, test_dir, runs = sys.argv[1], sys.argv[2], sys.argv[3:]
out = {}
for run in runs:
    model, info = load_run(run)
    test = MultiViewDataset(test_dir, image_size=model.cfg.image_size)
    with torch.no_grad():
        res = make_eval_fn(None, len(test))(model, test)
        res["failures"] = failure_breakdown(model, test)
    res.update(step=info.step, wall_s=info.wall_s, num_slots=model.cfg.num_slots)
    out[f"{run} on {test_dir}"] = res
    print(run, {k: round(v, 4) for k, v in res.items() if isinstance(v, float)}, flush=True)
with open(out_path, "w") as f:
    json.dump(out, f, indent=1, sort_keys=True)
