"""Subprocess of the ``speed`` protocol: one timed training + render measurement.

Run as ``python -m benchmark.protocols._speed_worker '<json args>'``; prints one
JSON line. A separate process so that its peak memory is this measurement's alone.
"""

from __future__ import annotations

import json
import resource
import shutil
import sys
import time
from pathlib import Path


def main(argv: list[str]) -> int:
    import torch

    from benchmark import adapter

    a = json.loads(argv[0])
    work = Path(a["work"])
    shutil.rmtree(work, ignore_errors=True)  # always a fresh run: timings, not results
    mcfg = adapter.model_config(a["scale"], a["train_preset"], a["variant"])
    warm = adapter.train_config(
        a["scale"], a["train_preset"], a["variant"], a["seed"], a["device"], steps=a["warmup"]
    )
    changes = {"log_every": 1, "ckpt_every": 10**9}
    if a["batch_scenes"]:
        changes["batch_scenes"] = int(a["batch_scenes"])
    warm = warm.replace(**changes)
    cuda = a["device"].startswith("cuda")
    t0 = time.perf_counter()
    adapter.train(a["train_dir"], work, mcfg, warm, progress=False)
    warm_wall = time.perf_counter() - t0
    if cuda:
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    timed = warm.replace(steps=a["warmup"] + a["steps"])
    t0 = time.perf_counter()
    summary = adapter.train(a["train_dir"], work, mcfg, timed, progress=False)
    if cuda:
        torch.cuda.synchronize()
    timed_wall = time.perf_counter() - t0
    s_per_step = summary.get("s_per_step") or timed_wall / a["steps"]

    model = adapter.load_model(work, device=a["device"])
    ds = adapter.open_dataset(a["test_dir"], image_size=mcfg.image_size)
    adapter.predict_scene(model, ds, 0)  # untimed (lazy init, caches)
    if cuda:
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    pred = adapter.predict_scene(model, ds, 0)
    if cuda:
        torch.cuda.synchronize()
    render_wall = time.perf_counter() - t0
    n_views = pred.rgb.shape[0]
    if cuda:
        peak_mb = torch.cuda.max_memory_allocated() / 2**20
        kind = "torch.cuda.max_memory_allocated during the timed steps"
    else:
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        kind = "peak RSS of the measuring process (CPU)"
    out = {
        "s_per_step": float(s_per_step),
        "timed_steps": int(a["steps"]),
        "warmup_steps": int(a["warmup"]),
        "timed_wall_s": timed_wall,
        "warmup_wall_s": warm_wall,
        "render_wall_s": render_wall,
        "render_s_per_view": render_wall / n_views,
        "peak_memory_mb": float(peak_mb),
        "memory_kind": kind,
        "batch_scenes": int(timed.batch_scenes),
        "rays_per_scene": int(timed.rays_per_scene),
        "params": summary.get("params"),
        "device": a["device"],
        "model_config": adapter.config_dict(mcfg),
        "train_config": adapter.config_dict(timed),
    }
    shutil.rmtree(work, ignore_errors=True)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
