"""Scoring a trained model (or a chance baseline) on a test split.

Where this sits: protocols call :func:`evaluate_model` once per (model, test
split) and :func:`evaluate_baselines` once per test split; both return
:class:`EvalResult` whose ``metrics`` are aggregated over scenes in report units
(ARI family in percent, as the paper prints). The metric functions come from
:mod:`benchmark.metrics`; the model is reached only through :mod:`benchmark.adapter`.

Protocol (paper 4.1/4.2): view ``input_view`` (0) is the model's input; ARI and
FG-ARI are scored on it, NV-ARI on the other (novel) views, ARI*/FG-ARI* over all
views; PSNR / SSIM / LPIPS and depth errors on the novel views.

Scene-shuffle control (not in the paper): a model whose foreground slots tile 3D
space in a fixed pattern scores a high FG-ARI without looking at the image, since
CLEVR objects rarely share a tile. So each test scene i is also rendered with the
slots of scene (i + 1) mod n (encoded from that scene's input view, placed in scene
i's input-camera frame) and scored on the input view: ``ari_shuffled``,
``fg_ari_shuffled`` and ``fg_ari_gain = fg_ari - fg_ari_shuffled``. A decomposition
loses most of its FG-ARI with another scene's slots; a spatial tiling keeps it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from benchmark import adapter
from benchmark.metrics import (
    ari_score,
    depth_errors,
    fg_ari_score,
    lpips_or_null,
    psnr,
    segmentation_metrics,
    ssim,
)

__all__ = [
    "CONTROL_KEYS",
    "EVAL_VERSION",
    "LPIPS_REASON",
    "EvalResult",
    "SceneScores",
    "aggregate",
    "evaluate_baselines",
    "evaluate_model",
    "score_scene",
]

#: Bumped when what :func:`evaluate_model` / :func:`evaluate_baselines` compute changes
#: (part of the evaluation cache key and of the finished-row context, not of the model
#: key: trained runs stay valid). "2": the scene-shuffle control.
EVAL_VERSION = "2"

SEG_KEYS = ("ari", "fg_ari", "nv_ari", "nv_fg_ari", "nv_ari_last", "ari_all", "fg_ari_all")
#: The scene-shuffle control (module docstring), percent like the ARI family.
CONTROL_KEYS = ("ari_shuffled", "fg_ari_shuffled", "fg_ari_gain")
#: Why the control is null on a split of one scene (there is no other scene's slots).
CONTROL_REASON = "needs_two_scenes: the control renders a scene with another test scene's slots"
IMAGE_KEYS = ("psnr", "ssim", "lpips")
DEPTH_KEYS = ("depth_abs_rel", "depth_rmse")
#: Short reason code for LPIPS; the full explanation (paths searched) goes into notes.
LPIPS_REASON = "lpips_unavailable"


@dataclass
class EvalResult:
    """Aggregated scores of one (model or baseline, test split).

    Attributes:
        metrics: metric -> mean over scenes (report units) or None.
        null_reasons: metric -> why it is None.
        n_scenes: scenes scored.
        nan_counts: metric -> scenes skipped as NaN (e.g. no foreground in a view).
        per_scene: metric -> list of per-scene values (None for NaN).
        wall_s: evaluation time.
        details: free-form notes (e.g. the full LPIPS reason).
        sample: arrays of the first scene for the qualitative figure (not in JSON).
    """

    metrics: dict[str, float | None]
    null_reasons: dict[str, str]
    n_scenes: int
    nan_counts: dict[str, int] = field(default_factory=dict)
    per_scene: dict[str, list[float | None]] = field(default_factory=dict)
    wall_s: float = 0.0
    details: dict[str, str] = field(default_factory=dict)
    sample: dict[str, np.ndarray] | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            "metrics": self.metrics,
            "null_reasons": self.null_reasons,
            "n_scenes": self.n_scenes,
            "nan_counts": self.nan_counts,
            "per_scene": self.per_scene,
            "wall_s": self.wall_s,
            "details": self.details,
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> EvalResult:
        return cls(
            metrics=d["metrics"],
            null_reasons=d["null_reasons"],
            n_scenes=d["n_scenes"],
            nan_counts=d.get("nan_counts", {}),
            per_scene=d.get("per_scene", {}),
            wall_s=d.get("wall_s", 0.0),
            details=d.get("details", {}),
        )


_PERCENT = set(SEG_KEYS) | set(CONTROL_KEYS)


def aggregate(
    per_scene: dict[str, list[float]], reasons: dict[str, str] | None = None
) -> tuple[dict[str, float | None], dict[str, str], dict[str, int], dict[str, list[float | None]]]:
    """Mean over scenes ignoring NaN; ARI family scaled to percent.

    Returns:
        ``(metrics, null_reasons, nan_counts, per_scene_json)``.
    """
    reasons = dict(reasons or {})
    metrics: dict[str, float | None] = {}
    nulls: dict[str, str] = {}
    nans: dict[str, int] = {}
    scenes_json: dict[str, list[float | None]] = {}
    for k, values in per_scene.items():
        arr = np.asarray(values, dtype=np.float64)
        scale = 100.0 if k in _PERCENT else 1.0
        finite = np.isfinite(arr)
        nans[k] = int((~finite).sum())
        scenes_json[k] = [float(v * scale) if f else None for v, f in zip(arr, finite, strict=True)]
        if finite.any():
            metrics[k] = float(arr[finite].mean() * scale)
        else:
            metrics[k] = None
            nulls[k] = reasons.get(
                k,
                "no_finite_value (NaN/inf in every scene: e.g. no foreground pixels, or "
                "identical images giving PSNR inf)",
            )
    for k, why in reasons.items():
        if k not in metrics:
            metrics[k] = None
            nulls[k] = why
    return metrics, nulls, nans, scenes_json


@dataclass
class SceneScores:
    """What :func:`score_scene` measured on one scene.

    Attributes:
        values: metric -> this scene's value (ARI family as a fraction, not yet percent),
            in the order computed.
        null_reasons: metric -> why it has no value here (``lpips`` without weights).
        details: free-form notes (the full LPIPS reason).
    """

    values: dict[str, float]
    null_reasons: dict[str, str] = field(default_factory=dict)
    details: dict[str, str] = field(default_factory=dict)

    def append_to(self, per_scene: dict[str, list[float]]) -> None:
        """Append each of :attr:`values` to its metric's list in ``per_scene`` (the input
        of :func:`aggregate`)."""
        for k, v in self.values.items():
            per_scene.setdefault(k, []).append(v)


def score_scene(
    *,
    pred_rgb: Tensor | None,
    pred_depth: Tensor | None,
    pred_labels: Tensor,
    truth: adapter.SceneTruth,
    input_view: int,
    lpips_weights: str | None = None,
    with_lpips: bool = True,
) -> SceneScores:
    """Score one scene's prediction against its ground truth.

    Segmentation (:data:`SEG_KEYS`) from ``pred_labels`` always; PSNR / SSIM (and LPIPS
    when ``with_lpips``) on the novel views when ``pred_rgb`` is given; depth errors on
    the novel views when ``pred_depth`` is given.

    Args:
        pred_rgb: [V, 3, H, W] predicted views, or None.
        pred_depth: [V, H, W] predicted planar depth, or None.
        pred_labels: int64 [V, H, W] predicted segmentation labels.
        truth: the scene's ground truth (:func:`benchmark.adapter.ground_truth`).
        input_view: the view the model sees (not a novel view).
        lpips_weights: optional LPIPS weight file.
        with_lpips: compute LPIPS (callers pass False once it proved unavailable).

    Returns:
        The scene's :class:`SceneScores`; LPIPS without weights is a null reason
        (:data:`LPIPS_REASON`, the full reason in ``details``), not a value.
    """
    values: dict[str, float] = {}
    reasons: dict[str, str] = {}
    details: dict[str, str] = {}
    seg = segmentation_metrics(pred_labels[None], truth.instances[None], input_view=input_view)
    for k in SEG_KEYS:
        values[k] = float(seg[k][0])
    n_views = truth.images.shape[0]
    novel = [v for v in range(n_views) if v != input_view]
    if pred_rgb is not None and novel:
        p, g = pred_rgb[novel].float(), truth.images[novel].float()
        values["psnr"] = float(psnr(p, g).mean())
        values["ssim"] = float(ssim(p, g).mean())
        if with_lpips:
            lp, why = lpips_or_null(p, g, weights_path=lpips_weights)
            if lp is None:
                reasons["lpips"] = LPIPS_REASON
                details["lpips"] = str(why)
            else:
                values["lpips"] = float(lp.mean())
    if pred_depth is not None and novel:
        err = depth_errors(pred_depth[novel].float(), truth.depth_z[novel].float())
        values["depth_abs_rel"] = float(torch.nanmean(err["abs_rel"]))
        values["depth_rmse"] = float(torch.nanmean(err["rmse"]))
    return SceneScores(values, reasons, details)


def _score_control(
    labels: Tensor, truth: adapter.SceneTruth, input_view: int, acc: dict[str, list[float]]
) -> None:
    """Append the control's scores of one scene to ``acc``.

    Args:
        labels: int64 [1, H, W] input-view labels rendered with another scene's slots.
        truth: the scene's ground truth (its input view is scored).
        input_view: the input view.
        acc: per-scene lists; ``fg_ari`` of this scene must already be in it.
    """
    gt = truth.instances[input_view : input_view + 1]
    if labels.shape != gt.shape:
        raise ValueError(
            f"predict_scene(input_view_only=True) returned labels {tuple(labels.shape)}, "
            f"expected {tuple(gt.shape)} like the input view's ground truth"
        )
    ari_s = float(ari_score(labels, gt)[0])
    fg_s = float(fg_ari_score(labels, gt)[0])
    acc.setdefault("ari_shuffled", []).append(ari_s)
    acc.setdefault("fg_ari_shuffled", []).append(fg_s)
    # NaN exactly when fg_ari is NaN (no foreground in the input view: same ground truth).
    acc.setdefault("fg_ari_gain", []).append(acc["fg_ari"][-1] - fg_s)


def _scene_indices(dataset: Any, max_scenes: int | None) -> list[int]:
    n = len(dataset)
    return list(range(n if max_scenes is None else min(n, max_scenes)))


def evaluate_model(
    model: Any,
    dataset: Any,
    *,
    input_view: int = 0,
    max_scenes: int | None = None,
    lpips_weights: str | None = None,
    progress: Callable[[int, int], None] | None = None,
    refine_steps: int = 0,
    refine_lr: float | None = None,
) -> EvalResult:
    """Score ``model`` on every scene of ``dataset`` (segmentation, image and depth metrics).

    Besides the metrics of :data:`SEG_KEYS`, :data:`IMAGE_KEYS` and :data:`DEPTH_KEYS`
    it computes the scene-shuffle control :data:`CONTROL_KEYS` (module docstring): scene
    ``idx[j]`` rendered (input view only) with the slots of scene ``idx[(j + 1) % n]``,
    ``n`` the number of scenes scored; null with a reason when ``n < 2``.

    Args:
        model: from :func:`benchmark.adapter.load_model`.
        dataset: from :func:`benchmark.adapter.open_dataset` (the test split).
        input_view: the view the model sees.
        max_scenes: score only the first scenes (None = all).
        lpips_weights: optional LPIPS weight file.
        progress: optional callback ``(done, total)``.
        refine_steps: test-time slot refinement on the input view's pixels before every
            prediction, the control's included (``benchmark run --refine-slots``;
            :func:`benchmark.adapter.predict_scene`); 0 = the encoder's slots.
        refine_lr: the slots' Adam learning rate of that refinement (None: svorf's default,
            :func:`benchmark.adapter.default_refine_lr`).

    Returns:
        The aggregated :class:`EvalResult`; ``sample`` holds scene 0's arrays.
    """
    t0 = time.perf_counter()
    acc: dict[str, list[float]] = {}
    reasons: dict[str, str] = {}
    details: dict[str, str] = {}
    sample = None
    idx = _scene_indices(dataset, max_scenes)
    refine: dict[str, Any] = {}
    if refine_steps:
        refine = {"refine_steps": int(refine_steps), "refine_lr": refine_lr}
    if len(idx) < 2:
        reasons.update(dict.fromkeys(CONTROL_KEYS, CONTROL_REASON))
    for j, i in enumerate(idx):
        truth = adapter.ground_truth(dataset, i)
        pred = adapter.predict_scene(model, dataset, i, input_view=input_view, **refine)
        if pred.labels.shape != truth.instances.shape:
            raise ValueError(
                f"predict_scene returned labels {tuple(pred.labels.shape)}, expected "
                f"{tuple(truth.instances.shape)} like the ground truth"
            )
        scores = score_scene(
            pred_rgb=pred.rgb,
            pred_depth=pred.depth_z,
            pred_labels=pred.labels,
            truth=truth,
            input_view=input_view,
            lpips_weights=lpips_weights,
            with_lpips="lpips" not in reasons,
        )
        scores.append_to(acc)
        reasons.update(scores.null_reasons)
        details.update(scores.details)
        if len(idx) >= 2:
            ctrl = adapter.predict_scene(
                model,
                dataset,
                i,
                input_view=input_view,
                slots_scene=idx[(j + 1) % len(idx)],
                input_view_only=True,
                **refine,
            )
            _score_control(ctrl.labels, truth, input_view, acc)
        if sample is None:
            sample = {
                "gt_rgb": truth.images.permute(0, 2, 3, 1).numpy(),
                "pred_rgb": pred.rgb.permute(0, 2, 3, 1).numpy(),
                "pred_labels": pred.labels.numpy(),
                "gt_labels": truth.instances.numpy(),
                "pred_depth": pred.depth_z.numpy(),
                "gt_depth": truth.depth_z.numpy(),
            }
        if progress:
            progress(j + 1, len(idx))
    metrics, nulls, nans, scenes = aggregate(acc, reasons)
    return EvalResult(
        metrics, nulls, len(idx), nans, scenes, time.perf_counter() - t0, details, sample
    )


BASELINES = {
    "one_label": "chance: all pixels one label",
    "random_slots": "chance: uniform random slot per pixel",
    "spatial_blocks": "chance: K image blocks (2 rows)",
    "median_colour": "chance: flat median colour of the input view",
}


def _blocks(shape: torch.Size, num_slots: int) -> Tensor:
    """[V, H, W] labels of a fixed 2-row grid of ``num_slots`` blocks."""
    v, h, w = shape
    rows = 2 if num_slots > 1 else 1
    cols = max(1, math.ceil(num_slots / rows))
    y = torch.arange(h) * rows // h
    x = torch.arange(w) * cols // w
    lab = (y[:, None] * cols + x[None, :]).clamp_max(num_slots - 1)
    return lab.expand(v, h, w).contiguous()


def evaluate_baselines(
    dataset: Any,
    num_slots: int,
    *,
    input_view: int = 0,
    max_scenes: int | None = None,
    seed: int = 0,
    lpips_weights: str | None = None,
) -> dict[str, EvalResult]:
    """Chance baselines on a test split, scored exactly like a model.

    - ``one_label``: every pixel of every view gets label 0 (ARI 0, FG-ARI 0 unless a
      scene shows a single object).
    - ``random_slots``: each pixel gets a uniform random slot in ``[0, num_slots)``
      (seeded); the expected ARI of an uninformed labeling.
    - ``spatial_blocks``: each view cut into ``num_slots`` blocks (2 rows of
      ``ceil(K/2)`` columns), the same for every scene: an "areas, not objects"
      partition like the paper's w/o-NVS failure mode; with few large objects it
      scores well above 0, which is why a model must beat the best baseline.
    - ``median_colour``: novel views predicted as a flat image of the input view's
      per-channel median colour (PSNR/SSIM/LPIPS floor of an image-independent guess).

    Returns:
        baseline name -> :class:`EvalResult`.
    """
    gen = torch.Generator().manual_seed(seed)
    out: dict[str, dict[str, list[float]]] = {k: {} for k in BASELINES}
    reasons: dict[str, dict[str, str]] = {k: {} for k in BASELINES}
    details: dict[str, dict[str, str]] = {k: {} for k in BASELINES}
    t0 = time.perf_counter()
    idx = _scene_indices(dataset, max_scenes)

    def score(
        name: str, truth: adapter.SceneTruth, labels: Tensor, rgb: Tensor | None = None
    ) -> SceneScores:
        scores = score_scene(
            pred_rgb=rgb,
            pred_depth=None,
            pred_labels=labels,
            truth=truth,
            input_view=input_view,
            lpips_weights=lpips_weights,
            with_lpips="lpips" not in reasons[name],
        )
        reasons[name].update(scores.null_reasons)
        details[name].update(scores.details)
        return scores

    for i in idx:
        truth = adapter.ground_truth(dataset, i)
        shape = truth.instances.shape
        ones = torch.zeros(shape, dtype=torch.long)
        score("one_label", truth, ones).append_to(out["one_label"])
        rnd = torch.randint(0, num_slots, shape, generator=gen)
        score("random_slots", truth, rnd).append_to(out["random_slots"])
        blocks = _blocks(shape, num_slots)
        score("spatial_blocks", truth, blocks).append_to(out["spatial_blocks"])
        med = truth.images[input_view].flatten(1).median(dim=1).values  # [3]
        flat = med[None, :, None, None].expand_as(truth.images).contiguous()
        image = score("median_colour", truth, ones, flat)
        for k in IMAGE_KEYS:
            if k in image.values:
                out["median_colour"].setdefault(k, []).append(image.values[k])
    wall = (time.perf_counter() - t0) / len(BASELINES)
    results = {}
    for name in BASELINES:
        if name == "median_colour":
            keep = {k: v for k, v in reasons[name].items() if k in IMAGE_KEYS}
        else:
            keep = {}
        m, nulls, nans, scenes = aggregate(out[name], keep)
        results[name] = EvalResult(m, nulls, len(idx), nans, scenes, wall, details[name])
    return results


def finite_or_none(x: float | None) -> float | None:
    """``x`` if it is a finite float, else None."""
    return x if x is not None and math.isfinite(x) else None
