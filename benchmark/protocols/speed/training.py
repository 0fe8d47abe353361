"""The ``speed`` protocol's training measurements: step time, memory and inference speed,
each measured in a fresh worker subprocess.

Where this sits: :func:`benchmark.protocols.speed.run_speed` makes the ``tab:time``,
``speed`` and ``speed_inference`` rows here (:func:`measure_training`,
:func:`training_row`, :func:`inference_rows`); the sVORF vs uORF-style comparison
(:mod:`.compare`) starts its workers with :func:`run_worker` / :func:`worker_args`
too. The worker itself is :mod:`benchmark.protocols.speed.worker` (its peak memory
belongs to that training alone).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

from benchmark.context import Context
from benchmark.jobs import ModelJob
from benchmark.report import stable_hash
from benchmark.report_row import Row

__all__ = [
    "PAPER_EPOCH_SCENES",
    "available_mb",
    "inference_rows",
    "load_avg",
    "measure_training",
    "run_worker",
    "training_row",
    "worker_args",
]

PAPER_EPOCH_SCENES = 1000  # CLEVR-567 training split


def available_mb() -> float | None:
    """Memory available to new processes (MiB, ``MemAvailable``), None where unknown."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def load_avg() -> list[float] | None:
    """1/5/15-minute load averages (None where the OS has none): the machine's load."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def run_worker(args: dict[str, Any]) -> dict[str, Any]:
    """Run one measurement (:mod:`benchmark.protocols.speed.worker`) in a fresh
    interpreter and return its JSON result.

    Raises:
        RuntimeError: the worker failed (the end of its stderr is in the message).
    """
    env = dict(os.environ)
    repo = Path(__file__).resolve().parents[3]  # benchmark/protocols/speed/training.py
    env["PYTHONPATH"] = os.pathsep.join([str(repo), env.get("PYTHONPATH", "")])
    proc = subprocess.run(
        [sys.executable, "-m", "benchmark.protocols.speed.worker", json.dumps(args)],
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


def worker_args(
    ctx: Context,
    job: ModelJob,
    batch_scenes: int | None,
    tag: str,
    *,
    warmup: int,
    steps: int,
    **extra: Any,
) -> dict[str, Any]:
    """The worker's arguments for training ``job`` at ``batch_scenes`` scenes per step
    (None = the scale's) on the splits of ``job.train_preset``, in a work folder named by
    ``tag``; ``extra`` goes to the worker as is."""
    train = ctx.train_dataset(job)
    test = ctx.dataset(job.train_preset, "test")
    work = (
        ctx.out
        / "speed-work"
        / f"{tag}-{stable_hash([train.fingerprint, batch_scenes, ctx.device])}"
    )
    return {
        "scale": ctx.scale,
        "train_preset": job.train_preset,
        "variant": job.variant,
        "seed": ctx.seeds["train"],
        "device": ctx.device,
        "batch_scenes": batch_scenes,
        "warmup": int(warmup),
        "steps": int(steps),
        "train_dir": str(train.path),
        "test_dir": str(test.path),
        "work": str(work),
        **extra,
    }


def measure_training(
    ctx: Context, job: ModelJob, batch_scenes: int | None, tag: str, render_repeats: int = 1
) -> dict[str, Any]:
    """One worker measurement of ``job`` with the scale's ``speed_warmup`` / ``speed_steps``
    (and ``render_repeats`` timed test scenes for the inference rows)."""
    return run_worker(
        worker_args(
            ctx,
            job,
            batch_scenes,
            tag,
            warmup=ctx.settings.speed_warmup,
            steps=ctx.settings.speed_steps,
            render_repeats=render_repeats,
        )
    )


def training_row(table: str, model: str, m: dict[str, Any], epoch: bool) -> dict[str, Any]:
    """The ``tab:time`` / ``speed`` row of worker result ``m`` (with ``epoch_time_s`` and
    ``memory_gb`` when ``epoch``)."""
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
    extra = {
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
    row = Row(
        table=table,
        model=model,
        dataset="clevr567",
        source="measured",
        metrics=metrics,
        null_reasons=reasons,
        variant="full",
        extra=extra,
    )
    return row.to_dict()


def inference_rows(m: dict[str, Any], scale: str) -> list[dict[str, Any]]:
    """``speed_inference``: novel-view and segmentation images/s from one measurement."""
    rows = []
    n = int(m.get("render_repeats", 1))
    for model, ips, spv, what in (
        (
            f"novel-view rendering (sVORF, {scale} config)",
            m.get("nvs_images_per_s"),
            m.get("render_s_per_view"),
            (
                f"every view ({m.get('render_views')}) of a test scene from one encode of "
                "its input view, RGB + depth + slot masks in one render; median over scenes"
            ),
        ),
        (
            f"segmentation rendering (sVORF, {scale} config)",
            m.get("seg_images_per_s"),
            m.get("seg_s_per_image"),
            (
                "encode + render of the input view only (its slot masks are the "
                "segmentation; RGB and depth come with them); median over scenes"
            ),
        ),
    ):
        metrics = {"images_per_s": ips, "render_s_per_view": spv}
        row = Row(
            table="speed_inference",
            model=model,
            dataset="clevr567",
            source="measured",
            metrics=metrics,
            null_reasons={k: "not_measured" for k, v in metrics.items() if v is None},
            variant="full",
            extra={
                "n_cases": n if ips is not None else 0,
                "device": m["device"],
                "note": f"{what}; {n} test scene(s) timed after one untimed render; the "
                "model is the few-step speed run (render time does not depend on training "
                "with the evaluation knobs off)",
            },
        )
        rows.append(row.to_dict())
    return rows
