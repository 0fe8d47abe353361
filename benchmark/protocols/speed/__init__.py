"""``speed`` protocol: training step time and memory (sVORF and a uORF-style configuration
of the same code, side by side), generator overhead and scaling, inference images/s.

Where this sits: compared with the paper's Table 8 (``tab:time``: memory and time of one
CLEVR-567 epoch at batch size 1 on a V100) and with the project's speed targets
(:data:`TARGET_RATIOS`, :data:`GENERATOR_BASELINE_TARGET`). Every
training measurement runs in a fresh subprocess (:mod:`benchmark.protocols.speed.worker`)
so that its peak memory belongs to that training alone:

- CPU: ``peak_memory_mb`` is the peak resident set size of the worker process (Python,
  torch and the training split included, ~0.5 GB at cpu scale); ``train_memory_mb`` is
  that peak minus the resident size at the first training step (dataset, model and
  optimizer already built): what the training steps themselves add. CUDA:
  ``torch.cuda.max_memory_allocated`` (tensors only) and that minus the memory allocated
  at the first step.
- ``tensor_peak_mb``: the peak of live tensor bytes during training, the measure of the
  paper's GPU figure (CUDA: ``max_memory_allocated``; CPU: the allocator events that
  ``torch.profiler`` records over a few extra untimed steps, see the worker).
- step time: the median of the timed steps' own durations (svorf's per-step log, after
  warm-up steps; checkpoint writes excluded). ``steps_per_s`` is its inverse.

Tables (rows):

1. ``tab:time``: "sVORF" measured at batch 1 (the paper's setting), ``epoch_time_s`` =
   1000 scenes x mean step time, ``memory_gb``; beside the paper's rows.
2. ``speed``: the same at the scale's own batch size.
3. ``speed_vs_uorf``: sVORF (small-ray training: the scale's rays per scene and ray
   sampling) against the uORF-style configuration of the same code (every pixel of one
   target view per scene per step, density-weighted composition, slot-conditioned MLP
   without hypernetwork), same resolution, batch, encoder, decoder and samples per ray;
   at each batch of ``compare_batches`` (1 = Table 8's setting, then the scale's
   training batch: labels of batches other than 1 end in ", batch B").
   The two run alternately (sVORF, uORF-style, sVORF, ...), ``compare_repeats`` times
   each, every repeat a fresh subprocess, so machine load hits both alike; the ratio row
   "sVORF vs uORF-style" has ``step_time_ratio`` (uORF-style median step / sVORF's),
   ``memory_ratio`` (peak memory), ``train_memory_ratio`` (memory added by training) and
   ``tensor_memory_ratio`` (peak live tensor bytes),
   with the paper's ratios (Table 8: 522 s / 204 s = 2.56x, 23.6 GB / 4.6 GB = 5.13x)
   and the targets (>= 3x, >= 5x) as plain fields, never as measured values.
4. ``speed_generator``: seconds per view of ``generate`` (a fresh command per worker
   count, :func:`benchmark.scaling.measure_generation`) and of a bare Cycles render of
   the same views at the same settings (:func:`benchmark.tools.bench_overhead.
   bare_render_s_per_view`, 1 thread, render calls only); ``overhead_ratio`` =
   generate s/view (1 worker x 1 thread) / bare Cycles s/view; ``scaling_speedup`` per
   worker count. Needs Blender (``bpy``): otherwise, and with ``--data-source synthetic``,
   one row of nulls with the reason.
5. ``speed_inference``: images per second of novel-view rendering (every view of a test
   scene from one encode; RGB, depth and slot masks come out of the same render) and of
   segmentation rendering (encode + the input view only), medians over test scenes.

Layout: this package's ``__init__`` runs the protocol (:func:`run_speed`, cached rows keyed
on :func:`code_fingerprint`) and re-exports the public names of its parts: the options
(:mod:`.options`), tables 1, 2 and 5 (:mod:`.training`), table 3 (:mod:`.compare`) and table
4 (:mod:`.generator`).
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

from benchmark.context import Context
from benchmark.jobs import ModelJob
from benchmark.paper_numbers import paper_rows
from benchmark.protocols.speed.compare import (
    PAPER_RATIOS,
    RATIO_KEYS,
    RATIO_LABEL,
    SVORF_LABEL,
    TARGET_RATIOS,
    UORF_LABEL,
    compare_batches,
    compare_row,
    compare_training,
    ratio_note,
    ratio_row,
)
from benchmark.protocols.speed.generator import (
    BASELINE_LABELS,
    GENERATOR_BASELINE_TARGET,
    baseline_note,
    baseline_row_ids,
    baseline_rows,
    generator_row_ids,
    generator_rows,
)
from benchmark.protocols.speed.options import SpeedOptions, default_options
from benchmark.protocols.speed.training import (
    PAPER_EPOCH_SCENES,
    inference_rows,
    measure_training,
    training_row,
)
from benchmark.report import RowStore
from benchmark.report_row import row_id

__all__ = [
    "BASELINE_CODE",
    "BASELINE_LABELS",
    "GENERATOR_BASELINE_TARGET",
    "GENERATOR_TOOLS",
    "MEASURED_CODE",
    "PAPER_EPOCH_SCENES",
    "PAPER_RATIOS",
    "RATIO_KEYS",
    "RATIO_LABEL",
    "SVORF_LABEL",
    "TARGET_RATIOS",
    "UORF_LABEL",
    "SpeedOptions",
    "baseline_note",
    "baseline_rows",
    "code_fingerprint",
    "compare_batches",
    "compare_row",
    "compare_training",
    "default_options",
    "generator_rows",
    "ratio_note",
    "ratio_row",
    "run_speed",
]


def run_speed(ctx: Context, options: SpeedOptions | None = None) -> Path:
    """Run the ``speed`` protocol and write its report (see the module docstring).

    Args:
        ctx: the protocol context (scale, device, data, output folder).
        options: what to measure beyond ``speed_steps``/``speed_warmup``; None =
            :func:`default_options` of the scale.

    Returns:
        The path of the written ``report.json``.
    """
    options = options or default_options(ctx.scale)
    report = ctx.base_report()
    report["scale_settings"]["speed_options"] = options.to_dict()
    job = ModelJob("full", "clevr567")
    store = RowStore(
        ctx.report_dir / "rows",
        {
            "scale": ctx.scale,
            "settings": ctx.settings.to_dict(),
            "device": ctx.device,
            "source": ctx.data_source,
            "seed": ctx.seeds,
            # the script comparison has its own store: its options leave these rows valid
            "speed_options": {
                k: v for k, v in options.to_dict().items() if not k.startswith("baseline_")
            },
            "code": code_fingerprint(),
        },
    )
    base_store = RowStore(
        ctx.report_dir / "rows",
        {
            "scale": ctx.scale,
            "source": ctx.data_source,
            "baseline_options": {
                k: v for k, v in options.to_dict().items() if k.startswith("baseline_")
            },
            "code": code_fingerprint(BASELINE_CODE),
        },
    )
    rows = paper_rows("tab:time")
    inference: list[dict[str, Any]] = []
    for table, model, batch, epoch in (
        ("tab:time", "sVORF", 1, True),
        ("speed", f"sVORF ({ctx.scale} config)", None, False),
    ):
        rid = row_id(table, model, "clevr567", "measured")
        row = store.get(rid)
        if row is None or (table == "speed" and "raw" not in row):
            m = measure_training(
                ctx,
                job,
                batch,
                "b1" if batch == 1 else "scale",
                render_repeats=options.render_repeats if table == "speed" else 1,
            )
            ctx.timers["training"] += m["timed_wall_s"] + m["warmup_wall_s"]
            ctx.timers["evaluation"] += m["render_wall_s"]
            row = training_row(table, model, m, epoch)
            if table == "speed":  # the inference rows are made from this measurement
                row["raw"] = {k: v for k, v in m.items() if "config" not in k}
            store.put(row)
        if table == "speed":
            inference = inference_rows(row["raw"], ctx.scale)
            row = {k: v for k, v in row.items() if k != "raw"}
        rows.append(row)
    cmp_rows = [
        r for b in compare_batches(ctx, options) for r in compare_training(ctx, options, store, b)
    ]
    rows.extend(cmp_rows)
    rows.extend(inference)
    ids = generator_row_ids(options)
    gen = [r for r in (store.get(i) for i in ids) if r is not None]
    if len(gen) != len(ids):
        gen = generator_rows(ctx, options)
        if all(r["n_cases"] for r in gen):
            for r in gen:
                store.put(r)
    rows.extend(gen)
    base_ids = baseline_row_ids(options)
    base = [r for r in (base_store.get(i) for i in base_ids) if r is not None]
    if len(base) != len(base_ids):
        base = baseline_rows(ctx, options)
        for r in base:
            if r["n_cases"]:
                base_store.put(r)
    rows.extend(base)
    report["rows"] = rows
    report["notes"] = [
        (
            "tab:time in the paper: batch size 1 on an NVIDIA V100, full model at 128x128 "
            "supervision; measured rows use this machine, this scale's model and resolution."
        ),
        (
            "CPU memory is the peak resident set size of the measuring process (Python + torch "
            "+ the training split included); train_memory_mb is that peak minus the resident "
            "size at the first training step. CUDA memory is torch.cuda.max_memory_allocated."
        ),
        *(ratio_note(r) for r in cmp_rows if r["variant"] == "ratio"),
        *(baseline_note(r) for r in base),
        *ctx.settings.notes,
    ]
    from benchmark.figures import speed_chart, speed_compare_chart

    report["figures"] = [
        speed_chart(ctx.report_dir / "speed.png", rows, ctx.scale),
        speed_compare_chart(ctx.report_dir / "speed_vs_uorf.png", rows, ctx.scale),
    ]
    return ctx.finish(report)


#: The generator's measuring tools that the generator rows and the script comparison run.
GENERATOR_TOOLS: tuple[str, ...] = tuple(
    f"benchmark/tools/{t}.py" for t in ("bench_overhead", "bench_baseline", "bench_quality")
)
#: Source whose change makes cached speed rows stale: the model, the generator and the
#: code that measures them (repository-relative; folders mean their ``*.py`` files).
MEASURED_CODE: tuple[str, ...] = (
    "svorf",
    "generators",
    *GENERATOR_TOOLS,
    "benchmark/protocols/speed/worker.py",
)
#: The same for the script comparison's rows (the generator and its tools only).
BASELINE_CODE: tuple[str, ...] = ("generators", *GENERATOR_TOOLS)


def code_fingerprint(paths: tuple[str, ...] = MEASURED_CODE) -> str:
    """sha256 (16 hex) of the named source files, so that a cached timing or memory row
    is measured again after the code it measured has changed (not after docs or tests)."""
    root = Path(__file__).resolve().parents[3]  # the repository (this is speed/__init__.py)
    h = hashlib.sha256()
    for rel in paths:
        p = root / rel
        files = sorted(p.rglob("*.py")) if p.is_dir() else [p] if p.is_file() else []
        for f in files:
            h.update(f.relative_to(root).as_posix().encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:16]
