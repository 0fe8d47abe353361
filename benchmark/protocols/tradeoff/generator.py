"""The ``tradeoff`` protocol's generator curve: Cycles seconds per view against the image
error of the generator's render settings (:mod:`benchmark.tools.bench_quality`).

Where this sits: :func:`benchmark.protocols.tradeoff.run_tradeoff` calls
:func:`measure_generator` (absent, with the reason, without bpy) and
:func:`generator_curve` for its front.
"""

from __future__ import annotations

import contextlib
import math
import sys
from typing import Any

from benchmark.context import Context
from benchmark.protocols.tradeoff.common import TradeoffSettings
from benchmark.protocols.tradeoff.pareto import curve_summary, timing_noise
from benchmark.report_row import Row

__all__ = ["GENERATOR_CANDIDATES", "generator_curve", "measure_generator"]

#: (label, RenderSettings overrides) of the generator curve; the first is the shipped
#: default (``RenderSettings()`` at the scale's resolution), the second the same again (its
#: speed-up is the timing noise).
GENERATOR_CANDIDATES: list[tuple[str, dict[str, Any]]] = [
    ("default (8spp+oidn, 4 bounces)", {}),
    ("default (timed again)", {}),
    ("1spp+oidn", {"samples": 1}),
    ("4spp+oidn", {"samples": 4}),
    ("16spp+oidn", {"samples": 16}),
    ("32spp+oidn", {"samples": 32}),
    ("8spp raw", {"denoise": False}),
    ("64spp raw", {"samples": 64, "denoise": False}),
    ("8spp+oidn q=FAST", {"denoise_quality": "FAST"}),
    ("8spp+oidn q=HIGH", {"denoise_quality": "HIGH"}),
    ("8spp+oidn prefilter NONE", {"denoise_prefilter": "NONE"}),
    # Blender's own denoiser defaults (what a script that only switches OIDN on gets)
    (
        "8spp+oidn prefilter ACCURATE q=HIGH",
        {"denoise_prefilter": "ACCURATE", "denoise_quality": "HIGH"},
    ),
    (
        "4spp+oidn prefilter ACCURATE q=HIGH",
        {"samples": 4, "denoise_prefilter": "ACCURATE", "denoise_quality": "HIGH"},
    ),
    ("8spp+oidn 1 bounce", {"max_bounces": 1, "diffuse_bounces": 1}),
    ("8spp+oidn 2 bounces", {"max_bounces": 2, "diffuse_bounces": 2}),
    ("8spp+oidn 8 bounces", {"max_bounces": 8, "diffuse_bounces": 8}),
]


def _generator_knob(overrides: dict[str, Any]) -> str:
    if not overrides:
        return "default"
    if {"denoise", "denoise_quality", "denoise_prefilter"} & set(overrides):
        return "denoiser"
    if "max_bounces" in overrides:
        return "bounces"
    return "samples"


def measure_generator(
    ctx: Context, settings: TradeoffSettings
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The generator curve: :func:`benchmark.tools.bench_quality.run` over
    :data:`GENERATOR_CANDIDATES` on the first ``settings.generator_scenes`` clevr567 test
    scenes at the scale's resolution, against a ``settings.generator_ref_samples``-sample
    reference render (no denoiser, 8 bounces) of the same views.

    Returns:
        (rows, info); no rows and ``info["absent"]`` when bpy is not installed.
    """
    from generators.blender_backend import bpy_available

    res = int(ctx.settings.resolution)
    n, ref = settings.generator_scenes, settings.generator_ref_samples
    info: dict[str, Any] = {
        "preset": "clevr567",
        "scenes": n,
        "resolution": res,
        "reference_samples": ref,
        "candidates": [{"label": lab, "overrides": kw} for lab, kw in GENERATOR_CANDIDATES],
    }
    if not settings.generator:
        info["absent"] = "turned off in the tradeoff settings of this scale (generator=False)"
        return [], info
    if not bpy_available():
        info["absent"] = "bpy (Blender as a Python module) is not installed: no generator curve"
        return [], info
    from benchmark.tools import bench_quality

    threads = settings.threads or 1
    with contextlib.redirect_stdout(sys.stderr):  # its per-candidate lines: progress only
        raw = bench_quality.run("clevr567", n, res, ref, threads, GENERATOR_CANDIDATES)
    table = "tradeoff generator: Cycles render settings"
    dataset = (
        f"clevr567 test scenes 0..{n - 1} (generator specs, {res}px), reference {ref} spp "
        "without denoiser, 8 bounces"
    )
    t_ref = raw[0]["s_per_view"]
    rows = []
    for (label, kw), r in zip(GENERATOR_CANDIDATES, raw, strict=True):
        metrics: dict[str, float | None] = {
            "render_s_per_view": r["s_per_view"],
            "speedup": t_ref / r["s_per_view"] if r["s_per_view"] > 0 else None,
            "psnr": r["psnr_db"] if math.isfinite(r["psnr_db"]) else None,
        }
        reasons = {
            k: "non_finite (identical images, or no time)" for k, v in metrics.items() if v is None
        }
        row = Row(
            table=table,
            model=label,
            dataset=dataset,
            source="measured",
            metrics=metrics,
            null_reasons=reasons,
            variant="generator",
            n_scenes=n,
            extra={
                "curve": "generator",
                "knob": _generator_knob(kw),
                "setting": label,
                "overrides": kw,
                "reference": label == GENERATOR_CANDIDATES[0][0],
                "exact_by_construction": label == GENERATOR_CANDIDATES[1][0],
                "render_settings": r["settings"],
                "masks_identical": r["masks_identical"],
                "depth_identical": r["depth_identical"],
            },
        )
        rows.append(row.to_dict())
    info["masks_and_depth_identical"] = all(
        r["masks_identical"] and r["depth_identical"] for r in rows
    )
    return rows, info


def generator_curve(rows: list[dict[str, Any]], info: dict[str, Any]) -> dict[str, Any]:
    """The generator curve's entry of ``report["curves"]``: its front, knee and shipped
    default (:func:`benchmark.protocols.tradeoff.pareto.curve_summary`), or ``absent``
    with the reason when :func:`measure_generator` made no rows."""
    if not rows:
        return {"kind": "generator", "absent": info["absent"]}
    ref = next(r["id"] for r in rows if r["reference"])
    noise = timing_noise([r["metrics"]["speedup"] for r in rows if r["exact_by_construction"]])
    c = curve_summary(
        rows,
        "render_s_per_view",
        "psnr",
        True,
        ref,
        "Cycles render seconds per view (one pass per candidate, not interleaved) against the "
        "PSNR of the 8-bit sRGB image vs the high-sample reference render of the same view "
        "(benchmark.tools.bench_quality); the shipped default is generators.spec.RenderSettings() "
        "at this resolution. masks_identical / depth_identical: the instance-id and planar "
        "depth passes equal the reference's exactly at that point.",
        noise,
    )
    assert c is not None  # the default always has a time and a finite PSNR or a reason
    return {
        "kind": "generator",
        **c,
        "masks_and_depth_identical": info["masks_and_depth_identical"],
    }
