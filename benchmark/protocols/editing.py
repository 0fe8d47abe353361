"""The ``editing`` protocol: scene editing measured against re-rendered ground truth.

Where this sits: ``benchmark run editing`` -> :func:`run_editing`. It trains (or reuses,
through :class:`benchmark.context.Context`'s model cache, ``<out>/runs/<key>/``, shared with
the table protocols) sVORF and its density-weighted-composition ablation on each preset's
training split, generates the preset's
manipulation split (``generate --split manip``: per scene one object moved by a recorded
offset, and the scene with another scene's background, every variant re-rendered by
Cycles), and scores the edits the way uORF does (KovenYu/uORF
``scripts/eval_scene_manip.sh``, ``models/uorf_manip_model.py``):

- *move*: encode view 0, pick the foreground slot whose arg-max mask has the highest
  IoU with ``_mask_for_moving`` in view 0, translate its sample points by the movement
  file's (dx, dy) and render every view; PSNR / SSIM / LPIPS against the moved ground
  truth (``_moved.png``), ARI / FG-ARI of the rendered segmentation against the moved
  instance ids.
- *background*: swap sVORF's background slot (the last) for the one encoded from
  ``_providing_bg.png`` of view 0 (the donor scene seen from this camera) and render every
  view; the same metrics against ``_changed.png`` and its instance ids.
- *no edit*: the unedited render scored against the same edited ground truth: the floor
  an edit has to beat (rows with ``source: baseline``).

All views are scored (view 0 included), as uORF's manipulation test does. Scenes whose
moved object is not visible in view 0 have no move (counted in the row's ``n_scenes``).

The run options of the table protocols apply: ``--datasets`` keeps some of
:func:`editing_datasets`, ``--train-minutes`` (with ``--steps`` and ``--seed``) is part of the
model key, so ``benchmark run segmentation`` and ``benchmark run editing`` with the same
``--out``, ``--scale``, ``--seed``, ``--steps`` and ``--train-minutes`` use the same trained
sVORF; ``--no-train`` trains nothing and leaves the rows of untrained models null with the
reason ``not_trained``.
Presets without rooms have one background for every scene, so their background edit is
scored against a "changed" view that equals the original: the report says so.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmark import adapter
from benchmark.context import Context, ModelRecord
from benchmark.datasets import DatasetInfo
from benchmark.generator_bridge import DatasetUnavailable
from benchmark.jobs import ModelJob
from benchmark.log import log
from benchmark.metrics import ari_score, fg_ari_score, lpips_or_null, psnr, ssim
from benchmark.report import stable_hash, write_json
from benchmark.rows import Row
from scenefmt import MANIP_SPLIT

__all__ = ["EDITING_MODELS", "EDIT_METRICS", "EDIT_TABLES", "editing_datasets", "run_editing"]

#: Bumped when what an editing evaluation computes changes (its cache key).
EDIT_EVAL_VERSION = "1"
#: Report table per edit.
EDIT_TABLES = {"move": "editing: move one object", "background": "editing: change background"}
#: (row name, model variant) of the models scored.
EDITING_MODELS = (("sVORF", "full"), ("sVORF (density-weighted)", "density_weighted"))
EDIT_METRICS = ("psnr", "ssim", "lpips", "ari", "fg_ari")
#: Metrics where higher is better (LPIPS: lower).
_HIGHER = {"psnr": True, "ssim": True, "lpips": False, "ari": True, "fg_ari": True}


def editing_datasets(scale: str) -> tuple[str, ...]:
    """Presets the protocol scores at ``scale`` (smoke: CLEVR-567 only, to stay in minutes)."""
    return ("clevr567",) if scale == "smoke" else ("clevr567", "room-chair")


def _scores(pred_rgb, pred_labels, gt_rgb, gt_ids, lpips_weights) -> tuple[dict, str | None]:
    """Per-scene means over views: image metrics and ARI (fractions; percent later)."""
    out = {
        "psnr": float(psnr(pred_rgb, gt_rgb).mean()),
        "ssim": float(ssim(pred_rgb, gt_rgb).mean()),
        "ari": float(ari_score(pred_labels, gt_ids).mean()),
        "fg_ari": float(torch.nanmean(fg_ari_score(pred_labels, gt_ids))),
    }
    lp, why = lpips_or_null(pred_rgb, gt_rgb, weights_path=lpips_weights)
    if lp is not None:
        out["lpips"] = float(lp.mean())
    return out, why


def evaluate_editing(
    rec: ModelRecord, test: DatasetInfo, device: str, max_scenes: int | None,
    lpips_weights: str | None, sample_dir: Path | None = None,
) -> dict[str, Any]:  # fmt: skip
    """Score ``rec``'s edits on manipulation split ``test`` (module docstring).

    Returns:
        ``{"per_scene": {"move"|"background": {"edit"|"no_edit": {metric: [values]}}},
        "n_scenes": {...}, "lpips_reason": str|None}``; the first scene's images go to
        ``sample_dir/sample.npz`` when given (the figures).
    """
    hw = rec.model_config.get("image_size")
    ds = adapter.open_dataset(test.path, image_size=hw)
    model = adapter.load_model(rec.run_dir, device=device)
    n = len(ds) if max_scenes is None else min(len(ds), max_scenes)
    acc: dict[str, dict[str, dict[str, list[float]]]] = {
        e: {"edit": {}, "no_edit": {}} for e in EDIT_TABLES
    }
    lpips_reason = None
    for pos in range(n):
        truth = adapter.read_manip_truth(test.path, ds.scene_ids[pos], ds.image_hw)
        res = adapter.edit_scene(model, ds, pos, truth)
        pairs = {"background": (res.changed, res.changed_labels, truth.changed, truth.changed_ids)}
        if res.moved is not None:
            pairs["move"] = (res.moved, res.moved_labels, truth.moved, truth.moved_ids)
        for edit, (rgb, labels, gt, gt_ids) in pairs.items():
            for kind, (p, lab) in (
                ("edit", (rgb, labels)),
                ("no_edit", (res.recon, res.recon_labels)),
            ):
                vals, why = _scores(p, lab, gt, gt_ids, lpips_weights)
                lpips_reason = lpips_reason or why
                for k, x in vals.items():
                    acc[edit][kind].setdefault(k, []).append(x)
        if pos == 0 and sample_dir is not None and res.moved is not None:
            sample_dir.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(
                sample_dir / "sample.npz", input=ds[pos].images.numpy(), moved=res.moved.numpy(),
                moved_gt=truth.moved.numpy(), changed=res.changed.numpy(),
                changed_gt=truth.changed.numpy(), providing=truth.providing.numpy(),
            )  # fmt: skip
    return {"per_scene": acc, "n_scenes": n, "lpips_reason": lpips_reason}


def _aggregate(values: dict[str, list[float]], lpips_reason: str | None):
    metrics: dict[str, float | None] = {}
    reasons: dict[str, str] = {}
    for m in EDIT_METRICS:
        xs = [x for x in values.get(m, []) if isinstance(x, float) and math.isfinite(x)]
        if not xs:
            metrics[m] = None
            reasons[m] = "lpips_unavailable" if m == "lpips" and lpips_reason else "no_scene_scored"
            continue
        v = float(np.mean(xs))
        metrics[m] = v * 100.0 if m in ("ari", "fg_ari") else v
    return metrics, reasons


def _row(table, model, dataset, source, variant, metrics, reasons, n, extra) -> dict[str, Any]:
    return Row(
        table=table, model=model, dataset=dataset, source=source, metrics=metrics,
        null_reasons=reasons, variant=variant, n_scenes=int(n), extra=extra,
    ).to_dict()  # fmt: skip


def _null_rows(name, variant, dataset, reason, extra) -> list[dict[str, Any]]:
    """One row per edit table with every metric null for ``reason``."""
    return [
        _row(table, name, dataset, "measured", variant, dict.fromkeys(EDIT_METRICS),
             dict.fromkeys(EDIT_METRICS, reason[:300]), 0, extra)
        for table in EDIT_TABLES.values()
    ]  # fmt: skip


def _models_note(ctx: Context) -> str | None:
    """Which models this run trained and which it found in the cache (by run key)."""
    if not ctx.models:
        return None
    parts = [
        f"{r.job.variant} on {r.job.train_preset} (run {r.key}): "
        + ("reused, trained earlier with the same key under this --out" if r.reused
           else "trained in this run")
        for r in ctx.models.values()
    ]  # fmt: skip
    return "Models: " + "; ".join(parts) + "."


def _beats(edit: dict[str, Any], floor: dict[str, Any]) -> dict[str, bool | None]:
    out: dict[str, bool | None] = {}
    for m, hi in _HIGHER.items():
        a, b = edit.get(m), floor.get(m)
        out[m] = None if a is None or b is None else (a > b if hi else a < b)
    return out


def _figure(path: Path, title: str, sample: dict[str, np.ndarray], edit: str) -> str:
    """Views as rows; columns input, edited ground truth, edited render, |difference|."""
    from matplotlib import pyplot as plt

    pred, gt = sample[edit], sample[f"{edit}_gt"]
    v = pred.shape[0]
    fig, axes = plt.subplots(v, 4, figsize=(8, 2 * v + 0.6), squeeze=False)
    cols = ("input (view 0)", "edited ground truth", "edited render", "|difference|")
    for i in range(v):
        diff = np.abs(pred[i] - gt[i]).mean(0)
        ims = (sample["input"][0].transpose(1, 2, 0), gt[i].transpose(1, 2, 0),
               pred[i].transpose(1, 2, 0), diff)  # fmt: skip
        for j, im in enumerate(ims):
            ax = axes[i][j]
            ax.imshow(np.clip(im, 0, 1), cmap="magma" if j == 3 else None, vmin=0, vmax=1)
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(cols[j], fontsize=8)
        axes[i][0].set_ylabel(f"view {i}", fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path.name


def run_editing(ctx: Context) -> Path:
    """``benchmark run editing``: rows per (edit, model, dataset) plus the "no edit" floors."""
    report = ctx.base_report()
    rows: list[dict[str, Any]] = []
    figures: list[str] = []
    failed: list[str] = []
    not_trained: list[str] = []
    verdict_notes: list[str] = []
    datasets, left_out = ctx.select_datasets(editing_datasets(ctx.scale))  # before any work
    if left_out:
        ctx.notes.append(
            f"Datasets left out by --datasets {','.join(ctx.only_datasets or ())}: "
            f"{', '.join(left_out)} (no rows of theirs are in this report)."
        )
    ctx.report_dir.mkdir(parents=True, exist_ok=True)
    for dataset in datasets:
        try:
            if ctx.data_source != "generator":
                raise DatasetUnavailable(
                    f"the manipulation split needs the Blender generator (--data-source "
                    f"generator), not {ctx.data_source!r}"
                )
            test = ctx.dataset(dataset, MANIP_SPLIT)
        except (DatasetUnavailable, ValueError) as err:
            why = f"dataset_unavailable: {err}"[:300]
            failed.append(f"{dataset}: {err}")
            for name, variant in EDITING_MODELS:
                rows.extend(_null_rows(name, variant, dataset, why, {}))
            continue
        for name, variant in EDITING_MODELS:
            job = ModelJob(variant, dataset)
            try:
                rec = ctx.model(job, train=ctx.may_train(job))
                if rec is None:  # --no-train and no finished cached run (as the tables)
                    why = ctx.not_trained_why(job)
                    not_trained.append(f"{name} / {dataset}")
                    rows.extend(_null_rows(name, variant, dataset, f"not_trained: {why}",
                                           {"train_dataset": f"{dataset}/train"}))  # fmt: skip
                    continue
                ekey = stable_hash({"v": EDIT_EVAL_VERSION, "model": rec.key,
                                    "test": test.fingerprint, "max": ctx.settings.eval_scenes,
                                    "lpips": ctx.lpips_available()})  # fmt: skip
                d = ctx.out / "evals" / f"editing-{ekey}"
                try:
                    res = json.loads((d / "result.json").read_text())
                except (OSError, ValueError):
                    log(f"editing: scoring {variant} on {test.name}")
                    t = time.perf_counter()
                    res = evaluate_editing(rec, test, ctx.device, ctx.settings.eval_scenes,
                                           ctx.lpips_weights, d)  # fmt: skip
                    ctx.timers["evaluation"] += time.perf_counter() - t
                    write_json(d / "result.json", res)
            except Exception as err:  # noqa: BLE001 - one failing model must not lose the others
                why = f"{type(err).__name__}: {err}".splitlines()[0]
                failed.append(f"{name} / {dataset}: {why}")
                rows.extend(_null_rows(name, variant, dataset, f"failed: {why}", {"failed": why}))
                continue
            for edit, table in EDIT_TABLES.items():
                per = res["per_scene"][edit]
                n_edit = len(per["edit"].get("psnr", []))
                m_edit, r_edit = _aggregate(per["edit"], res["lpips_reason"])
                m_floor, r_floor = _aggregate(per["no_edit"], res["lpips_reason"])
                beats = _beats(m_edit, m_floor)
                extra = {"train_dataset": f"{dataset}/train", "run_key": rec.key,
                         "test_fingerprint": test.fingerprint}  # fmt: skip
                rows.append(_row(table, name, dataset, "measured", variant, m_edit, r_edit,
                                 n_edit, {**extra, "beats_no_edit": beats}))  # fmt: skip
                rows.append(_row(table, f"no edit ({name})", dataset, "baseline", variant,
                                 m_floor, r_floor, n_edit, extra))  # fmt: skip
                judged = {k: b for k, b in beats.items() if b is not None}
                word = ("beats" if judged and all(judged.values()) else
                        "does NOT beat" if judged else "cannot be compared with")  # fmt: skip
                per_metric = ", ".join(f"{k} {'yes' if b else 'no'}" for k, b in judged.items())
                verdict_notes.append(
                    f"{table} / {name} / {dataset}: the edit {word} its no-edit floor "
                    f"({per_metric})."
                )
            sample = d / "sample.npz"
            if sample.is_file():
                with np.load(sample) as z:
                    s = {k: z[k] for k in z.files}
                for edit, key in (("move", "moved"), ("background", "changed")):
                    fname = f"{edit}_{variant}_{dataset}.png"
                    figures.append(_figure(ctx.report_dir / fname,
                                           f"{EDIT_TABLES[edit]}: {name} on {dataset} "
                                           f"{MANIP_SPLIT} scene 0 ({ctx.scale})", s, key))  # fmt: skip
        if dataset.startswith("clevr"):
            ctx.notes.append(
                f"{dataset} has one background (a grey floor) for every scene, so its "
                "background edit is scored against views whose background did not change."
            )
    if failed:
        report["status"] = "partial"
        ctx.notes.insert(0, "Rows without numbers: " + "; ".join(failed))
    if not_trained:
        report["status"] = "partial"
        ctx.notes.append(
            "Rows not trained in this run (--no-train or --train-only; metrics null, "
            "reason 'not_trained'): " + "; ".join(not_trained)
        )
    models = _models_note(ctx)
    if models:
        ctx.notes.append(models)
    ctx.notes.extend(verdict_notes)
    ctx.notes.append(
        "Every view is scored (view 0, the encoder's input, included), as uORF's manipulation "
        "test does; 'no edit' rows score the unedited render against the edited ground truth."
    )
    ctx.notes.extend(ctx.settings.notes)
    report["rows"] = rows
    report["verdicts"] = []
    report["figures"] = figures
    return ctx.finish(report)
