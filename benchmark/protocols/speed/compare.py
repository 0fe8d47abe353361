"""The ``speed`` protocol's side-by-side comparison: sVORF against the uORF-style
configuration of the same code (table ``speed_vs_uorf``).

Where this sits: :func:`benchmark.protocols.speed.run_speed` calls :func:`compare_training`
at every batch of :func:`compare_batches`; each repeat of each configuration is a fresh
worker subprocess (:mod:`.training`), alternating, and :func:`ratio_row` sets the ratios
beside the paper's (:data:`PAPER_RATIOS`) and the targets (:data:`TARGET_RATIOS`).
"""

from __future__ import annotations

import statistics
from typing import Any

from benchmark.context import Context
from benchmark.jobs import ModelJob
from benchmark.protocols.speed.options import SpeedOptions
from benchmark.protocols.speed.training import available_mb, load_avg, run_worker, worker_args
from benchmark.report import RowStore
from benchmark.report_row import Row

__all__ = [
    "PAPER_RATIOS",
    "RATIO_KEYS",
    "RATIO_LABEL",
    "SVORF_LABEL",
    "TARGET_RATIOS",
    "UORF_LABEL",
    "compare_batches",
    "compare_row",
    "compare_training",
    "ratio_note",
    "ratio_row",
]

#: The paper's Table 8 ratios, uORF (coarse stage) over sVORF: 522 s / 204 s per epoch and
#: 23.6 GB / 4.6 GB of GPU memory, batch 1 on a V100.
PAPER_RATIOS: dict[str, float] = {
    "step_time_ratio": round(522.0 / 204.0, 3),
    "memory_ratio": round(23.6 / 4.6, 3),
    "tensor_memory_ratio": round(23.6 / 4.6, 3),  # GPU memory is tensor memory
}
#: The ratio row's metrics, in the order notes and figures show them.
RATIO_KEYS: tuple[str, ...] = (
    "step_time_ratio",
    "memory_ratio",
    "train_memory_ratio",
    "tensor_memory_ratio",
)
#: The speed targets for the same ratios (sVORF at least this much faster / smaller). The
#: memory target is checked on both memory measures: the whole process (``memory_ratio``;
#: on a CPU it carries Python, torch and the data on both sides) and live tensor bytes
#: (``tensor_memory_ratio``, what the paper's GPU memory counts).
TARGET_RATIOS: dict[str, float] = {
    "step_time_ratio": 3.0,
    "memory_ratio": 5.0,
    "tensor_memory_ratio": 5.0,
}

SVORF_LABEL = "sVORF (small-ray training)"
UORF_LABEL = "uORF-style (full image, density-weighted, slot-conditioned MLP)"
RATIO_LABEL = "sVORF vs uORF-style"


def _median(xs: list[float]) -> float | None:
    return float(statistics.median(xs)) if xs else None


def compare_row(
    model: str, style: str, runs: list[dict[str, Any]], errors: list[str]
) -> dict[str, Any]:
    """The ``speed_vs_uorf`` row of one configuration (``style`` ``svorf`` or ``uorf``):
    medians over the ``runs`` that did not fail, ``errors`` of those that did as the null
    reason."""
    ok = [r for r in runs if "error" not in r]
    steps = [t for r in ok for t in r["step_times_s"]]
    step = _median(steps)
    peak = _median([r["peak_memory_mb"] for r in ok])
    train_mem = _median([r["train_memory_mb"] for r in ok if r.get("train_memory_mb") is not None])
    tensor_peak = _median([r["tensor_peak_mb"] for r in ok if r.get("tensor_peak_mb") is not None])
    metrics: dict[str, float | None] = {
        "step_time_s": step,
        "steps_per_s": 1.0 / step if step else None,
        "peak_memory_mb": peak,
        "train_memory_mb": train_mem,
        "tensor_peak_mb": tensor_peak,
    }
    why = "; ".join(errors) if errors else "not_measured"
    if ok and tensor_peak is None:
        why_tensor = "tensor memory not measured (tensor_memory_steps = 0)"
    else:
        why_tensor = why
    first = ok[0] if ok else {}
    reasons = {
        k: (why_tensor if k == "tensor_peak_mb" else why) for k, v in metrics.items() if v is None
    }
    extra = {
        "n_cases": len(steps),
        "repeats": len(ok),
        "repeats_failed": len(runs) - len(ok),
        "step_times_s": steps,
        "peak_memory_mb_per_repeat": [r["peak_memory_mb"] for r in ok],
        "train_memory_mb_per_repeat": [r.get("train_memory_mb") for r in ok],
        "load_avg_per_repeat": [[r.get("load_avg_before"), r.get("load_avg_after")] for r in ok],
        "batch_scenes": first.get("batch_scenes"),
        "rays_per_scene": first.get("rays_per_scene"),
        "ray_sampling": first.get("ray_sampling"),
        "memory_kind": first.get("memory_kind"),
        "tensor_peak_mb_per_repeat": [r.get("tensor_peak_mb") for r in ok],
        "tensor_train_mb_per_repeat": [r.get("tensor_train_mb") for r in ok],
        "tensor_memory_kind": first.get("tensor_memory_kind"),
        "params": first.get("params"),
        "device": first.get("device"),
        "model_config": first.get("model_config"),
        "train_config": first.get("train_config"),
        "note": (
            f"median over {len(steps)} timed steps of {len(ok)} fresh subprocess(es) "
            f"(alternating with the other configuration); memory = median of the repeats' peaks"
        ),
    }
    row = Row(
        table="speed_vs_uorf",
        model=model,
        dataset="clevr567",
        source="measured",
        metrics=metrics,
        null_reasons=reasons,
        variant="full" if style == "svorf" else "uorf_style",
        extra=extra,
    )
    return row.to_dict()


def ratio_row(
    svorf: dict[str, Any], uorf: dict[str, Any], label: str = RATIO_LABEL
) -> dict[str, Any]:
    """The "sVORF vs uORF-style" row: uORF-style value / sVORF value (> 1 = sVORF better).

    Args:
        svorf, uorf: the two ``speed_vs_uorf`` rows (:func:`compare_training`).
        label: the row's model label.

    Returns:
        A measured row with ``step_time_ratio``, ``memory_ratio``, ``train_memory_ratio``
        (null with the reason when either side is null), plus ``paper`` (Table 8's ratios),
        ``targets`` (:data:`TARGET_RATIOS`) and ``target_met`` (bool or None per ratio) as plain fields.
    """
    pairs = {
        "step_time_ratio": "step_time_s",
        "memory_ratio": "peak_memory_mb",
        "train_memory_ratio": "train_memory_mb",
        "tensor_memory_ratio": "tensor_peak_mb",
    }
    metrics: dict[str, float | None] = {}
    reasons: dict[str, str] = {}
    for name, src in pairs.items():
        a, b = svorf["metrics"].get(src), uorf["metrics"].get(src)
        if a and b is not None:
            metrics[name] = round(float(b) / float(a), 4)
        else:
            metrics[name] = None
            side = svorf if not a else uorf
            reasons[name] = f"{src} of {side['model']!r} is null: " + (
                side["null_reasons"].get(src) or "zero"
            )
    met = {
        k: (None if metrics.get(k) is None else bool(metrics[k] >= t))
        for k, t in TARGET_RATIOS.items()
    }
    n = min(int(svorf["n_cases"]), int(uorf["n_cases"]))
    extra = {
        "n_cases": n if any(v is not None for v in metrics.values()) else 0,
        "batch_scenes": svorf.get("batch_scenes"),
        "paper": dict(PAPER_RATIOS),
        "targets": dict(TARGET_RATIOS),
        "target_met": met,
        "note": (
            "uORF-style / sVORF, same run (alternating fresh subprocesses); "
            "step_time_ratio from median step times, memory_ratio from peak memory, "
            "train_memory_ratio from the memory the training steps add, tensor_memory_ratio "
            "from the peak of live tensor bytes (the measure of the paper's GPU figure: "
            "max_memory_allocated on CUDA, the allocator's profiler events on a CPU); "
            "paper = Table 8 (uORF coarse vs sVORF, V100 GPU memory), targets = sVORF at "
            "least 3x faster per step and 5x smaller in memory, "
            "checked on the whole-process peak (memory_ratio) and on tensor memory "
            "(tensor_memory_ratio); on CUDA the two are the same measure"
        ),
    }
    row = Row(
        table="speed_vs_uorf",
        model=label,
        dataset="clevr567",
        source="measured",
        metrics=metrics,
        null_reasons=reasons,
        variant="ratio",
        extra=extra,
    )
    return row.to_dict()


def compare_batches(ctx: Context, options: SpeedOptions) -> list[int]:
    """``options.compare_batches`` resolved (None = the scale's training batch), in order,
    each batch once."""
    from benchmark import adapter

    scale_batch = adapter.train_config(ctx.scale, "clevr567", "full", 0, "cpu").batch_scenes
    out: list[int] = []
    for b in options.compare_batches:
        b = int(scale_batch if b is None else b)
        if b not in out:
            out.append(b)
    return out


def _batch_label(label: str, batch: int) -> str:
    """Row label of a comparison at ``batch`` (batch 1, Table 8's setting, keeps the
    plain label and so the row ids of earlier reports)."""
    return label if batch == 1 else f"{label}, batch {batch}"


def compare_training(
    ctx: Context, options: SpeedOptions, store: RowStore | None = None, batch: int = 1
) -> list[dict[str, Any]]:
    """sVORF against the uORF-style configuration of the same code, side by side.

    Runs ``options.compare_repeats`` fresh worker subprocesses of each configuration,
    alternating (sVORF first), at the same batch (``batch`` scenes per step), resolution
    and model size. Each run's raw result is kept in ``store`` (if given), so an
    interrupted comparison resumes with the repeats it has.

    Returns:
        Three ``speed_vs_uorf`` rows: sVORF, uORF-style and the ratio row (:func:`ratio_row`);
        their labels end in ", batch B" unless ``batch`` is 1.
    """
    job = ModelJob("full", "clevr567")
    steps = options.compare_steps or ctx.settings.speed_steps
    warmup = ctx.settings.speed_warmup if options.compare_warmup is None else options.compare_warmup
    avail = available_mb()
    limit = None if avail is None else avail * options.memory_fraction
    runs: dict[str, list[dict[str, Any]]] = {"svorf": [], "uorf": []}
    errors: dict[str, list[str]] = {"svorf": [], "uorf": []}
    for i in range(options.compare_repeats):
        for style in ("svorf", "uorf"):
            rid = f"speed_vs_uorf|raw|{style}|{i}|b{batch}|s{steps}|w{warmup}"
            raw = store.get(rid) if store is not None else None
            if raw is None:
                load_before = load_avg()
                m = run_worker(
                    worker_args(
                        ctx,
                        job,
                        batch,
                        f"cmp-{style}",
                        warmup=warmup,
                        steps=steps,
                        style=style,
                        render=False,
                        max_memory_mb=limit,
                    )
                )
                m["load_avg_before"], m["load_avg_after"] = load_before, load_avg()
                raw = {"id": rid, "result": m}
                if store is not None:
                    store.put(raw)
                if "error" not in m:
                    ctx.timers["training"] += m["timed_wall_s"] + m["warmup_wall_s"]
            m = raw["result"]
            runs[style].append(m)
            if "error" in m:
                lim = f"{limit:.0f} MiB" if limit else "none"
                errors[style].append(f"{m['error']} (address-space limit {lim}): {m['message']}")
    svorf = compare_row(_batch_label(SVORF_LABEL, batch), "svorf", runs["svorf"], errors["svorf"])
    uorf = compare_row(_batch_label(UORF_LABEL, batch), "uorf", runs["uorf"], errors["uorf"])
    return [svorf, uorf, ratio_row(svorf, uorf, _batch_label(RATIO_LABEL, batch))]


def ratio_note(row: dict[str, Any]) -> str:
    """The report's note on a ratio row (:func:`ratio_row`): each ratio, the paper's and
    whether the target is met."""
    m, met = row["metrics"], row["target_met"]

    def show(k: str) -> str:
        v = m.get(k)
        if v is None:
            return f"{k} null ({row['null_reasons'].get(k)})"
        paper = PAPER_RATIOS.get(k)
        tail = f", paper {paper}x" if paper else ""
        goal = TARGET_RATIOS.get(k)
        if goal:
            tail += f", target >= {goal}x {'met' if met.get(k) else 'NOT met'}"
        return f"{k} {v:.3f}x{tail}"

    head = f"sVORF vs uORF-style at batch {row.get('batch_scenes')} (same run, same batch "
    return head + "and resolution): " + "; ".join(show(k) for k in RATIO_KEYS)
