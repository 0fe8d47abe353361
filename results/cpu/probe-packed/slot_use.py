"""How many objects a model's slots find per scene, and how many slots it uses.

Usage: python slot_use.py OUT_JSON RUN TEST [RUN TEST ...]. For each (run, test split) pair
the input view of every test scene is rendered from the encoder's slots
(``benchmark.tools.failures.render_input_view``, the benchmark's own labels); each
ground-truth object is sorted into own / merged / lost (``object_failures``), and the slots
other than the background that are the argmax of at least 4 pixels are counted. A
diagnosis, not a model.
"""

import json
import sys

import numpy as np
import torch

from benchmark.tools.failures import object_failures, render_input_view
from svorf.data import MultiViewDataset
from svorf.train import load_run

torch.set_num_threads(2)
out = {}
for run, split in zip(sys.argv[2::2], sys.argv[3::2]):
    model, _ = load_run(run)
    ds = MultiViewDataset(split, image_size=model.cfg.image_size)
    bg = model.cfg.num_slots - 1
    rows = []
    for i in range(len(ds)):
        labels, _ = render_input_view(model, ds, i, i, 0)
        kinds = [r["kind"] for r in object_failures(labels, ds[i].instances[0], bg)]
        ids, counts = labels.unique(return_counts=True)
        used = sum(1 for s, c in zip(ids.tolist(), counts.tolist()) if s != bg and c >= 4)
        rows.append(
            {
                "objects": len(kinds),
                "slots_used": used,
                **{k: kinds.count(k) for k in ("own", "merged", "lost")},
            }
        )
    key = f"{run} on {split}"
    out[key] = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
    out[key]["num_slots"] = model.cfg.num_slots
    out[key]["scenes_by_slots_used"] = np.bincount([r["slots_used"] for r in rows]).tolist()
    print(key, out[key], flush=True)
with open(sys.argv[1], "w") as f:
    json.dump(out, f, indent=1)
