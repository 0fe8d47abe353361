"""``tradeoff`` protocol: a measured time-vs-error curve for every speed knob.

Where this sits: every speed knob must come with a measured time-vs-error curve, so that
its cost in accuracy is known before it is switched on. The knobs are the ``ModelConfig`` fields that trade accuracy for speed
(``bf16_autocast``, ``slot_keep_mass``, ``slot_topk``, ``fg_box``) plus the samples per ray
(``n_coarse`` / ``n_fine``) and two knob combinations (the scale's defaults, every knob).
Each knob is swept over a few settings; each setting is one point:

- time: median wall time of one training step (forward + loss + backward of the scale's
  training batch shape, perturbed samples), over ``repeats`` repeats **interleaved** with
  every other point of the run (repeat r runs every point once, in turn), so the load of
  other processes hits all points alike (the method of :mod:`benchmark.tools.speedbench`,
  whose batch, step, error and pair-counting functions the curves call);
- speed-up: the knob-free baseline's median / this point's median, same run;
- error: the point's evaluation render (no jitter) against the knob-free model with the
  same weights on the same rays (:func:`benchmark.tools.speedbench.render_errors`): rgb
  max / mean |diff| (colour units), depth mean |diff| (world units), slot_probs max |diff|;
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
  ``clip_floor_front`` flipped (where the floor is clipped), ``eval_early_stop`` and
  ``eval_fine_min_weight`` (the evaluation-only knobs of ``ModelConfig``), on the trained
  weights when there are some; with trained weights scored against the truth, test-time
  slot refinement too (``refine_slots``, 20 and 50 steps: the evaluation's best lever on
  ARI, at its price in time). Scored with
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

Layout: this package's ``__init__`` runs the protocol (:func:`run_tradeoff`) and re-exports
the public names of its parts: each curve's module (:mod:`.step`, :mod:`.render`,
:mod:`.training`, :mod:`.generator`), the fronts (:mod:`.pareto`) and the shared settings
(:mod:`.common`). The step and render curves time their points with
:func:`benchmark.tools.speedbench.time_interleaved`.
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

import torch

from benchmark import adapter
from benchmark.context import Context
from benchmark.protocols.tradeoff.common import (
    SETTINGS,
    TradeoffSettings,
    WeightSet,
    log_tradeoff,
)
from benchmark.protocols.tradeoff.generator import (
    GENERATOR_CANDIDATES,
    generator_curve,
    measure_generator,
)
from benchmark.protocols.tradeoff.pareto import (
    METRIC_EPS,
    MIN_NOISE,
    curve_summary,
    front_notes,
    knee_point,
    mark_fronts,
    pareto_front,
)
from benchmark.protocols.tradeoff.render import (
    EARLY_STOPS,
    EVAL_COMBINED,
    FINE_MIN_WEIGHTS,
    RenderPoint,
    RenderScenes,
    format_render_table,
    measure_render,
    render_curves,
    render_note,
    render_points,
)
from benchmark.protocols.tradeoff.step import (
    ALL_KNOBS,
    SHARPEN,
    TOLERANCE,
    TOLERANCE_COMBINED,
    Point,
    find_trained_run,
    format_table,
    knob_points,
    knobs_off,
    measure,
    step_curves,
    step_row,
    step_summaries,
    steps_done,
    weight_sets,
)
from benchmark.protocols.tradeoff.training import (
    TRAIN_KNEE_DB,
    TRAIN_SMOOTH,
    training_curve,
    training_entry,
)

__all__ = [
    "ALL_KNOBS",
    "EARLY_STOPS",
    "EVAL_COMBINED",
    "FINE_MIN_WEIGHTS",
    "GENERATOR_CANDIDATES",
    "METRIC_EPS",
    "MIN_NOISE",
    "SETTINGS",
    "SHARPEN",
    "TOLERANCE",
    "TOLERANCE_COMBINED",
    "TRAIN_KNEE_DB",
    "TRAIN_SMOOTH",
    "Point",
    "RenderPoint",
    "RenderScenes",
    "TradeoffSettings",
    "WeightSet",
    "curve_summary",
    "find_trained_run",
    "format_render_table",
    "format_table",
    "knee_point",
    "knob_points",
    "knobs_off",
    "measure",
    "measure_generator",
    "measure_render",
    "pareto_front",
    "render_points",
    "run_tradeoff",
    "steps_done",
    "training_curve",
    "weight_sets",
]


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
        log_tradeoff(
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
    rows = [step_row(p, m, settings, batch) for p, m in zip(points, measured, strict=True)]
    curves = step_curves(rows, sets, ctx.scale)
    curves.update(render_curves(render_rows, render_ws, scenes))
    trained = next((ws for ws in sets if ws.name == "trained"), None)
    curves["training"] = training_entry(trained, ctx)
    curves["generator"] = generator_curve(gen_rows, gen_info)
    mark_fronts(rows + render_rows + gen_rows, curves)
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
            "median in the same run. Inputs are benchmark.tools.speedbench's random images and "
            "rays, not dataset scenes."
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
    report["notes"].extend(step_summaries(rows, max(offs) if offs else None))
    report["notes"].append(render_note(render_rows, render_ws, scenes, settings))
    report["notes"].extend(front_notes(curves, report["rows"]))
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
    log_tradeoff("\n" + format_table(rows))
    log_tradeoff("\n" + format_render_table(render_rows))
    return ctx.finish(report)
