"""``stability`` protocol: volume rendering under stress against a float64 reference.

Where this sits: volume rendering must keep float32 log-space transmittance even
under autocast, bounded densities, guarded divisions and no NaN/Inf anywhere, checked
by stress tests with extreme densities, distances and dtypes against a float64
reference. This protocol feeds ``svorf.render.volume_render`` (through the
adapter) rays with extreme densities (0 ... 1e38, inf), distances (1e-6 ... 1e6,
coincident samples), many samples, and inputs in float16 / bfloat16 / float32 /
float64 and under bf16 autocast; compares colour, opacity and depth with
:func:`reference_render` (float64, the closed-form quadrature, no clamping), and
counts NaN/Inf in the outputs and in the gradients. No dataset or model needed.
The float64 oracles live in :mod:`.reference` (re-exported here); the cases
beyond the renderer in :mod:`.cases`.

Each case is a row of table ``stability`` with ``max_abs_err_rgb``,
``max_abs_err_acc``, ``max_abs_err_depth``, ``max_rel_err_depth`` and
``nonfinite_count``, plus ``pass`` against the stated tolerances.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from benchmark import adapter
from benchmark.context import Context
from benchmark.protocols.stability import cases as sc
from benchmark.protocols.stability.reference import (
    loguniform,
    nonfinite_count,
    reference_render,
    reference_weights,
)
from benchmark.report_row import Row

__all__ = [
    "CASES",
    "loguniform",
    "nonfinite_count",
    "reference_render",
    "reference_weights",
    "run_stability",
]

TOL_RGB = 1e-4
TOL_ACC = 1e-4
TOL_DEPTH_REL = 1e-4  # relative to the largest sample distance of the ray batch


def _rays(gen: torch.Generator, n_rays: int, n: int, t_lo: float, t_hi: float) -> Tensor:
    t = t_lo + (t_hi - t_lo) * torch.rand(n_rays, n, generator=gen, dtype=torch.float64)
    return t.sort(1).values


Case = Callable[[torch.Generator], tuple[Tensor, Tensor, Tensor, float]]


def _case_moderate(g):
    t = _rays(g, 256, 64, 6.0, 20.0)
    return (
        loguniform(g, t.shape, 1e-3, 1e2),
        torch.rand(*t.shape, 3, generator=g, dtype=torch.float64),
        t,
        1e10,
    )


def _case_extreme_density(g):
    t = _rays(g, 256, 64, 6.0, 20.0)
    choices = torch.tensor(
        [0.0, 1e-12, 1e-3, 1.0, 1e6, 1e10, 1e20, 1e38, float("inf")], dtype=torch.float64
    )
    sigma = choices[torch.randint(0, len(choices), t.shape, generator=g)]
    return sigma, torch.rand(*t.shape, 3, generator=g, dtype=torch.float64), t, 1e10


def _case_empty(g):
    t = _rays(g, 64, 64, 6.0, 20.0)
    return torch.zeros_like(t), torch.rand(*t.shape, 3, generator=g, dtype=torch.float64), t, 1e10


def _case_opaque_first(g):
    t = _rays(g, 64, 64, 6.0, 20.0)
    sigma = loguniform(g, t.shape, 1e-2, 1e2)
    sigma[:, 0] = float("inf")
    return sigma, torch.rand(*t.shape, 3, generator=g, dtype=torch.float64), t, 1e10


def _case_tiny_distances(g):
    t = _rays(g, 256, 64, 1e-6, 1e-5)
    return (
        loguniform(g, t.shape, 1e3, 1e7),
        torch.rand(*t.shape, 3, generator=g, dtype=torch.float64),
        t,
        1e-6,
    )


def _case_huge_distances(g):
    t = _rays(g, 256, 64, 1e4, 1e6)
    return (
        loguniform(g, t.shape, 1e-8, 1e-4),
        torch.rand(*t.shape, 3, generator=g, dtype=torch.float64),
        t,
        1e5,
    )


def _case_coincident(g):
    t = _rays(g, 128, 32, 6.0, 20.0)
    t = torch.repeat_interleave(t, 2, dim=1)  # every sample twice: delta = 0 intervals
    return (
        loguniform(g, t.shape, 1e-2, 1e4),
        torch.rand(*t.shape, 3, generator=g, dtype=torch.float64),
        t,
        1e10,
    )


def _case_many_samples(g):
    t = _rays(g, 64, 1024, 6.0, 20.0)
    return (
        loguniform(g, t.shape, 1e-3, 1e1),
        torch.rand(*t.shape, 3, generator=g, dtype=torch.float64),
        t,
        1e10,
    )


def _case_finite_far(g):
    t = _rays(g, 256, 64, 6.0, 20.0)
    return (
        loguniform(g, t.shape, 1e-3, 1e1),
        torch.rand(*t.shape, 3, generator=g, dtype=torch.float64),
        t,
        0.05,
    )


def _case_wide(g):
    # Spacings log-uniform over 11 decades from t = 1 (in float32 the smallest ones round
    # to 0 or one ulp: the reference sees the same rounded t); 10% empty samples.
    u = torch.rand(256, 64, generator=g, dtype=torch.float64)
    t = 1.0 + torch.cumsum(torch.exp(math.log(1e-8) + u * (math.log(1e3) - math.log(1e-8))), 1)
    sigma = loguniform(g, t.shape, 1e-3, 1e8)
    sigma[torch.rand(t.shape, generator=g) < 0.1] = 0.0
    return sigma, torch.rand(*t.shape, 3, generator=g, dtype=torch.float64), t, 1e3


#: (name, case builder, input dtype, autocast: False, True (= bfloat16) or a dtype)
CASES: list[tuple[str, Case, torch.dtype, bool | torch.dtype]] = [
    ("moderate densities, float32", _case_moderate, torch.float32, False),
    ("extreme densities 0..1e38/inf, float32", _case_extreme_density, torch.float32, False),
    ("zero density everywhere, float32", _case_empty, torch.float32, False),
    ("opaque first sample (inf), float32", _case_opaque_first, torch.float32, False),
    ("tiny distances 1e-6..1e-5, float32", _case_tiny_distances, torch.float32, False),
    ("huge distances 1e4..1e6, float32", _case_huge_distances, torch.float32, False),
    ("coincident samples (delta=0), float32", _case_coincident, torch.float32, False),
    ("1024 samples per ray, float32", _case_many_samples, torch.float32, False),
    ("finite last interval, float32", _case_finite_far, torch.float32, False),
    ("moderate densities, float16 inputs", _case_moderate, torch.float16, False),
    ("moderate densities, bfloat16 inputs", _case_moderate, torch.bfloat16, False),
    ("moderate densities, float64 inputs", _case_moderate, torch.float64, False),
    ("extreme densities, bf16 autocast", _case_extreme_density, torch.float32, True),
    ("extreme densities, bfloat16 inputs", _case_extreme_density, torch.bfloat16, False),
    ("spacings 1e-8..1e3, densities 0..1e8, float32", _case_wide, torch.float32, False),
    ("spacings 1e-8..1e3, densities 0..1e8, bf16 autocast", _case_wide, torch.float32, True),
    ("moderate densities, fp16 autocast", _case_moderate, torch.float32, torch.float16),
    ("extreme densities, fp16 autocast", _case_extreme_density, torch.float32, torch.float16),
]


def run_case(
    name: str, build: Case, dtype: torch.dtype, autocast: bool | torch.dtype, seed: int, device: str
) -> dict[str, Any]:
    """Run one stress case; returns the row's metrics and pass flag."""
    g = torch.Generator().manual_seed(seed)
    sigma64, rgb64, t64, last = build(g)
    # The reference sees exactly the (quantised) inputs the renderer sees.
    sigma = sigma64.to(dtype).to(device).requires_grad_(dtype.is_floating_point)
    rgb = rgb64.to(dtype).to(device).requires_grad_(True)
    t = t64.to(dtype).to(device)
    ac_dtype = torch.bfloat16 if autocast is True else (autocast or None)
    ctx = (
        torch.autocast(device_type=torch.device(device).type, dtype=ac_dtype)
        if ac_dtype is not None
        else contextlib.nullcontext()
    )
    with ctx:
        out_rgb, depth, _w, acc = adapter.volume_render(sigma, rgb, t, last_delta=last)
    loss = out_rgb.float().sum() + depth.float().sum() * 1e-3 + acc.float().sum()
    loss.backward()
    ref = reference_render(
        sigma.detach().cpu().double(), rgb.detach().cpu().double(), t.cpu().double(), last
    )
    t_scale = float(t.double().abs().max())
    err_rgb = float(
        (out_rgb.detach().cpu().double() - ref["rgb"]).abs().nan_to_num(float("inf")).max()
    )
    err_acc = float((acc.detach().cpu().double() - ref["acc"]).abs().nan_to_num(float("inf")).max())
    err_depth = float(
        (depth.detach().cpu().double() - ref["depth"]).abs().nan_to_num(float("inf")).max()
    )
    nonfinite = (
        nonfinite_count(out_rgb)
        + nonfinite_count(depth)
        + nonfinite_count(acc)
        + nonfinite_count(sigma.grad)
        + nonfinite_count(rgb.grad)
    )
    rel = err_depth / t_scale if t_scale > 0 else err_depth
    passed = nonfinite == 0 and err_rgb <= TOL_RGB and err_acc <= TOL_ACC and rel <= TOL_DEPTH_REL

    def fin(x: float) -> float | None:
        return x if math.isfinite(x) else None

    metrics = {
        "max_abs_err_rgb": fin(err_rgb),
        "max_abs_err_acc": fin(err_acc),
        "max_abs_err_depth": fin(err_depth),
        "max_rel_err_depth": fin(rel),
        "nonfinite_count": float(nonfinite),
    }
    return {
        "metrics": metrics,
        "null_reasons": {
            k: "non_finite_error (NaN/Inf output)" for k, v in metrics.items() if v is None
        },
        "pass": bool(passed),
        "n_cases": int(t.shape[0]),
        "samples_per_ray": int(t.shape[1]),
        "input_dtype": str(dtype).replace("torch.", ""),
        "autocast_bf16": ac_dtype == torch.bfloat16,
        "autocast_dtype": None if ac_dtype is None else str(ac_dtype).replace("torch.", ""),
        "tolerance": {"rgb": TOL_RGB, "acc": TOL_ACC, "depth_rel": TOL_DEPTH_REL, "nonfinite": 0},
    }


def _failure_text(r: dict[str, Any]) -> str:
    m = r["metrics"]
    shown = ", ".join(f"{k} {v}" for k, v in m.items())
    return f"[{r['table']}] {r['model']} ({shown})"


def run_stability(ctx: Context) -> Path:
    """Every stress case as a row: the renderer (:data:`CASES`, table ``stability``), then
    composition, losses, metrics and the NaN guard (:mod:`.cases`); the report notes
    each failure plainly."""
    import time

    from benchmark.figures import stability_chart

    report = ctx.base_report()
    rows = []
    t0 = time.perf_counter()
    for i, (name, build, dtype, autocast) in enumerate(CASES):
        r = run_case(name, build, dtype, autocast, ctx.seeds["eval"] + i, ctx.device)
        metrics, reasons = r.pop("metrics"), r.pop("null_reasons")
        row = Row(
            table="stability",
            model=name,
            dataset="synthetic rays",
            source="measured",
            metrics=metrics,
            null_reasons=reasons,
            extra=r,
            fixed_id=f"stability|{name}|{ctx.device}|measured",
        )
        rows.append(row.to_dict())
    rows += sc.compose_rows(ctx.seeds["eval"] + 100)
    rows += sc.loss_rows(ctx.seeds["eval"] + 200)
    rows += sc.metric_rows()
    rows.append(sc.training_row(ctx.scale, ctx.seeds["train"]))
    ctx.timers["evaluation"] += time.perf_counter() - t0
    failed = [_failure_text(r) for r in rows if not r["pass"]]
    counts = {}
    for r in rows:
        n, ok = counts.get(r["table"], (0, 0))
        counts[r["table"]] = (n + 1, ok + bool(r["pass"]))
    report["rows"] = rows
    report["notes"] = [
        (
            f"Renderer (table stability): float64 closed-form quadrature without clamping; "
            f"tolerances rgb {TOL_RGB}, acc {TOL_ACC}, depth {TOL_DEPTH_REL} relative to the "
            "largest t, no NaN/Inf in outputs or gradients."
        ),
        (
            "stability_compose: slot masks, sVORF and density-weighted composition, then the "
            "renderer, against the same pipeline in float64 (max |diff| <= 1e-4). "
            "stability_loss: connectivity loss against its O(N^2) definition on float64 "
            "weights (relative error <= 1e-4). stability_metrics: ARI / FG-ARI against "
            "sklearn, PSNR / SSIM against scikit-image, equal to 1e-9. stability_training: "
            f"learning rate {sc.DIVERGE_LR:g} at this scale's model; the NaN guard must stop "
            "the run and leave the previous step's checkpoint, loadable and finite. Every row "
            "counts NaN/Inf in outputs and gradients (must be 0)."
        ),
        "; ".join(f"{t}: {ok}/{n} pass" for t, (n, ok) in counts.items()),
        (
            f"{len(rows)}/{len(rows)} cases pass."
            if not failed
            else f"{len(failed)}/{len(rows)} cases FAIL: " + "; ".join(failed)
        ),
    ]
    charted = [
        r for r in rows if r["table"] in ("stability", "stability_compose", "stability_loss")
    ]
    report["figures"] = [stability_chart(ctx.report_dir / "stability.png", charted)]
    return ctx.finish(report)
