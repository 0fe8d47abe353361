"""The units of work of a table protocol: train one model run, evaluate one model on one
test split, and read / write the evaluation cache.

Where this sits: :class:`benchmark.context.Context` calls :func:`train_run` and
:func:`evaluate_run` in its own process (``--backend local``); :mod:`benchmark.ray_jobs`
calls the same functions as Ray tasks (``--backend ray``), so a model run or an evaluation
is the same bytes on disk whichever backend made it. Nothing here knows about protocols,
rows or the report.
"""

from __future__ import annotations

import io
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmark import adapter
from benchmark.datasets import DatasetInfo
from benchmark.evaluate import EvalResult, evaluate_model
from benchmark.report import write_json
from scenefmt import atomic_write_bytes
from scenefmt.cli_util import progress_kwargs

__all__ = ["ModelJob", "evaluate_run", "read_eval", "train_run", "write_eval"]


@dataclass(frozen=True)
class ModelJob:
    """One model to train: a config variant on a training preset."""

    variant: str
    train_preset: str


def train_run(
    ds_path: Path,
    run_dir: Path,
    mcfg: Any,
    tcfg: Any,
    *,
    key: str,
    key_src: dict[str, Any],
    job: ModelJob,
    progress: bool,
    max_wall_s: float | None,
    init_from: Path | None = None,
) -> tuple[dict[str, Any], float]:
    """Train one cached model run and mark it finished (``benchmark_run.json``).

    The unit of work of :meth:`Context.model` and of a Ray training task
    (:mod:`benchmark.ray_jobs`); svorf resumes an interrupted run from ``run_dir``.

    Returns:
        ``(marker payload, wall seconds of this call)``.
    """
    t = time.perf_counter()
    summary = adapter.train(
        ds_path, run_dir, mcfg, tcfg, progress=progress, max_wall_s=max_wall_s, init_from=init_from
    )
    wall = time.perf_counter() - t
    train_wall = summary.get("train_wall_s")
    train_wall = float(train_wall) if isinstance(train_wall, (int, float)) else wall
    payload = {
        "key": key,
        "key_source": key_src,
        "summary": summary,
        "train_wall_s": train_wall,
        "job": vars(job),
    }
    write_json(Path(run_dir) / "benchmark_run.json", payload)
    return payload, wall


def evaluate_run(
    run_dir: Path,
    test: DatasetInfo,
    out_dir: Path,
    *,
    image_size: Any,
    device: str,
    max_scenes: int | None,
    lpips_weights: str | None,
    progress: bool,
    refine_steps: int = 0,
    refine_lr: float | None = None,
) -> EvalResult:
    """Score the model in ``run_dir`` on ``test`` and write the result to ``out_dir``.

    The unit of work of :meth:`Context.evaluation` and of a Ray evaluation task;
    ``refine_steps`` and ``refine_lr`` as :func:`benchmark.evaluate.evaluate_model`.
    """
    ds = adapter.open_dataset(test.path, image_size=image_size)
    model = adapter.load_model(run_dir, device=device)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(
            total=len(ds) if max_scenes is None else min(len(ds), max_scenes),
            desc=f"eval {test.preset}",
            dynamic_ncols=True,
            **progress_kwargs(),
        )
    try:
        res = evaluate_model(
            model,
            ds,
            input_view=0,
            max_scenes=max_scenes,
            lpips_weights=lpips_weights,
            progress=(lambda i, n: bar.update(1)) if bar is not None else None,
            refine_steps=refine_steps,
            refine_lr=refine_lr,
        )
    finally:
        if bar is not None:
            bar.close()
    write_eval(Path(out_dir), res)
    return res


def read_eval(d: Path) -> EvalResult | None:
    """The cached evaluation in folder ``d`` (its ``result.json``), None if absent or unreadable."""
    try:
        return EvalResult.from_json(json.loads((d / "result.json").read_text()))
    except (OSError, ValueError, KeyError):
        return None


def write_eval(d: Path, res: EvalResult) -> None:
    """Cache ``res`` in folder ``d``: ``sample.npz`` (if any), then ``result.json``, which
    marks the entry complete (both atomic)."""
    d.mkdir(parents=True, exist_ok=True)
    if res.sample is not None:
        buf = io.BytesIO()
        np.savez_compressed(buf, **res.sample)
        atomic_write_bytes(d / "sample.npz", buf.getvalue())
    write_json(d / "result.json", res.to_json())  # written last: marks the entry complete
