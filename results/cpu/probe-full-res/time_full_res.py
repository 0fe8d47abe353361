"""Step cost of a feature map at the input resolution (``enc_full_res``), priced on
trained weights.

Encoder-side changes look cheap at initialisation, where every slot's field runs at every
point; trained, keep-mass selection drops most slots per point. So both models start from
one 25,000-step run's moving average (the run's own config, and the same config with
``enc_full_res=True``, whose two new convs keep their initialisation). One training step
of each in turn (interleaved), 2 threads, the recipe's batch (4 scenes x 128 rays): the
images are the first four training scenes' input views; the rays and targets are
``speedbench.make_batch``'s. The committed JSON came from, at the repository root, alone:
    .venv/bin/python results/cpu/probe-full-res/time_full_res.py RUN 15 \
        DATA1/cpu/clevr567/train > results/cpu/probe-full-res/time_full_res.json
"""

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from benchmark.tools.speedbench import compare_train_steps, make_batch
from svorf.checkpoint import load_run
from svorf.model import SVORF

torch.set_num_threads(2)
if len(sys.argv) != 4:
    sys.exit("usage: time_full_res.py RUN REPEATS TRAIN_SPLIT_DIR")
run, repeats, train_dir = sys.argv[1], int(sys.argv[2]), Path(sys.argv[3])
base, _ = load_run(run)
full = SVORF(dataclasses.replace(base.cfg, enc_full_res=True))
missing = full.load_state_dict(base.state_dict(), strict=False).missing_keys
assert all(k.startswith(("encoder.stem_full", "encoder.up4")) for k in missing), missing
models = {"run's config": base, "enc_full_res": full}
for m in models.values():
    m.train()
    m.set_progress(0.9)
views = sorted(train_dir.glob("*_az00.png"))[:4]
images = torch.tensor(
    np.stack([np.asarray(Image.open(p).convert("RGB"), dtype=np.float32) / 255.0 for p in views])
).permute(0, 3, 1, 2)
_, o, d, rgb = make_batch(base.cfg, 4, 128)
report = compare_train_steps(models, (images, o, d, rgb), repeats=repeats)
report["run"] = run
print(json.dumps(report, indent=1))
