"""The ``tradeoff`` protocol's render curve: evaluation render time per view against image
and segmentation quality, over the evaluation knobs of the model.

Where this sits: :func:`benchmark.protocols.tradeoff.run_tradeoff` calls
:func:`measure_render` on one weight set (the trained one where there is one), then
:func:`render_curves` for its fronts and :func:`render_note` for the report. Points are
scored with :mod:`benchmark.evaluate`'s functions against the ground truth of the
clevr567 test split when it is on disk and the weights are trained; otherwise against the
default render (on small analytic sphere scenes).
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import torch

from benchmark import adapter
from benchmark.context import Context
from benchmark.protocols.tradeoff.common import (
    TradeoffSettings,
    WeightSet,
    fmt_value,
    knobs_text,
    log_tradeoff,
)
from benchmark.protocols.tradeoff.pareto import curve_summary, timing_noise
from benchmark.report_row import Row
from scenefmt import Manifest, read_json

__all__ = [
    "EARLY_STOPS",
    "EVAL_COMBINED",
    "FINE_MIN_WEIGHTS",
    "REFINE_STEPS",
    "RenderPoint",
    "RenderScenes",
    "clip_flip",
    "format_render_table",
    "measure_render",
    "render_curves",
    "render_note",
    "render_points",
]

#: Thresholds swept for ``ModelConfig.eval_early_stop`` (transmittance).
EARLY_STOPS = (1e-3, 1e-2, 5e-2, 0.2)
#: Thresholds swept for ``ModelConfig.eval_fine_min_weight`` (coarse bin weight).
FINE_MIN_WEIGHTS = (0.01, 0.05, 0.1, 0.3)
#: Test-time slot refinement steps swept on trained weights (at svorf's default rate).
REFINE_STEPS = (20, 50)
#: The combination point of the render curve.
EVAL_COMBINED = {"eval_early_stop": 1e-2, "eval_fine_min_weight": 0.05}
_RENDER_QUALITY = ("psnr", "nv_ari", "nv_fg_ari", "fg_ari")
_RENDER_DIFF = ("rgb_max_err", "rgb_mean_err", "depth_mean_err", "labels_changed")


@dataclass
class RenderPoint:
    """One evaluation-render setting of the render curve."""

    knob: str
    setting: str
    overrides: dict[str, Any]
    reference: bool = False
    exact: bool = False
    """The default's config, timed as a point of its own (error 0 by construction)."""
    refine_steps: int = 0
    """Test-time slot refinement steps before rendering (0: the encoder's slots)."""
    times: list[float] = field(default_factory=list)

    @property
    def label(self) -> str:
        if self.reference or self.exact:
            return f"default ({self.setting})"
        return f"{self.knob}={self.setting}"


def render_points(cfg: Any, refine: bool = False) -> list[RenderPoint]:
    """The shipped default (``cfg``, eval knobs off) and every render-curve point: samples
    per ray, ``clip_to_box`` flipped, ``clip_floor_front`` flipped (where the floor is
    clipped), ``eval_early_stop``, ``eval_fine_min_weight`` (with fine samples only),
    :data:`EVAL_COMBINED` and, with ``refine`` (trained weights), test-time slot refinement
    at :data:`REFINE_STEPS`."""
    nc, nf = int(cfg.n_coarse), int(cfg.n_fine)
    pts = [
        RenderPoint(
            "default",
            f"{nc}+{nf} samples, clip_to_box={cfg.clip_to_box}, eval knobs off",
            {},
            reference=True,
        ),
        # The default again, built and timed separately: its speed-up is the timing noise.
        RenderPoint("default", "timed again", {}, exact=True),
    ]
    sp = [(max(1, nc // 2), nf // 2)] + ([(nc, 0)] if nf > 0 else []) + [(2 * nc, 2 * nf)]
    for c, f in sp:
        pts.append(RenderPoint("samples_per_ray", f"{c}+{f}", {"n_coarse": c, "n_fine": f}))
    pts.append(clip_flip(cfg))
    if cfg.clip_to_box and cfg.clip_floor_z is not None:
        front = not cfg.clip_floor_front
        pts.append(RenderPoint("clip_floor_front", str(front), {"clip_floor_front": front}))
    for v in EARLY_STOPS:
        pts.append(RenderPoint("eval_early_stop", fmt_value(v), {"eval_early_stop": v}))
    if nf > 0:
        for v in FINE_MIN_WEIGHTS:
            pts.append(
                RenderPoint("eval_fine_min_weight", fmt_value(v), {"eval_fine_min_weight": v})
            )
        pts.append(RenderPoint("combined", knobs_text(EVAL_COMBINED), dict(EVAL_COMBINED)))
    if refine:
        for n in REFINE_STEPS:
            pts.append(RenderPoint("refine_slots", str(n), {}, refine_steps=n))
    return pts


def clip_flip(cfg: Any) -> RenderPoint:
    """The ``clip_to_box`` point: the shipped setting flipped. Turning the box off also turns
    off what only exists inside it (``box_z``, ``clip_floor_z``, ``clip_floor_front``), so
    that the point is a valid config; its setting names them."""
    if not cfg.clip_to_box:
        return RenderPoint("clip_to_box", "True", {"clip_to_box": True})
    inside = {
        "box_z": None,
        "clip_floor_z": None,
        "clip_floor_front": False,
    }
    dropped = [k for k, off in inside.items() if getattr(cfg, k) != off]
    setting = "False" + (f" ({', '.join(dropped)} off with it)" if dropped else "")
    return RenderPoint("clip_to_box", setting, {"clip_to_box": False, **inside})


@dataclass
class RenderScenes:
    """What the render curve renders: a split, its scene positions and how it is scored."""

    dataset: Any
    scenes: list[int]
    name: str
    ground_truth: bool
    why_no_truth: str | None = None


def _render_scenes(
    ctx: Context, ws: WeightSet, settings: TradeoffSettings, tmp: Path
) -> RenderScenes:
    """The clevr567 test split at this scale when ``ws`` is trained on clevr567 and the split
    is complete on disk (scored against its ground truth); otherwise a small analytic
    sphere split written to ``tmp`` (scored against the default render only)."""
    from benchmark.datasets import dataset_dir, ensure_dataset, source_of

    n = settings.render_scenes
    root = dataset_dir(ctx.data, ctx.scale, "clevr567", "test")
    why = "init weights: no trained model to score against ground truth"
    if ws.name == "trained":
        why = f"no complete clevr567 test split at {root}"
        try:
            complete = _usable_as_found(root, ctx)
        except ValueError as err:  # another resolution
            complete, why = False, str(err)
        if complete:
            source = source_of(Manifest.from_json(read_json(root / "manifest.json")))
            info = ensure_dataset(
                ctx.data,
                ctx.settings,
                "clevr567",
                "test",
                source=source,
                seed=ctx.seeds["data"],
                progress=False,
            )  # usable as found: nothing is generated
            ctx.datasets[("clevr567", "test")] = info
            ds = adapter.open_dataset(info.path)
            return RenderScenes(ds, list(range(min(n, len(ds)))), info.name, True)
    split = adapter.write_synthetic_split(
        tmp / "render_scenes",
        n_scenes=n,
        resolution=ctx.settings.resolution,
        seed=ctx.seeds["eval"],
        n_views=2,
        preset="synthetic",
        split="test",
    )
    ds = adapter.open_dataset(split)
    return RenderScenes(
        ds,
        list(range(len(ds))),
        f"svorf.synthetic spheres ({n} scenes x 2 views, {ctx.settings.resolution}px)",
        False,
        why,
    )


def _usable_as_found(root: Path, ctx: Context) -> bool:
    """Whether :func:`benchmark.datasets.ensure_dataset` would use the split at ``root``
    without generating anything (:func:`benchmark.datasets.split_state` for the source
    that made it)."""
    from benchmark.datasets import source_of, split_state

    if not (root / "manifest.json").is_file():
        return False
    raw = read_json(root / "manifest.json")
    try:
        manifest = Manifest.from_json(raw)
    except ValueError:
        return False  # not a manifest: split_state finds the split unusable
    source = source_of(manifest)
    state = split_state(
        ctx.data, ctx.settings, "clevr567", "test", source=source, seed=ctx.seeds["data"]
    )
    return state.usable


def _build(ws: WeightSet, cfg: Any) -> Any:
    from svorf.model import SVORF

    m = SVORF(cfg)
    m.load_state_dict(ws.state)
    return m.eval()


def measure_render(
    ctx: Context, ws: WeightSet, settings: TradeoffSettings, tmp: Path
) -> tuple[list[dict[str, Any]], RenderScenes, Any]:
    """Render the scenes with every :func:`render_points` setting, timed interleaved.

    Returns:
        (rows, scenes, shipped config): one report row per point, the default first.
    """
    from benchmark.evaluate import aggregate, score_scene
    from benchmark.tools import speedbench

    shipped = ws.shipped if ws.shipped is not None else _shipped(ctx)
    scenes = _render_scenes(ctx, ws, settings, tmp)
    # Refinement only where it can be scored: trained weights against the ground truth.
    points = render_points(shipped, refine=scenes.ground_truth)
    models = [_build(ws, shipped.replace(**p.overrides)).to(ctx.device) for p in points]
    preds: list[list[Any]] = [[] for _ in points]
    for m in models:  # warm-up (allocator, caches), untimed
        adapter.predict_scene(m, scenes.dataset, scenes.scenes[0])

    def render(j: int) -> None:
        n = points[j].refine_steps
        out = [
            adapter.predict_scene(models[j], scenes.dataset, i, refine_steps=n)
            for i in scenes.scenes
        ]
        if not preds[j]:  # the first repeat's renders are the ones scored
            preds[j] = out

    times = speedbench.time_interleaved(
        [partial(render, j) for j in range(len(points))],
        repeats=settings.render_repeats,
        on_repeat=lambda r, _: log_tradeoff(
            f"render repeat {r + 1}/{settings.render_repeats} done ({len(points)} points)"
        ),
    )
    for p, t in zip(points, times, strict=True):
        p.times.extend(t)
    views = sum(int(o.rgb.shape[0]) for o in preds[-1])
    truths = [adapter.ground_truth(scenes.dataset, i) for i in scenes.scenes]
    ref = preds[0]
    table = f"tradeoff render: {ws.name} weights"
    rows = []
    for p, pr in zip(points, preds, strict=True):
        per_view = statistics.median(p.times) / max(views, 1)
        metrics: dict[str, float | None] = {
            "render_s_per_view": per_view,
            "speedup": statistics.median(points[0].times) / statistics.median(p.times),
        }
        rgb_d = torch.cat([(a.rgb - b.rgb).abs().flatten() for a, b in zip(pr, ref, strict=True)])
        dep = torch.cat(
            [(a.depth_z - b.depth_z).flatten().abs() for a, b in zip(pr, ref, strict=True)]
        )
        dep = dep[torch.isfinite(dep)]
        lab = torch.cat([(a.labels != b.labels).flatten() for a, b in zip(pr, ref, strict=True)])
        metrics.update(
            rgb_max_err=float(rgb_d.max()),
            rgb_mean_err=float(rgb_d.mean()),
            depth_mean_err=float(dep.mean()) if dep.numel() else None,
            labels_changed=float(lab.float().mean()),
        )
        reasons: dict[str, str] = {}
        if metrics["depth_mean_err"] is None:
            reasons["depth_mean_err"] = "no_finite_value (no finite depth in either render)"
        if scenes.ground_truth:
            acc: dict[str, list[float]] = {}
            for pred, truth in zip(pr, truths, strict=True):
                score_scene(
                    pred_rgb=pred.rgb,
                    pred_depth=None,
                    pred_labels=pred.labels,
                    truth=truth,
                    input_view=0,
                    with_lpips=False,  # not computed by tradeoff
                ).append_to(acc)
            agg, nulls, _, _ = aggregate({k: acc[k] for k in _RENDER_QUALITY if k in acc})
            for k in _RENDER_QUALITY:
                metrics[k] = agg.get(k)
                if metrics[k] is None:
                    reasons[k] = nulls.get(k, "not computed (no novel view)")
        else:
            for k in _RENDER_QUALITY:
                metrics[k] = None
                reasons[k] = f"no ground truth used: {scenes.why_no_truth}"
        for k, v in list(metrics.items()):
            if v is not None and not math.isfinite(v):
                metrics[k] = None
                reasons[k] = "non_finite (NaN/Inf measured)"
        cfg = shipped.replace(**p.overrides)
        extra: dict[str, Any] = {
            "curve": "render",
            "knob": p.knob,
            "setting": p.setting,
            "overrides": p.overrides,
            "refine_steps": p.refine_steps,
            "weights": ws.name,
            "reference": p.reference,
            "exact_by_construction": p.exact,
            "n_views": views,
            "samples_per_ray": [int(cfg.n_coarse), int(cfg.n_fine)],
            "render_times_s": [round(t, 6) for t in p.times],
            "ground_truth": scenes.ground_truth,
        }
        if ws.run_key:
            extra["run_key"] = ws.run_key
        if p.reference:
            extra["note"] = (
                "the shipped default: the model's config as trained, evaluation knobs off; "
                "the differences of every point are against this render"
            )
        row = Row(
            table=table,
            model=p.label,
            dataset=scenes.name,
            source="measured",
            metrics=metrics,
            null_reasons=reasons,
            variant=ws.name,
            n_scenes=len(scenes.scenes),
            extra=extra,
        )
        rows.append(row.to_dict())
    return rows, scenes, shipped


def _shipped(ctx: Context) -> Any:
    """The benchmark's clevr567 model config at this scale, speed knobs as configured."""
    return adapter.model_config(ctx.scale, "clevr567", "full")


def render_curves(
    rows: list[dict[str, Any]], ws: WeightSet, scenes: RenderScenes
) -> dict[str, dict[str, Any]]:
    """Fronts of the render curve: time per view against PSNR and NV-ARI (ground truth), or
    against the rgb / label difference from the default render (no ground truth)."""
    ref = next(r["id"] for r in rows if r["reference"])
    noise = timing_noise([r["metrics"]["speedup"] for r in rows if r["exact_by_construction"]])
    axes = (
        [("psnr", True), ("nv_ari", True)]
        if scenes.ground_truth
        else [("rgb_mean_err", False), ("labels_changed", False)]
    )
    why = (
        f"against the ground truth of {scenes.name}"
        if scenes.ground_truth
        else f"against the default render (no ground truth: {scenes.why_no_truth})"
    )
    out = {}
    for y, higher in axes:
        c = curve_summary(
            rows,
            "render_s_per_view",
            y,
            higher,
            ref,
            f"evaluation render time per view (encoding included, median of the repeats) "
            f"against {y}, {why}; the shipped default is the model's config as trained with "
            "the evaluation knobs off. Times within the timing noise (|speed-up - 1| of the "
            "default timed again, at least 5%) count as equal.",
            noise,
        )
        if c is not None:
            out[f"render: {ws.name} weights, {y}"] = {"kind": "render", "weights": ws.name, **c}
    return out


def render_note(
    rows: list[dict[str, Any]], ws: WeightSet, scenes: RenderScenes, settings: TradeoffSettings
) -> str:
    """The report's note on the render curve of ``ws``: what each point renders, how it is
    timed and what it is scored against."""
    truth = (
        "PSNR (novel views) and NV-ARI / NV-FG-ARI / FG-ARI against the ground truth of "
        f"{scenes.name} (benchmark.evaluate's scoring)"
        if scenes.ground_truth
        else f"no ground-truth metric ({scenes.why_no_truth}): PSNR and NV-ARI are null"
    )
    return (
        f"Render curve ({ws.name} weights): each point renders {len(scenes.scenes)} scenes x "
        f"every view with svorf's predict_scene (encode the input view, render_chunked), "
        f"{settings.render_repeats} interleaved repeat(s), time per view = median / views; "
        f"{truth}; rgb/depth/label differences are against the default render. Knobs: "
        "samples per ray, clip_to_box, clip_floor_front (where the floor is clipped), "
        "eval_early_stop (transmittance threshold), "
        "eval_fine_min_weight (fine samples only in coarse bins of at least this weight), "
        "and on trained weights test-time slot refinement (refine_slots: Adam steps on the "
        "slots, networks frozen, fitted to the input view's pixels, at svorf's default rate; "
        "its time is in the time per view)."
    )


def format_render_table(rows: list[dict[str, Any]]) -> str:
    """Plain-text table of the render curve's rows."""
    head = (
        f"{'point':58s} {'s/view':>8s} {'speed-up':>8s} {'PSNR dB':>7s} {'NV-ARI':>7s} "
        f"{'rgb mean':>9s} {'labels':>7s} {'front':>5s}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        m = r["metrics"]

        def f(k: str, spec: str, m: dict[str, Any] = m) -> str:
            return "null" if m.get(k) is None else format(m[k], spec)

        lines.append(
            f"{r['model'][:58]:58s} {f('render_s_per_view', '8.4f')} {f('speedup', '8.2f')} "
            f"{f('psnr', '7.1f')} {f('nv_ari', '7.1f')} {f('rgb_mean_err', '9.2e')} "
            f"{f('labels_changed', '7.4f')} {'yes' if r.get('on_front') else '':>5s}"
        )
    return "\n".join(lines)
