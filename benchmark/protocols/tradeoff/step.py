"""The ``tradeoff`` protocol's step curve: training-step time against the error of every
speed knob of the model, on each weight set.

Where this sits: :func:`benchmark.protocols.tradeoff.run_tradeoff` builds the weight sets
(:func:`weight_sets`) and their points (:func:`knob_points`), times them interleaved with
:func:`benchmark.tools.speedbench.time_interleaved` and takes each point's render error against its
weight set's knob-free model (:func:`measure`), then makes one row per point
(:func:`step_row`) and a front per weight set (:func:`step_curves`).
"""

from __future__ import annotations

import dataclasses
import json
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

__all__ = [
    "ALL_KNOBS",
    "SHARPEN",
    "TOLERANCE",
    "TOLERANCE_COMBINED",
    "Point",
    "find_trained_run",
    "format_table",
    "knob_points",
    "knobs_off",
    "measure",
    "step_curves",
    "step_row",
    "step_summaries",
    "steps_done",
    "weight_sets",
]

#: Bounds stated in tests/test_speed_knobs.py for bf16_autocast and slot_keep_mass=0.99
#: (cpu-scale model, flat and sharp masks): applied here to every point of every knob.
TOLERANCE: dict[str, float] = {
    "rgb_max_err": 1e-2,
    "depth_mean_err": 1e-2,
    "slot_probs_max_err": 1e-2,
}
#: The bound stated there for the cpu defaults together (test_cpu_default_knobs_within_tolerance).
TOLERANCE_COMBINED: dict[str, float] = {**TOLERANCE, "slot_probs_max_err": 3e-2}
#: Composition-logit scale of the ``sharp-m`` weights (speedbench's default ``--sharpen``).
SHARPEN = 8.0
#: Every knob ``all`` turns on (speedbench's ``all`` variant).
ALL_KNOBS: dict[str, Any] = {
    "bf16_autocast": True,
    "fg_box": 3.75,
    "slot_topk": 2,
    "slot_keep_mass": 0.99,
}
_DATASET = "speedbench batch (random images and rays)"
_METRICS = (
    "step_time_s",
    "speedup",
    "rgb_max_err",
    "rgb_mean_err",
    "depth_mean_err",
    "slot_probs_max_err",
    "kept_pairs",
)


@dataclass
class Point:
    """One setting of one knob on one weight set."""

    weights: WeightSet
    knob: str
    setting: str
    overrides: dict[str, Any]
    exact: bool = False
    """Equal to the baseline by construction (the off setting; settings that select
    everything): its error must be 0 up to float summation order."""
    reference: bool = False
    times: list[float] = field(default_factory=list)

    @property
    def label(self) -> str:
        return "baseline (every knob off)" if self.reference else f"{self.knob}={self.setting}"


def knob_points(ws: WeightSet, scale: str) -> list[Point]:
    """The baseline and every (knob, setting) point of ``ws`` (off setting first per knob)."""
    b = ws.base
    k = int(b.num_slots)
    pts = [Point(ws, "baseline", "off", {}, exact=True, reference=True)]
    guided = b.composition == "slot_guided"  # slot selection is inert otherwise

    def off(knob: str, label: str) -> None:
        pts.append(Point(ws, knob, label, {}, exact=True))

    if "bf16_autocast" in ws.knobs:
        off("bf16_autocast", "False")
        pts.append(Point(ws, "bf16_autocast", "True", {"bf16_autocast": True}))
    if "slot_keep_mass" in ws.knobs and guided:
        off("slot_keep_mass", "1.0")
        for m in (0.999, 0.99, 0.95, 0.9):
            pts.append(Point(ws, "slot_keep_mass", fmt_value(m), {"slot_keep_mass": m}))
    if "slot_topk" in ws.knobs and guided:
        off("slot_topk", "0 (all)")
        # topk = K evaluates every slot through the selection code: exact by construction.
        pts.append(Point(ws, "slot_topk", f"{k} (=K)", {"slot_topk": k}, exact=True))
        for t in sorted({t for t in (4, 3, 2) if t < k}, reverse=True):
            pts.append(Point(ws, "slot_topk", str(t), {"slot_topk": t}))
    if "fg_box" in ws.knobs and b.fg_box is None:
        off("fg_box", "None")
        if b.clip_to_box:  # every sample lies in +-box_half: a larger box removes nothing
            big = float(b.box_half) + 0.5
            pts.append(Point(ws, "fg_box", f"{big:g} (> box)", {"fg_box": big}, exact=True))
        for s in (3.75, 3.0):
            if s < b.box_half:
                pts.append(Point(ws, "fg_box", fmt_value(s), {"fg_box": s}))
    if "samples_per_ray" in ws.knobs:
        nc, nf = int(b.n_coarse), int(b.n_fine)
        off("samples_per_ray", f"{nc}+{nf} (default)")
        for c, f in ((max(1, nc // 2), nf // 2), (2 * nc, 2 * nf)):
            pts.append(Point(ws, "samples_per_ray", f"{c}+{f}", {"n_coarse": c, "n_fine": f}))
    if "combined" in ws.knobs:
        off("combined", "every knob off")
        scale_cfg = adapter.model_config(scale, "clevr567", "full")  # knobs as configured
        defaults = {
            n: getattr(scale_cfg, n) for n in ALL_KNOBS if getattr(scale_cfg, n) != _off_value(n)
        }
        every = dict(ALL_KNOBS)
        if b.fg_box is not None:  # part of this model: not a knob here
            every.pop("fg_box")
            defaults.pop("fg_box", None)
        if defaults and defaults != every:
            pts.append(
                Point(ws, "combined", f"{scale} defaults ({knobs_text(defaults)})", defaults)
            )
        pts.append(Point(ws, "combined", f"all ({knobs_text(every)})", every))
    return pts


def _off_value(name: str) -> Any:
    from benchmark.tools.speedbench import KNOBS_OFF

    return KNOBS_OFF[name]


def knobs_off(cfg: Any) -> Any:
    """``cfg`` with every speed knob off; ``fg_box`` stays where the model was built with it
    (then it is part of the model, not a knob of it)."""
    from benchmark.tools.speedbench import KNOBS_OFF

    off = dict(KNOBS_OFF)
    if cfg.fg_box is not None:
        off.pop("fg_box")
    return cfg.replace(**off)


def find_trained_run(ctx: Context) -> tuple[Path, dict[str, Any]] | None:
    """The finished cached run of the benchmark's clevr567 ``full`` model at this scale.

    Looks only at ``<out>/runs/*/benchmark_run.json`` (no dataset is generated, nothing is
    trained): the job must be ``full`` on ``clevr567`` and its model config equal to this
    code's for the scale. Of several, the one with the most training steps, then the newest.

    Returns:
        ``(run folder, marker dict)`` or None.
    """
    want = json.loads(
        json.dumps(adapter.config_dict(adapter.model_config(ctx.scale, "clevr567", "full")))
    )
    best: tuple[tuple[int, float], Path, dict[str, Any]] | None = None
    for marker in sorted((ctx.out / "runs").glob("*/benchmark_run.json")):
        try:
            m = json.loads(marker.read_text())
        except (OSError, ValueError):
            continue
        src = m.get("key_source") or {}
        if (
            m.get("job") != {"variant": "full", "train_preset": "clevr567"}
            or src.get("adapter") != adapter.ADAPTER_VERSION
            or src.get("model") != want
        ):
            continue
        rank = (steps_done(m), marker.stat().st_mtime)
        if best is None or rank > best[0]:
            best = (rank, marker.parent, m)
    return None if best is None else (best[1], best[2])


def steps_done(marker: dict[str, Any]) -> int:
    """Training steps a cached run did: its summary's ``steps``, else the configured steps
    (a budgeted run's configured steps are only a limit)."""
    done = (marker.get("summary") or {}).get("steps")
    if isinstance(done, int):
        return done
    return int(((marker.get("key_source") or {}).get("train") or {}).get("steps") or 0)


def weight_sets(ctx: Context, settings: TradeoffSettings) -> list[WeightSet]:
    """``init``, ``sharp-m`` (if ``settings.sharp``) and ``trained`` (if a cached run exists)."""
    from benchmark.tools import speedbench

    base = knobs_off(adapter.model_config(ctx.scale, "clevr567", "full"))
    every = ("bf16_autocast", "slot_keep_mass", "slot_topk", "fg_box", "samples_per_ray")
    init_model = speedbench.build_model(
        ctx.scale, speedbench.Variant("init", _cfg_overrides(base)), None, ctx.seeds["train"]
    )
    state = {k: v.detach().clone() for k, v in init_model.state_dict().items()}
    out = [
        WeightSet(
            "init",
            "tradeoff: init weights",
            base,
            state,
            1.0,
            (*every, "combined"),
            f"the benchmark's clevr567 model at initialisation (seed {ctx.seeds['train']}); "
            "composition masks m nearly uniform over the K slots",
        )
    ]
    if settings.sharp:
        out.append(
            WeightSet(
                "sharp-m",
                f"tradeoff: sharp-m x{SHARPEN:g} weights",
                base,
                state,
                SHARPEN,
                ("slot_keep_mass", "slot_topk", "combined"),
                f"the init weights with the composition logits x{SHARPEN:g} (in the points and "
                "in their baseline), mimicking the nearly one-hot masks of a trained model",
            )
        )
    found = find_trained_run(ctx)
    if found is not None:
        run_dir, marker = found
        from svorf.train import CheckpointError

        try:
            model = adapter.load_model(run_dir, device="cpu")
        except (CheckpointError, OSError, ValueError, RuntimeError, KeyError) as err:
            # A stale or foreign checkpoint must not stop the protocol.
            ctx.notes.append(
                f"trained run {run_dir.name} found but not loadable ({str(err)[:200]}); "
                "its curves are left out."
            )
        else:
            steps = steps_done(marker)
            wall = marker.get("train_wall_s")
            trained_for = f"{steps} training steps" + (
                f" in {float(wall) / 60:.1f} min" if isinstance(wall, (int, float)) else ""
            )
            out.append(
                WeightSet(
                    "trained",
                    "tradeoff: trained weights",
                    knobs_off(model.cfg),
                    {k: v.detach().clone() for k, v in model.state_dict().items()},
                    1.0,
                    (*every, "combined"),
                    f"benchmark run {run_dir.name} (full model on clevr567, {trained_for} "
                    f"at scale {ctx.scale})",
                    run_key=run_dir.name,
                    shipped=model.cfg,
                    run_dir=run_dir,
                )
            )
    return out


def _cfg_overrides(cfg: Any) -> dict[str, Any]:
    """Every field of ``cfg``, so that ``model_config(scale, **overrides) == cfg``."""
    return {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg)}


def measure(
    ctx: Context, points: list[Point], settings: TradeoffSettings, batch_shape: tuple[int, int]
) -> list[dict[str, Any]]:
    """Time every point interleaved, then take each point's render error against the
    baseline of its weight set; returns one metrics dict per point (same order)."""
    from benchmark.tools import speedbench

    dev = ctx.device
    models, counters = [], []
    for p in points:
        cfg = p.weights.base.replace(**p.overrides)
        v = speedbench.Variant(p.label, _cfg_overrides(cfg), p.weights.sharpen)
        m = speedbench.build_model(ctx.scale, v, p.weights.state, ctx.seeds["train"])
        assert m.cfg == cfg, (m.cfg, cfg)  # build_model reproduced the requested config
        models.append(m.to(dev))
        counters.append(m.count_pairs())
    scenes, rays = batch_shape
    batch = tuple(
        x.to(dev) for x in speedbench.make_batch(models[0].cfg, scenes, rays, ctx.seeds["eval"])
    )
    torch.manual_seed(ctx.seeds["eval"])  # the perturbed samples of the training steps

    def reset_counters() -> None:
        for c in counters:
            c.reset()

    times = speedbench.time_interleaved(
        [partial(speedbench.train_step, m, batch) for m in models],
        repeats=settings.repeats,
        warmup=settings.warmup,
        sync=torch.cuda.synchronize if dev.startswith("cuda") else None,
        # outside the timing: keep memory to one set of grads
        after_step=lambda i: models[i].zero_grad(set_to_none=True),
        after_warmup=reset_counters,
        on_repeat=lambda r, _: log_tradeoff(
            f"repeat {r + 1}/{settings.repeats} done ({len(points)} points)"
        ),
    )
    for p, t in zip(points, times, strict=True):
        p.times.extend(t)
    refs = {id(p.weights): (p, m) for p, m in zip(points, models, strict=True) if p.reference}
    out = []
    for p, m, c in zip(points, models, counters, strict=True):
        ref_p, ref_m = refs[id(p.weights)]
        med = statistics.median(p.times)
        if p.reference:  # against itself: 0 and 1 by definition
            errs = dict.fromkeys(("rgb_max_err", "rgb_mean_err", "depth_mean_err"), 0.0)
            errs["slot_probs_max_err"] = 0.0
            speedup = 1.0
        else:
            errs = speedbench.render_errors(m, ref_m, batch)
            speedup = statistics.median(ref_p.times) / med
        out.append({"step_time_s": med, "speedup": speedup, **errs, "kept_pairs": c.fraction})
    return out


def step_row(
    p: Point, m: dict[str, Any], settings: TradeoffSettings, batch: tuple[int, int]
) -> dict[str, Any]:
    """The report row of point ``p`` from its :func:`measure` metrics ``m`` (non-finite
    values null with the reason; ``within_tolerance`` against :data:`TOLERANCE`, or
    :data:`TOLERANCE_COMBINED` for combinations)."""
    tol = TOLERANCE_COMBINED if p.knob == "combined" else TOLERANCE
    metrics: dict[str, float | None] = {
        k: (float(m[k]) if math.isfinite(float(m[k])) else None) for k in _METRICS
    }
    reasons = {k: "non_finite (NaN/Inf measured)" for k, v in metrics.items() if v is None}
    within = all(metrics[k] is not None and metrics[k] <= t for k, t in tol.items())
    cfg = p.weights.base.replace(**p.overrides)
    extra: dict[str, Any] = {
        "n_cases": settings.repeats,
        "curve": "step",
        "knob": p.knob,
        "setting": p.setting,
        "overrides": p.overrides,
        "weights": p.weights.name,
        "sharpen": p.weights.sharpen,
        "reference": p.reference,
        "exact_by_construction": p.exact,
        "within_tolerance": bool(within),
        "tolerance": dict(tol),
        "batch_scenes": batch[0],
        "rays_per_scene": batch[1],
        "samples_per_ray": [int(cfg.n_coarse), int(cfg.n_fine)],
        "step_times_s": [round(t, 6) for t in p.times],
    }
    if p.weights.run_key:
        extra["run_key"] = p.weights.run_key
    if p.reference:
        extra["note"] = (
            "the knob-free reference of this table: speed-up 1 and error 0 by definition"
        )
    elif p.exact:
        extra["note"] = "equal to the baseline by construction: error must be 0"
    row = Row(
        table=p.weights.table,
        model=p.label,
        dataset=_DATASET,
        source="measured",
        metrics=metrics,
        null_reasons=reasons,
        variant=p.weights.name,
        extra=extra,
    )
    return row.to_dict()


def format_table(rows: list[dict[str, Any]]) -> str:
    """Plain-text table of the report's rows (printed to stderr by :func:`run_tradeoff`)."""
    head = (
        f"{'weights':8s} {'point':52s} {'step s':>8s} {'speed-up':>8s} {'rgb max':>9s} "
        f"{'rgb mean':>9s} {'depth':>9s} {'m max':>9s} {'pairs':>6s} {'tol':>4s}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:

        def f(k: str, spec: str, m: dict[str, Any] = r["metrics"]) -> str:
            return "null" if m[k] is None else format(m[k], spec)

        lines.append(
            f"{r['weights']:8s} {r['model'][:52]:52s} {f('step_time_s', '8.4f')} "
            f"{f('speedup', '8.2f')} {f('rgb_max_err', '9.2e')} {f('rgb_mean_err', '9.2e')} "
            f"{f('depth_mean_err', '9.2e')} {f('slot_probs_max_err', '9.2e')} "
            f"{f('kept_pairs', '6.2f')} {'ok' if r['within_tolerance'] else 'OUT':>4s}"
        )
    return "\n".join(lines)


def step_summaries(rows: list[dict[str, Any]], noise_hi: float | None) -> list[str]:
    """Per weight set and knob: the fastest point within tolerance, in words (flagged when its
    speed-up does not exceed ``noise_hi``, the largest speed-up of a knob-free instance)."""
    out = []
    seen: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in rows:
        if not r["reference"]:
            seen.setdefault((r["weights"], r["knob"]), []).append(r)
    for (w, knob), rs in seen.items():
        ok = [r for r in rs if r["within_tolerance"] and not r["exact_by_construction"]]
        beyond = [r["setting"] for r in rs if not r["within_tolerance"]]
        if ok:
            best = max(ok, key=lambda r: r["metrics"]["speedup"] or 0.0)
            m = best["metrics"]
            txt = (
                f"{w} / {knob}: fastest point within tolerance {best['setting']} "
                f"(speed-up {m['speedup']:.2f}x, rgb max {m['rgb_max_err']:.1e})"
            )
            if noise_hi is not None and m["speedup"] <= noise_hi:
                txt += ", a speed-up within the timing noise"
        else:
            txt = f"{w} / {knob}: no non-trivial point within tolerance"
        if beyond:
            txt += "; beyond tolerance: " + ", ".join(beyond)
        out.append(txt + ".")
    return out


def _step_default_id(sel: list[dict[str, Any]], ws: WeightSet, scale: str) -> str | None:
    """Id of the step-curve row holding the scale's shipped knobs: the ``combined`` row of
    the scale defaults (or of every knob, when the defaults are every knob), else the
    knob-free reference (no knob on by default)."""
    scale_cfg = adapter.model_config(scale, "clevr567", "full")
    defaults = {
        n: getattr(scale_cfg, n) for n in ALL_KNOBS if getattr(scale_cfg, n) != _off_value(n)
    }
    if ws.base.fg_box is not None:
        defaults.pop("fg_box", None)
    for r in sel:
        if (r["reference"] and not defaults) or (
            defaults and r["knob"] == "combined" and r["overrides"] == defaults
        ):
            return r["id"]
    return None


def step_curves(
    rows: list[dict[str, Any]], sets: list[WeightSet], scale: str
) -> dict[str, dict[str, Any]]:
    """Front of every weight set's training-step points: step time against rgb mean error."""
    out = {}
    for ws in sets:
        sel = [r for r in rows if r["weights"] == ws.name]
        offs = [  # the knob-free config timed as points of their own
            r["metrics"]["speedup"]
            for r in sel
            if not r["overrides"] and not r["reference"] and r["metrics"]["speedup"]
        ]
        c = curve_summary(
            sel,
            "step_time_s",
            "rgb_mean_err",
            False,
            _step_default_id(sel, ws, scale),
            "training-step time against the evaluation render's rgb mean |diff| from the "
            "knob-free model with the same weights; the shipped default is the scale's "
            "knobs (model_config) on these weights. Times within the timing noise (the "
            "largest |speed-up - 1| of the knob-free instances, at least 5%) count as equal.",
            timing_noise(offs),
        )
        if c is not None:
            out[f"step: {ws.name} weights"] = {"kind": "step", "weights": ws.name, **c}
    return out
