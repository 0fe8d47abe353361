"""``tradeoff`` protocol: a measured time-vs-error curve for every speed knob.

Where this sits: every speed knob must come with a measured time-vs-error curve, so that
its cost in accuracy is known before it is switched on. The knobs are the ``ModelConfig`` fields that trade accuracy for speed
(``bf16_autocast``, ``slot_keep_mass``, ``slot_topk``, ``fg_box``) plus the samples per ray
(``n_coarse`` / ``n_fine``) and two knob combinations (the scale's defaults, every knob).
Each knob is swept over a few settings; each setting is one point:

- time: median wall time of one training step (forward + loss + backward of the scale's
  training batch shape, perturbed samples), over ``repeats`` repeats **interleaved** with
  every other point of the run (repeat r runs every point once, in turn), so the load of
  other processes hits all points alike (the method of :mod:`svorf.speedbench`, whose
  batch, step, error and pair-counting functions this module calls);
- speed-up: the knob-free baseline's median / this point's median, same run;
- error: the point's evaluation render (no jitter) against the knob-free model with the
  same weights on the same rays (:func:`svorf.speedbench.render_errors`): rgb max / mean
  |diff| (colour units), depth mean |diff| (world units), slot_probs max |diff|;
- ``within_tolerance``: every error within the bound stated in
  ``tests/test_speed_knobs.py`` (:data:`TOLERANCE`; slot_probs 3e-2 for combinations).

Every curve holds its own "off" setting as a separately built and timed instance of the
knob-free configuration: its error must be exactly 0 (the off path is the baseline's) and
the spread of the off points' speed-ups around 1 is the timing noise of the run.

Weights (each a table of its own, with its own baseline):

- ``init``: the benchmark's clevr567 model at initialisation (seed ``seeds.train``);
  composition masks m are nearly uniform over the K slots there;
- ``sharp-m``: the same with the composition logits x :data:`SHARPEN`, mimicking a trained
  model whose masks are nearly one-hot (the ``sharp-m`` variants of speedbench); only the
  knobs that depend on m (slot selection, combinations);
- ``trained``: a finished benchmark run of the same model (``<out>/runs/*``, variant
  ``full`` on clevr567, the same model config) where one exists; never trained here.

Inputs are speedbench's batch (random images, rays from ~11.7 units into the scene box),
not dataset scenes, so no dataset is needed; the report says so. These rows are the
``"curve": "step"`` rows. Three more curves:

- ``render`` (rows ``"curve": "render"``): evaluation render time per view (svorf's
  ``predict_scene``: encode, ``render_chunked``) over samples per ray, ``clip_to_box`` flipped,
  ``eval_early_stop`` and ``eval_fine_min_weight`` (the evaluation-only knobs of
  ``ModelConfig``), on the trained weights when there are some. Scored with
  :mod:`benchmark.evaluate`'s functions against the ground truth of the clevr567 test split
  (PSNR on the novel views, NV-ARI, NV-FG-ARI, FG-ARI) when the split is on disk and the
  weights are trained; otherwise PSNR / NV-ARI are null with the reason and the curve's
  error is the difference from the default render (on small analytic sphere scenes);
- ``training``: training-batch PSNR against training wall time from the trained run's
  ``log.jsonl`` (and held-out metrics from its ``eval.jsonl``); absent, with the reason,
  without a trained run;
- every curve has a Pareto front (times within the measured timing noise, and quality
  differences below :data:`METRIC_EPS`, count as equal), a knee and the position of the
  shipped default (``report["curves"]``; rows carry ``on_front``). Figures:
  ``tradeoff.png`` (step), ``tradeoff_render.png``, ``tradeoff_training.png``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from benchmark import adapter
from benchmark.log import log
from benchmark.runner import Context, row_id

__all__ = [
    "SETTINGS",
    "SHARPEN",
    "TOLERANCE",
    "TOLERANCE_COMBINED",
    "TradeoffSettings",
    "format_table",
    "run_tradeoff",
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


@dataclass(frozen=True)
class TradeoffSettings:
    """How hard one scale measures.

    Attributes:
        repeats: timed interleaved repeats (the median is taken over them).
        warmup: untimed repeats before (allocator, caches).
        threads: torch intra-op threads during the run (None = leave as is).
        sharp: add the ``sharp-m`` weight set.
        render_scenes: test scenes each point of the render curve renders (every view).
        render_repeats: timed interleaved repeats of the render curve.
        generator_scenes: clevr567 test scenes of the generator curve (every view).
        generator_ref_samples: samples per pixel of its reference render.
        generator: measure the generator curve (needs bpy).
    """

    repeats: int
    warmup: int
    threads: int | None
    sharp: bool = True
    render_scenes: int = 2
    render_repeats: int = 1
    generator_scenes: int = 1
    generator_ref_samples: int = 64
    generator: bool = True


SETTINGS: dict[str, TradeoffSettings] = {
    # Tiny model, 2 scenes x 64 rays: seconds; one thread so tests stay quiet on 2 cores.
    "smoke": TradeoffSettings(repeats=3, warmup=1, threads=1),
    # The cpu-scale model and batch (4 x 128 rays) on a 2-core machine: minutes; the render
    # curve renders 4 test scenes x 4 views at 64x64 per point (~0.3-0.6 s per view).
    # The generator curve: 2 scenes x 4 views at 64x64 against a 512-sample reference.
    "cpu": TradeoffSettings(
        repeats=7,
        warmup=2,
        threads=2,
        render_scenes=4,
        render_repeats=2,
        generator_scenes=2,
        generator_ref_samples=512,
    ),
    # The paper's model and batch (16 x 64 rays); meant for a GPU.
    "paper": TradeoffSettings(
        repeats=5,
        warmup=2,
        threads=None,
        render_scenes=8,
        render_repeats=2,
        generator_scenes=4,
        generator_ref_samples=512,
    ),
}


@dataclass
class WeightSet:
    """Weights shared by a group of points, and their knob-free configuration."""

    name: str
    table: str
    base: Any  # svorf ModelConfig with every knob off
    state: dict[str, torch.Tensor]
    sharpen: float
    knobs: tuple[str, ...]
    description: str
    run_key: str | None = None
    shipped: Any = None
    """The model config as shipped / trained (speed knobs as configured): the render
    curve's default point. None = ``base``."""
    run_dir: Path | None = None


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


def _fmt(v: Any) -> str:
    return "None" if v is None else (f"{v:g}" if isinstance(v, float) else str(v))


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
            pts.append(Point(ws, "slot_keep_mass", _fmt(m), {"slot_keep_mass": m}))
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
                pts.append(Point(ws, "fg_box", _fmt(s), {"fg_box": s}))
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
                Point(ws, "combined", f"{scale} defaults ({_knobs_txt(defaults)})", defaults)
            )
        pts.append(Point(ws, "combined", f"all ({_knobs_txt(every)})", every))
    return pts


def _off_value(name: str) -> Any:
    from svorf.speedbench import KNOBS_OFF

    return KNOBS_OFF[name]


def _knobs_txt(d: dict[str, Any]) -> str:
    short = {"bf16_autocast": "bf16", "slot_keep_mass": "keep", "slot_topk": "topk"}
    return ", ".join(f"{short.get(k, k)}={_fmt(v)}" for k, v in d.items())


def _knobs_off(cfg: Any) -> Any:
    """``cfg`` with every speed knob off; ``fg_box`` stays where the model was built with it
    (then it is part of the model, not a knob of it)."""
    from svorf.speedbench import KNOBS_OFF

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
        rank = (_steps_done(m), marker.stat().st_mtime)
        if best is None or rank > best[0]:
            best = (rank, marker.parent, m)
    return None if best is None else (best[1], best[2])


def _steps_done(marker: dict[str, Any]) -> int:
    """Training steps a cached run did: its summary's ``steps``, else the configured steps
    (a budgeted run's configured steps are only a limit)."""
    done = (marker.get("summary") or {}).get("steps")
    if isinstance(done, int):
        return done
    return int(((marker.get("key_source") or {}).get("train") or {}).get("steps") or 0)


def weight_sets(ctx: Context, settings: TradeoffSettings) -> list[WeightSet]:
    """``init``, ``sharp-m`` (if ``settings.sharp``) and ``trained`` (if a cached run exists)."""
    from svorf import speedbench

    base = _knobs_off(adapter.model_config(ctx.scale, "clevr567", "full"))
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
            steps = _steps_done(marker)
            wall = marker.get("train_wall_s")
            trained_for = f"{steps} training steps" + (
                f" in {float(wall) / 60:.1f} min" if isinstance(wall, (int, float)) else ""
            )
            out.append(
                WeightSet(
                    "trained",
                    "tradeoff: trained weights",
                    _knobs_off(model.cfg),
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


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def measure(
    ctx: Context, points: list[Point], settings: TradeoffSettings, batch_shape: tuple[int, int]
) -> list[dict[str, Any]]:
    """Time every point interleaved, then take each point's render error against the
    baseline of its weight set; returns one metrics dict per point (same order)."""
    from svorf import speedbench

    dev = ctx.device
    models, counters = [], []
    for p in points:
        cfg = p.weights.base.replace(**p.overrides)
        v = speedbench.Variant(p.label, _cfg_overrides(cfg), p.weights.sharpen)
        m = speedbench.build_model(ctx.scale, v, p.weights.state, ctx.seeds["train"])
        assert m.cfg == cfg, (m.cfg, cfg)  # build_model reproduced the requested config
        models.append(m.to(dev))
        counters.append(speedbench.KeptPairs(m))
    scenes, rays = batch_shape
    batch = tuple(
        x.to(dev) for x in speedbench.make_batch(models[0].cfg, scenes, rays, ctx.seeds["eval"])
    )
    torch.manual_seed(ctx.seeds["eval"])  # the perturbed samples of the training steps

    def step(m) -> float:
        _sync(dev)
        t0 = time.perf_counter()
        speedbench.train_step(m, batch)
        _sync(dev)
        dt = time.perf_counter() - t0
        m.zero_grad(set_to_none=True)  # outside the timing: keep memory to one set of grads
        return dt

    for _ in range(settings.warmup):
        for m in models:
            step(m)
    for c in counters:
        c.kept = c.total = 0.0
    for r in range(settings.repeats):
        for p, m in zip(points, models, strict=True):
            p.times.append(step(m))
        _log(f"repeat {r + 1}/{settings.repeats} done ({len(points)} points)")
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


def _log(msg: str) -> None:
    log(f"tradeoff: {msg}")


def _row(p: Point, m: dict[str, Any], settings: TradeoffSettings, batch: tuple[int, int]):
    tol = TOLERANCE_COMBINED if p.knob == "combined" else TOLERANCE
    metrics: dict[str, float | None] = {
        k: (float(m[k]) if math.isfinite(float(m[k])) else None) for k in _METRICS
    }
    reasons = {k: "non_finite (NaN/Inf measured)" for k, v in metrics.items() if v is None}
    within = all(metrics[k] is not None and metrics[k] <= t for k, t in tol.items())
    cfg = p.weights.base.replace(**p.overrides)
    row = {
        "id": row_id(p.weights.table, p.label, _DATASET, "measured"),
        "table": p.weights.table,
        "model": p.label,
        "dataset": _DATASET,
        "variant": p.weights.name,
        "source": "measured",
        "metrics": metrics,
        "null_reasons": reasons,
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
        row["run_key"] = p.weights.run_key
    if p.reference:
        row["note"] = "the knob-free reference of this table: speed-up 1 and error 0 by definition"
    elif p.exact:
        row["note"] = "equal to the baseline by construction: error must be 0"
    return row


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


def _summaries(rows: list[dict[str, Any]], noise_hi: float | None) -> list[str]:
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


# ---------------------------------------------------------------------------------------------
# Pareto fronts (every curve)


def _dominates(
    a: tuple[float, float], b: tuple[float, float], noise: float, eps: float = 0.0
) -> bool:
    """Whether (time, error) ``a`` dominates ``b``: no worse on both axes and better on one,
    where times within the relative timing ``noise`` of each other, and errors within
    ``eps`` of each other, count as equal."""
    (ta, ea), (tb, eb) = a, b
    faster = ta < tb * (1.0 - noise)
    not_slower = ta <= tb * (1.0 + noise)
    return (ea <= eb + eps and faster) or (ea < eb - eps and not_slower)


def pareto_front(
    points: list[tuple[str, float, float]], noise: float = 0.0, eps: float = 0.0
) -> list[str]:
    """Ids of the points no other point dominates, by increasing time.

    Args:
        points: ``(id, time, error)``; smaller is better on both axes (pass -PSNR for a
            quality metric).
        noise: relative timing noise: times within it count as equal (so a point is not
            dominated by an equal-error point that was only luckier on the clock).
        eps: errors within it count as equal (e.g. 0.01 dB of PSNR).
    Returns:
        The ids of the front: no other point has time <= and error <= with one of them <.
    """
    front = []
    for pid, t, e in points:
        if not any(
            _dominates((t2, e2), (t, e), noise, eps) for qid, t2, e2 in points if qid != pid
        ):
            front.append((t, e, pid))
    return [pid for _, _, pid in sorted(front)]


def knee_point(points: list[tuple[str, float, float]], front: list[str]) -> str | None:
    """The front's knee: the point farthest below the chord from its fastest to its most
    accurate end, both axes scaled to [0, 1] over the front (time on a log axis). None for
    an empty front and for a front with no point below that chord (no knee: each step to
    a slower point buys at least as much as the last); the single point of a one-point
    front; with two, the faster one."""
    if not front:
        return None
    if len(front) <= 2:
        return front[0]
    by = {pid: (t, e) for pid, t, e in points}
    ts = [math.log(max(by[p][0], 1e-12)) for p in front]
    es = [by[p][1] for p in front]

    def unit(v: list[float]) -> list[float]:
        lo, hi = min(v), max(v)
        return [0.0 if hi == lo else (x - lo) / (hi - lo) for x in v]

    x, y = unit(ts), unit(es)
    # chord from (x0, y0) (fastest, largest error) to (x1, y1) (slowest, smallest error)
    x0, y0, x1, y1 = x[0], y[0], x[-1], y[-1]
    n = math.hypot(x1 - x0, y1 - y0) or 1.0
    dist = [((x1 - x0) * (y0 - yi) - (xi - x0) * (y0 - y1)) / n for xi, yi in zip(x, y)]
    best = max(range(len(front)), key=lambda i: dist[i])
    return front[best] if dist[best] > 0 else None


def curve_summary(
    rows: list[dict[str, Any]],
    x: str,
    y: str,
    higher_is_better: bool,
    default_id: str | None,
    note: str,
    noise: float = 0.0,
    eps: float | None = None,
) -> dict[str, Any] | None:
    """Front, knee and where ``default_id`` (the shipped default) sits, for ``rows`` on the
    axes ``metrics[x]`` (time, smaller is better) and ``metrics[y]``, times within the
    relative ``noise`` and values of ``y`` within ``eps`` (default :data:`METRIC_EPS`, else
    0) counting as equal. Rows with a null on either axis are left out; None when no row
    remains."""
    eps = METRIC_EPS.get(y, 0.0) if eps is None else eps
    pts = []
    for r in rows:
        tv, ev = r["metrics"].get(x), r["metrics"].get(y)
        if tv is None or ev is None:
            continue
        pts.append((r["id"], float(tv), -float(ev) if higher_is_better else float(ev)))
    if not pts:
        return None
    front = pareto_front(pts, noise, eps)
    knee = knee_point(pts, front)
    out: dict[str, Any] = {
        "x": x,
        "y": y,
        "y_better": "higher" if higher_is_better else "lower",
        "timing_noise": noise,
        "metric_eps": eps,
        "points": [p[0] for p in pts],
        "front": front,
        "knee": knee,
        "note": note,
    }
    if default_id is not None and any(p[0] == default_id for p in pts):
        t, e = next((t, e) for pid, t, e in pts if pid == default_id)
        out["shipped_default"] = {
            "id": default_id,
            "on_front": default_id in front,
            "is_knee": default_id == knee,
            "dominated_by": [
                pid
                for pid, t2, e2 in pts
                if pid != default_id and _dominates((t2, e2), (t, e), noise, eps)
            ],
        }
    return out


# ---------------------------------------------------------------------------------------------
# Render curve: evaluation render time per view against image / segmentation quality

#: Smallest relative timing noise assumed when comparing times on a front.
MIN_NOISE = 0.05
#: Differences of a quality metric below which two points count as equally good on a
#: front (report units: dB, ARI percent): below what a handful of test scenes resolves.
METRIC_EPS: dict[str, float] = {"psnr": 0.01, "nv_ari": 0.5, "nv_fg_ari": 0.5, "fg_ari": 0.5}
#: Thresholds swept for ``ModelConfig.eval_early_stop`` (transmittance).
EARLY_STOPS = (1e-3, 1e-2, 5e-2, 0.2)
#: Thresholds swept for ``ModelConfig.eval_fine_min_weight`` (coarse bin weight).
FINE_MIN_WEIGHTS = (0.01, 0.05, 0.1, 0.3)
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
    times: list[float] = field(default_factory=list)

    @property
    def label(self) -> str:
        if self.reference or self.exact:
            return f"default ({self.setting})"
        return f"{self.knob}={self.setting}"


def render_points(cfg: Any) -> list[RenderPoint]:
    """The shipped default (``cfg``, eval knobs off) and every render-curve point: samples
    per ray, ``clip_to_box`` flipped, ``eval_early_stop``, ``eval_fine_min_weight`` (with
    fine samples only) and :data:`EVAL_COMBINED`."""
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
    pts.append(
        RenderPoint("clip_to_box", str(not cfg.clip_to_box), {"clip_to_box": not cfg.clip_to_box})
    )
    for v in EARLY_STOPS:
        pts.append(RenderPoint("eval_early_stop", _fmt(v), {"eval_early_stop": v}))
    if nf > 0:
        for v in FINE_MIN_WEIGHTS:
            pts.append(RenderPoint("eval_fine_min_weight", _fmt(v), {"eval_fine_min_weight": v}))
        pts.append(RenderPoint("combined", _knobs_txt(EVAL_COMBINED), dict(EVAL_COMBINED)))
    return pts


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
            source = source_of(json.loads((root / "manifest.json").read_text()))
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
    source = source_of(json.loads((root / "manifest.json").read_text()))
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

    shipped = ws.shipped if ws.shipped is not None else _shipped(ctx)
    points = render_points(shipped)
    scenes = _render_scenes(ctx, ws, settings, tmp)
    models = [_build(ws, shipped.replace(**p.overrides)).to(ctx.device) for p in points]
    preds: list[list[Any]] = [[] for _ in points]
    views = 0
    for m in models:  # warm-up (allocator, caches), untimed
        adapter.predict_scene(m, scenes.dataset, scenes.scenes[0])
    for r in range(settings.render_repeats):
        for j, (p, m) in enumerate(zip(points, models, strict=True)):
            t0 = time.perf_counter()
            out = [adapter.predict_scene(m, scenes.dataset, i) for i in scenes.scenes]
            p.times.append(time.perf_counter() - t0)
            if r == 0:
                preds[j] = out
                views = sum(int(o.rgb.shape[0]) for o in out)
        _log(f"render repeat {r + 1}/{settings.render_repeats} done ({len(points)} points)")
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
        row = {
            "id": row_id(table, p.label, scenes.name, "measured"),
            "table": table,
            "model": p.label,
            "dataset": scenes.name,
            "variant": ws.name,
            "source": "measured",
            "metrics": metrics,
            "null_reasons": reasons,
            "n_scenes": len(scenes.scenes),
            "curve": "render",
            "knob": p.knob,
            "setting": p.setting,
            "overrides": p.overrides,
            "weights": ws.name,
            "reference": p.reference,
            "exact_by_construction": p.exact,
            "n_views": views,
            "samples_per_ray": [int(cfg.n_coarse), int(cfg.n_fine)],
            "render_times_s": [round(t, 6) for t in p.times],
            "ground_truth": scenes.ground_truth,
        }
        if ws.run_key:
            row["run_key"] = ws.run_key
        if p.reference:
            row["note"] = (
                "the shipped default: the model's config as trained, evaluation knobs off; "
                "the differences of every point are against this render"
            )
        rows.append(row)
    return rows, scenes, shipped


def _shipped(ctx: Context) -> Any:
    """The benchmark's clevr567 model config at this scale, speed knobs as configured."""
    return adapter.model_config(ctx.scale, "clevr567", "full")


# ---------------------------------------------------------------------------------------------
# Training curve: metric against wall-clock training time, from a run's logs

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


def _noise(speedups: list[float | None]) -> float:
    """Relative timing noise from the speed-ups of instances equal to the reference: the
    largest |speed-up - 1|, at least :data:`MIN_NOISE`."""
    vals = [abs(1.0 - v) for v in speedups if v]
    return max([MIN_NOISE, *vals])


def _step_curves(
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
            _noise(offs),
        )
        if c is not None:
            out[f"step: {ws.name} weights"] = {"kind": "step", "weights": ws.name, **c}
    return out


def _render_curves(
    rows: list[dict[str, Any]], ws: WeightSet, scenes: RenderScenes
) -> dict[str, dict[str, Any]]:
    """Fronts of the render curve: time per view against PSNR and NV-ARI (ground truth), or
    against the rgb / label difference from the default render (no ground truth)."""
    ref = next(r["id"] for r in rows if r["reference"])
    noise = _noise([r["metrics"]["speedup"] for r in rows if r["exact_by_construction"]])
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


def _training_entry(ws: WeightSet | None, ctx: Context) -> dict[str, Any]:
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


def _mark_fronts(rows: list[dict[str, Any]], curves: dict[str, dict[str, Any]]) -> None:
    """Add ``on_front`` (names of the curves whose front holds the row) to every row of a
    curve."""
    by_id = {r["id"]: r for r in rows}
    for name, c in curves.items():
        if c.get("kind") == "training" or "points" not in c:
            continue
        for pid in c["points"]:
            by_id[pid].setdefault("on_front", [])
        for pid in c["front"]:
            by_id[pid]["on_front"].append(name)


def _front_notes(curves: dict[str, dict[str, Any]], rows: list[dict[str, Any]]) -> list[str]:
    """One sentence per curve: its front, its knee and where the shipped default sits."""
    label = {r["id"]: f"{r['model']}" for r in rows}
    out = []
    for name, c in curves.items():
        if "absent" in c:
            out.append(f"Curve '{name}': absent ({c['absent']}).")
            continue
        if c.get("kind") == "training":
            out.append(f"Curve 'training' (run {c['run']}): {c['note']}")
            continue
        d = c.get("shipped_default")
        where = "not on this curve"
        if d:
            where = (
                ("the knee of the front" if d["is_knee"] else "on the front")
                if d["on_front"]
                else "off the front, dominated by " + ", ".join(label[i] for i in d["dominated_by"])
            )
        out.append(
            f"Curve '{name}' ({c['x']} vs {c['y']}, {c['y_better']} is better): front = "
            + ", ".join(label[i] for i in c["front"])
            + "; knee = "
            + (
                label[c["knee"]]
                if c["knee"] is not None
                else "none (no front point below the chord of its ends)"
            )
            + f"; the shipped default is {where}."
        )
    return out


def _render_note(
    rows: list[dict[str, Any]], ws: WeightSet, scenes: RenderScenes, settings: TradeoffSettings
) -> str:
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
        "samples per ray, clip_to_box, eval_early_stop (transmittance threshold), "
        "eval_fine_min_weight (fine samples only in coarse bins of at least this weight)."
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


# ---------------------------------------------------------------------------------------------
# Generator curve: Cycles seconds per view against image error (generators.bench_quality)

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
    """The generator curve: :func:`generators.bench_quality.run` over
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
    from generators import bench_quality

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
        rows.append(
            {
                "id": row_id(table, label, dataset, "measured"),
                "table": table,
                "model": label,
                "dataset": dataset,
                "variant": "generator",
                "source": "measured",
                "metrics": metrics,
                "null_reasons": reasons,
                "n_scenes": n,
                "curve": "generator",
                "knob": _generator_knob(kw),
                "setting": label,
                "overrides": kw,
                "reference": label == GENERATOR_CANDIDATES[0][0],
                "exact_by_construction": label == GENERATOR_CANDIDATES[1][0],
                "render_settings": r["settings"],
                "masks_identical": r["masks_identical"],
                "depth_identical": r["depth_identical"],
            }
        )
    info["masks_and_depth_identical"] = all(
        r["masks_identical"] and r["depth_identical"] for r in rows
    )
    return rows, info


def _generator_curve(rows: list[dict[str, Any]], info: dict[str, Any]) -> dict[str, Any]:
    if not rows:
        return {"kind": "generator", "absent": info["absent"]}
    ref = next(r["id"] for r in rows if r["reference"])
    noise = _noise([r["metrics"]["speedup"] for r in rows if r["exact_by_construction"]])
    c = curve_summary(
        rows,
        "render_s_per_view",
        "psnr",
        True,
        ref,
        "Cycles render seconds per view (one pass per candidate, not interleaved) against the "
        "PSNR of the 8-bit sRGB image vs the high-sample reference render of the same view "
        "(generators.bench_quality); the shipped default is generators.spec.RenderSettings() "
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


def run_tradeoff(ctx: Context) -> Path:
    """Measure every knob's time-vs-error curve at ``ctx.scale``; write the report."""
    from benchmark.figures import pareto_chart, tradeoff_chart, training_chart

    settings = SETTINGS[ctx.scale]
    report = ctx.base_report()
    threads0 = torch.get_num_threads()
    if settings.threads is not None:
        torch.set_num_threads(settings.threads)
    try:
        t0 = time.perf_counter()
        tcfg = adapter.train_config(
            ctx.scale, "clevr567", "full", ctx.seeds["train"], ctx.device, ctx.train_steps
        )
        batch = (int(tcfg.batch_scenes), int(tcfg.rays_per_scene))
        sets = weight_sets(ctx, settings)
        points = [p for ws in sets for p in knob_points(ws, ctx.scale)]
        _log(
            f"{len(points)} points ({', '.join(ws.name for ws in sets)} weights), batch "
            f"{batch[0]}x{batch[1]} rays, {settings.repeats} repeats + {settings.warmup} warm-up, "
            f"threads {torch.get_num_threads()}, device {ctx.device}"
        )
        measured = measure(ctx, points, settings, batch)
        # The render curve on the trained weights where there are some, else at init.
        render_ws = next((ws for ws in sets if ws.name == "trained"), sets[0])
        with tempfile.TemporaryDirectory(prefix="tradeoff-render-") as tmp:
            render_rows, scenes, shipped = measure_render(ctx, render_ws, settings, Path(tmp))
        ctx.timers["evaluation"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        gen_rows, gen_info = measure_generator(ctx, settings)
        ctx.timers["data"] += time.perf_counter() - t0
    finally:
        torch.set_num_threads(threads0)
    rows = [_row(p, m, settings, batch) for p, m in zip(points, measured, strict=True)]
    curves = _step_curves(rows, sets, ctx.scale)
    curves.update(_render_curves(render_rows, render_ws, scenes))
    trained = next((ws for ws in sets if ws.name == "trained"), None)
    curves["training"] = _training_entry(trained, ctx)
    curves["generator"] = _generator_curve(gen_rows, gen_info)
    _mark_fronts(rows + render_rows + gen_rows, curves)
    report["rows"] = rows + render_rows + gen_rows
    report["curves"] = curves
    report["scale_settings"]["tradeoff"] = {
        **dataclasses.asdict(settings),
        "threads_used": settings.threads if settings.threads is not None else threads0,
        "batch": {"scenes": batch[0], "rays": batch[1]},
        "tolerance": TOLERANCE,
        "tolerance_combined": TOLERANCE_COMBINED,
        "weight_sets": [
            {
                "name": ws.name,
                "table": ws.table,
                "description": ws.description,
                "sharpen": ws.sharpen,
                "run_key": ws.run_key,
                "knobs": list(ws.knobs),
                "model_config": adapter.config_dict(ws.base),
            }
            for ws in sets
        ],
    }
    offs = [  # instances of the knob-free config itself (not the other exact settings)
        r["metrics"]["speedup"]
        for r in rows
        if not r["overrides"] and not r["reference"] and r["metrics"]["speedup"]
    ]
    report["scale_settings"]["tradeoff"]["render"] = {
        "weights": render_ws.name,
        "scenes": scenes.name,
        "n_scenes": len(scenes.scenes),
        "ground_truth": scenes.ground_truth,
        "why_no_ground_truth": scenes.why_no_truth,
        "shipped_config": adapter.config_dict(shipped),
        "early_stops": list(EARLY_STOPS),
        "fine_min_weights": list(FINE_MIN_WEIGHTS),
    }
    report["scale_settings"]["tradeoff"]["generator"] = gen_info
    has_trained = any(ws.name == "trained" for ws in sets)
    report["notes"] = [
        "Weights: "
        + "; ".join(f"{ws.name} = {ws.description}" for ws in sets)
        + (
            "."
            if has_trained
            else ". No finished benchmark run of the clevr567 'full' model at this scale was "
            f"found under {ctx.out / 'runs'}, so no curve uses trained weights."
        ),
        (
            f"Time: median of {settings.repeats} interleaved training steps (forward + loss + "
            f"backward, batch {batch[0]} scenes x {batch[1]} rays, perturbed samples) after "
            f"{settings.warmup} warm-up round(s); speed-up = the baseline's median / the point's "
            "median in the same run. Inputs are svorf.speedbench's random images and rays, "
            "not dataset scenes."
        ),
        (
            "Error: the point's evaluation render vs the knob-free model with the same weights "
            "on the same rays: rgb max/mean |diff| (colour units), depth mean |diff| (world "
            "units), slot_probs max |diff|. kept_pairs: fraction of (point, slot) field "
            "evaluations done."
        ),
        (
            f"within_tolerance: rgb max <= {TOLERANCE['rgb_max_err']:g}, depth mean <= "
            f"{TOLERANCE['depth_mean_err']:g}, slot_probs max <= "
            f"{TOLERANCE['slot_probs_max_err']:g} ({TOLERANCE_COMBINED['slot_probs_max_err']:g} "
            "for combinations): the bounds tests/test_speed_knobs.py states for bf16 and "
            "slot_keep_mass=0.99, applied to every knob. fg_box (a modelling choice), fixed "
            "slot_topk on flat masks and other sample counts are expected to lie beyond them."
        ),
    ]
    if offs:
        report["notes"].append(
            f"Timing noise: the {len(offs)} off-setting instances (the baseline's config, timed "
            f"separately) have speed-ups {min(offs):.2f}..{max(offs):.2f}; speed-ups within that "
            "range are not distinguishable from 1."
        )
    if ctx.scale == "smoke":
        report["notes"].append(
            "smoke: a tiny model on a tiny batch, so step times are mostly fixed overheads and "
            "speed-ups say little; the errors and the plumbing are what this scale checks."
        )
    report["notes"].extend(_summaries(rows, max(offs) if offs else None))
    report["notes"].append(_render_note(render_rows, render_ws, scenes, settings))
    report["notes"].extend(_front_notes(curves, report["rows"]))
    report["figures"] = [
        tradeoff_chart(ctx.report_dir / "tradeoff.png", rows, ctx.scale, TOLERANCE["rgb_max_err"]),
        pareto_chart(
            ctx.report_dir / "tradeoff_render.png",
            report["rows"],
            {k: c for k, c in curves.items() if c.get("kind") == "render"},
            f"tradeoff ({ctx.scale}): evaluation render time per view vs quality, "
            f"{render_ws.name} weights, {scenes.name}",
        ),
    ]
    if curves["training"].get("points"):
        report["figures"].append(
            training_chart(ctx.report_dir / "tradeoff_training.png", curves["training"])
        )
    if gen_rows:
        report["figures"].append(
            pareto_chart(
                ctx.report_dir / "tradeoff_generator.png",
                report["rows"],
                {"generator": curves["generator"]},
                f"tradeoff ({ctx.scale}): Cycles seconds per view vs PSNR against a "
                f"{settings.generator_ref_samples}-sample reference (masks and depth identical "
                f"at every point: {gen_info['masks_and_depth_identical']})",
            )
        )
        if not gen_info["masks_and_depth_identical"]:
            report["notes"].append(
                "Generator curve: the masks or depth of some point differ from the reference "
                "render's: "
                + ", ".join(
                    r["model"]
                    for r in gen_rows
                    if not (r["masks_identical"] and r["depth_identical"])
                )
                + "."
            )
    _log("\n" + format_table(rows))
    _log("\n" + format_render_table(render_rows))
    return ctx.finish(report)
