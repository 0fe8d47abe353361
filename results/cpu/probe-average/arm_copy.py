"""Copy a benchmark run folder with one of its weight-average probes in place of its
moving average, so that `benchmark run ... --no-train --out COPY` scores that probe with the
benchmark's own evaluation (the config key, and so the run folder's name, is unchanged).

    python arm_copy.py OUT/runs/KEY COPY_OUT NAME     # NAME: ema0.9995, tail0.8, ... or raw
"""

import shutil
import sys
from pathlib import Path

import torch

from svorf.checkpoint import atomic_torch_save

src, dst_out, name = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
dst = dst_out / "runs" / src.name
if dst.exists():
    sys.exit(f"arm_copy: {dst} exists")
dst.mkdir(parents=True)
for f in src.iterdir():
    if f.is_file() and f.name != "checkpoint.pt":
        shutil.copy2(f, dst / f.name)
ckpt = torch.load(src / "checkpoint.pt", weights_only=True)
probes = ckpt.pop("model_average_probes")
ckpt["model_ema"] = ckpt["model"] if name == "raw" else probes[name]["model"]
atomic_torch_save(ckpt, dst / "checkpoint.pt")
print(f"{dst}: model_ema <- {name} (step {ckpt['step']})")
