"""The ``tradeoff`` protocol's training curve: training PSNR (and held-out metrics)
against training wall time, read from a finished run's logs.

Where this sits: :func:`benchmark.protocols.tradeoff.run_tradeoff` calls
:func:`training_entry` with the trained weight set (if any); :func:`training_curve` reads
the svorf run folder's ``log.jsonl`` / ``eval.jsonl``. Nothing is trained here.
"""

from __future__ import annotations

import json
import math
import statistics
from pathlib import Path
from typing import Any

from benchmark.context import Context
from benchmark.protocols.tradeoff.common import WeightSet

__all__ = ["TRAIN_KNEE_DB", "TRAIN_SMOOTH", "training_curve", "training_entry"]


#: Log lines averaged (centred running mean) to smooth the per-batch training PSNR: at
#: least this many, or 1/20 of the log.
TRAIN_SMOOTH = 9
#: The knee of the training curve: the first time after which the smoothed PSNR stays
#: within this of its last value.
TRAIN_KNEE_DB = 0.5


def _read_jsonl(path: Path) -> list[dict[str, Any]]:
    """Lines of a JSON-lines file (svorf's log.jsonl / eval.jsonl); [] if missing; a
    truncated last line (a run being written) is skipped."""
    if not path.is_file():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:
            continue
    return out


def training_curve(run_dir: Path, run_key: str | None = None) -> dict[str, Any] | None:
    """Training PSNR (per batch, smoothed) and any held-out metrics against training wall time.

    Reads ``log.jsonl`` (step, wall_s, parts.psnr, loss) and ``eval.jsonl`` (step, wall_s,
    held-out metrics) of an svorf run folder; ``wall_s`` is training time (evaluation and
    checkpoint writes excluded, svorf.train). The front is the running best of the smoothed
    PSNR; the knee is the first point after which the smoothed PSNR stays within
    :data:`TRAIN_KNEE_DB` dB of its last value; the shipped default is the last point (the
    run's training budget).

    Returns:
        The curve dict, or None when the run has no usable log.
    """
    log = [
        r
        for r in _read_jsonl(run_dir / "log.jsonl")
        if isinstance(r.get("wall_s"), (int, float)) and isinstance(r.get("parts"), dict)
        and isinstance(r["parts"].get("psnr"), (int, float)) and math.isfinite(r["parts"]["psnr"])
    ]  # fmt: skip
    if len(log) < 2:
        return None
    psnr = [float(r["parts"]["psnr"]) for r in log]
    window = max(TRAIN_SMOOTH, len(psnr) // 20)
    h = window // 2
    smooth = [statistics.fmean(psnr[max(0, i - h) : i + h + 1]) for i in range(len(psnr))]
    points = [
        {
            "id": f"step {int(r['step'])}",
            "step": int(r["step"]),
            "wall_s": round(float(r["wall_s"]), 3),
            "train_psnr": round(p, 4),
            "train_psnr_smoothed": round(sm, 4),
            "loss": float(r["loss"]) if math.isfinite(float(r.get("loss", math.nan))) else None,
        }
        for r, p, sm in zip(log, psnr, smooth, strict=True)
    ]
    front, best = [], -math.inf
    for pt in points:
        if pt["train_psnr_smoothed"] > best:
            best = pt["train_psnr_smoothed"]
            front.append(pt["id"])
    end = points[-1]["train_psnr_smoothed"]
    k = len(points) - 1  # walk back while the curve stays within TRAIN_KNEE_DB of its end
    while k > 0 and points[k - 1]["train_psnr_smoothed"] >= end - TRAIN_KNEE_DB:
        k -= 1
    knee = points[k]
    last = points[-1]
    # Off the front: an earlier point reached at least the last point's smoothed PSNR.
    beaten_by = next(
        (
            pt["id"]
            for pt in points[:-1]
            if pt["train_psnr_smoothed"] >= last["train_psnr_smoothed"]
        ),
        None,
    )
    held = []
    for r in _read_jsonl(run_dir / "eval.jsonl"):
        if not isinstance(r.get("wall_s"), (int, float)):
            continue
        keep = {
            k: float(v)
            for k, v in r.items()
            if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        }
        held.append(keep)
    return {
        "kind": "training",
        "run": run_dir.name,
        "run_key": run_key,
        "x": "wall_s",
        "y": "train_psnr_smoothed",
        "y_better": "higher",
        "smoothing_lines": window,
        "points": points,
        "front": front,
        "knee": knee["id"],
        "shipped_default": {
            "id": points[-1]["id"],
            "on_front": points[-1]["id"] in front,
            "is_knee": points[-1]["id"] == knee["id"],
            "dominated_by": [] if last["id"] in front or beaten_by is None else [beaten_by],
        },
        "held_out": held,
        "note": (
            f"Training-batch PSNR (the fine pass's MSE on the sampled rays, running mean over "
            f"{window} log lines) against training wall time (evaluation and checkpoint "
            f"writes excluded). Knee: the first point after which the smoothed PSNR stays "
            f"within {TRAIN_KNEE_DB:g} dB of its last value "
            f"({knee['wall_s'] / 60:.1f} of {points[-1]['wall_s'] / 60:.1f} min, "
            f"step {knee['step']} of {points[-1]['step']}). The shipped default is the run's "
            "budget, its last point. "
            + (
                f"held_out: the {len(held)} held-out evaluations of eval.jsonl."
                if held
                else "The run has no eval.jsonl, so no held-out metric over time."
            )
        ),
    }


def training_entry(ws: WeightSet | None, ctx: Context) -> dict[str, Any]:
    """The training curve's entry of ``report["curves"]``: :func:`training_curve` of the
    trained weight set's run, or ``absent`` with the reason (no trained run, no usable log)."""
    if ws is None or ws.run_dir is None:
        return {
            "kind": "training",
            "absent": (
                "no finished benchmark run of the clevr567 'full' model at this scale under "
                f"{ctx.out / 'runs'}: no training log to read"
            ),
        }
    c = training_curve(ws.run_dir, ws.run_key)
    if c is None:
        return {"kind": "training", "absent": f"run {ws.run_dir.name} has no usable log.jsonl"}
    return c
