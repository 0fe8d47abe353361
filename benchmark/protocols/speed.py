"""``speed`` protocol: training steps/s, peak memory and render time per view.

Where this sits: compared with the paper's Table 8 (``tab:time``: memory and time
of one CLEVR-567 epoch at batch size 1 on a V100). Each measurement runs in a
fresh subprocess (:mod:`benchmark.protocols._speed_worker`) so that the peak
memory belongs to that training alone:

- CPU: peak resident set size of the worker process (includes Python and torch,
  ~0.3 GB); CUDA: ``torch.cuda.max_memory_allocated`` (tensors only).
- steps/s: ``speed_warmup`` untimed steps, then ``speed_steps`` timed steps
  (svorf's own per-step timer, checkpoint writes excluded).
- render time per view: ``svorf.train.predict_scene`` on one test scene (every
  view at the dataset's resolution, after one untimed call), divided by the views.

Rows: ``tab:time`` "sVORF" measured at batch size 1 (the paper's setting), with
``epoch_time_s`` = 1000 scenes x step time (one epoch of CLEVR-567 at batch 1)
and ``memory_gb``; table ``speed`` holds the same at the scale's own batch size.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

from benchmark.paper_numbers import paper_rows
from benchmark.report import RowStore, stable_hash
from benchmark.runner import Context, ModelJob, row_id

__all__ = ["run_speed"]

PAPER_EPOCH_SCENES = 1000  # CLEVR-567 training split


def _measure(ctx: Context, job: ModelJob, batch_scenes: int | None, tag: str) -> dict[str, Any]:
    train = ctx.dataset(job.train_preset, "train")
    test = ctx.dataset(job.train_preset, "test")
    work = (
        ctx.out
        / "speed-work"
        / f"{tag}-{stable_hash([train.fingerprint, batch_scenes, ctx.device])}"
    )
    args = {
        "scale": ctx.scale,
        "train_preset": job.train_preset,
        "variant": job.variant,
        "seed": ctx.seeds["train"],
        "device": ctx.device,
        "batch_scenes": batch_scenes,
        "warmup": ctx.settings.speed_warmup,
        "steps": ctx.settings.speed_steps,
        "train_dir": str(train.path),
        "test_dir": str(test.path),
        "work": str(work),
    }
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(Path(__file__).resolve().parents[2]), env.get("PYTHONPATH", "")]
    )
    proc = subprocess.run(
        [sys.executable, "-m", "benchmark.protocols._speed_worker", json.dumps(args)],
        capture_output=True,
        text=True,
        check=False,
        env=env,
    )
    if proc.returncode != 0:
        raise RuntimeError(
            f"speed worker failed (rc {proc.returncode}): {proc.stderr.strip()[-1500:]}"
        )
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _row(table: str, model: str, m: dict[str, Any], epoch: bool) -> dict[str, Any]:
    step = m["s_per_step"]
    metrics: dict[str, float | None] = {
        "steps_per_s": 1.0 / step if step else None,
        "step_time_s": step,
        "peak_memory_mb": m["peak_memory_mb"],
        "render_s_per_view": m["render_s_per_view"],
    }
    if epoch:
        metrics = {
            "memory_gb": m["peak_memory_mb"] / 1024.0,
            "epoch_time_s": step * PAPER_EPOCH_SCENES / m["batch_scenes"] if step else None,
            **metrics,
        }
    reasons = {k: "not_measured" for k, v in metrics.items() if v is None}
    return {
        "id": row_id(table, model, "clevr567", "measured"),
        "table": table,
        "model": model,
        "dataset": "clevr567",
        "variant": "full",
        "source": "measured",
        "metrics": metrics,
        "null_reasons": reasons,
        "n_cases": int(m["timed_steps"]),
        "batch_scenes": m["batch_scenes"],
        "rays_per_scene": m["rays_per_scene"],
        "memory_kind": m["memory_kind"],
        "params": m.get("params"),
        "device": m["device"],
        "note": (
            f"{m['timed_steps']} timed steps after {m['warmup_steps']} warm-up; batch {m['batch_scenes']} "
            f"scene(s) x {m['rays_per_scene']} rays; memory = {m['memory_kind']}"
            + ("; epoch_time_s = 1000 scenes x step time" if epoch else "")
        ),
        "model_config": m["model_config"],
        "train_config": m["train_config"],
    }


def run_speed(ctx: Context) -> Path:
    """Measure training speed/memory at batch 1 (tab:time) and at the scale's batch size."""
    report = ctx.base_report()
    job = ModelJob("full", "clevr567")
    store = RowStore(
        ctx.report_dir / "rows",
        {
            "scale": ctx.scale,
            "settings": ctx.settings.to_dict(),
            "device": ctx.device,
            "source": ctx.data_source,
            "seed": ctx.seeds,
        },
    )
    rows = paper_rows("tab:time")
    for table, model, batch, epoch in (
        ("tab:time", "sVORF", 1, True),
        ("speed", f"sVORF ({ctx.scale} config)", None, False),
    ):
        rid = row_id(table, model, "clevr567", "measured")
        row = store.get(rid)
        if row is None:
            m = _measure(ctx, job, batch, "b1" if batch == 1 else "scale")
            ctx.timers["training"] += m["timed_wall_s"] + m["warmup_wall_s"]
            ctx.timers["evaluation"] += m["render_wall_s"]
            row = _row(table, model, m, epoch)
            store.put(row)
        rows.append(row)
    report["rows"] = rows
    report["notes"] = [
        (
            "tab:time in the paper: batch size 1 on an NVIDIA V100, full model at 128x128 "
            "supervision; measured rows use this machine, this scale's model and resolution."
        ),
        (
            "CPU memory is the peak resident set size of the measuring process (Python + torch "
            "included); CUDA memory is torch.cuda.max_memory_allocated."
        ),
        *ctx.settings.notes,
    ]
    from benchmark.figures import speed_chart

    report["figures"] = [speed_chart(ctx.report_dir / "speed.png", rows, ctx.scale)]
    return ctx.finish(report)
