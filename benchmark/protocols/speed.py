"""``speed`` protocol: training step time and memory (sVORF and a uORF-style configuration
of the same code, side by side), generator overhead and scaling, inference images/s.

Where this sits: compared with the paper's Table 8 (``tab:time``: memory and time of one
CLEVR-567 epoch at batch size 1 on a V100) and with the project's speed targets
(:data:`TARGET_RATIOS`, :data:`GENERATOR_BASELINE_TARGET`). Every
training measurement runs in a fresh subprocess (:mod:`benchmark.protocols._speed_worker`)
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
   the same views at the same settings (:func:`generators.bench_overhead.
   bare_render_s_per_view`, 1 thread, render calls only); ``overhead_ratio`` =
   generate s/view (1 worker x 1 thread) / bare Cycles s/view; ``scaling_speedup`` per
   worker count. Needs Blender (``bpy``): otherwise, and with ``--data-source synthetic``,
   one row of nulls with the reason.
5. ``speed_inference``: images per second of novel-view rendering (every view of a test
   scene from one encode; RGB, depth and slot masks come out of the same render) and of
   segmentation rendering (encode + the input view only), medians over test scenes.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
import json
import os
import statistics
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchmark.context import Context
from benchmark.jobs import ModelJob
from benchmark.paper_numbers import paper_rows
from benchmark.report import RowStore, stable_hash
from benchmark.rows import row_id

__all__ = [
    "GENERATOR_BASELINE_TARGET",
    "PAPER_RATIOS",
    "TARGET_RATIOS",
    "SpeedOptions",
    "baseline_rows",
    "compare_training",
    "default_options",
    "generator_rows",
    "ratio_row",
    "run_speed",
]

PAPER_EPOCH_SCENES = 1000  # CLEVR-567 training split

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

#: The generator's target: ``generate`` at least this much faster than a straightforward bpy script
#: rendering the same scenes, at equal (or better) PSNR against a high-sample reference.
GENERATOR_BASELINE_TARGET = 1.5

SVORF_LABEL = "sVORF (small-ray training)"
UORF_LABEL = "uORF-style (full image, density-weighted, slot-conditioned MLP)"
RATIO_LABEL = "sVORF vs uORF-style"


@dataclass(frozen=True)
class SpeedOptions:
    """What the ``speed`` protocol measures beyond the scale's ``speed_steps``/``speed_warmup``.

    Attributes:
        compare_batches: scenes per step of the sVORF / uORF-style comparisons, one
            comparison each (1 = Table 8's setting; None = the scale's training batch;
            a batch that repeats after resolving is measured once).
        compare_steps: timed steps per comparison run (None = ``speed_steps``).
        compare_warmup: untimed warm-up steps per comparison run (None = ``speed_warmup``).
        compare_repeats: fresh-subprocess runs of each configuration, alternating.
        memory_fraction: each worker's address-space limit as a fraction of the memory
            available when the protocol starts (a configuration that does not fit fails
            with a null row instead of pushing other processes out of memory).
        render_repeats: test scenes timed for the inference rows (median).
        generator: measure the generator; None = when ``data_source`` is ``generator``
            and ``bpy`` is importable.
        gen_scenes, gen_resolution, gen_samples: the generator measurement's split
            (``clevr567`` train scenes, pixels, Cycles samples per pixel).
        gen_workers: worker counts of the generator scaling rows (the first is the
            reference of ``scaling_speedup`` and of ``overhead_ratio``).
        baseline_scenes, baseline_resolution, baseline_samples, baseline_ref_samples,
            baseline_psnr_scenes: ``generate`` against the straightforward bpy script
            (:func:`generators.bench_baseline.compare`): scenes each side renders,
            pixels, Cycles samples of both sides (None = the shipped default), samples
            of the no-denoiser reference, scenes compared with it.
        baseline_denoisers: one comparison per entry of
            :data:`generators.bench_baseline.BASELINE_DENOISERS` (``factory``: the
            script keeps Blender's denoiser defaults; ``tuned``: it borrows
            ``generate``'s); empty = no comparison.
    """

    compare_batches: tuple[int | None, ...] = (1, None)
    compare_steps: int | None = None
    compare_warmup: int | None = None
    compare_repeats: int = 3
    memory_fraction: float = 0.6
    render_repeats: int = 3
    generator: bool | None = None
    gen_scenes: int = 8
    gen_resolution: int = 32
    gen_samples: int = 4
    gen_workers: tuple[int, ...] = (1, 2)
    baseline_scenes: int = 20
    baseline_resolution: int = 128
    baseline_samples: int | None = None
    baseline_ref_samples: int = 512
    baseline_psnr_scenes: int = 2
    baseline_denoisers: tuple[str, ...] = ("factory", "tuned")

    def __post_init__(self) -> None:
        for name in ("compare_repeats", "render_repeats", "gen_scenes", "gen_resolution",
                     "baseline_scenes", "baseline_ref_samples", "baseline_psnr_scenes"):  # fmt: skip
            if int(getattr(self, name)) < 1:
                raise ValueError(f"SpeedOptions.{name} must be >= 1, got {getattr(self, name)}")
        if not self.compare_batches:
            raise ValueError("SpeedOptions.compare_batches must name at least one batch")
        for b in self.compare_batches:
            if b is not None and int(b) < 1:
                raise ValueError(f"SpeedOptions.compare_batches must be >= 1 each, got {b}")
        for name in ("compare_steps", "compare_warmup", "gen_samples", "baseline_samples"):
            v = getattr(self, name)
            if v is not None and int(v) < (0 if name == "compare_warmup" else 1):
                raise ValueError(f"SpeedOptions.{name} must be a positive count, got {v}")
        if not 0.0 < self.memory_fraction <= 1.0:
            raise ValueError(
                f"SpeedOptions.memory_fraction must be in (0, 1], got {self.memory_fraction}"
            )
        if not self.gen_workers or min(self.gen_workers) < 1:
            raise ValueError(f"SpeedOptions.gen_workers must be >= 1 each, got {self.gen_workers}")
        if self.baseline_psnr_scenes > self.baseline_scenes:
            raise ValueError(
                f"SpeedOptions.baseline_psnr_scenes ({self.baseline_psnr_scenes}) must be <= "
                f"baseline_scenes ({self.baseline_scenes})"
            )
        from generators.bench_baseline import BASELINE_DENOISERS  # no bpy import

        bad = [d for d in self.baseline_denoisers if d not in BASELINE_DENOISERS]
        if bad:
            raise ValueError(
                f"SpeedOptions.baseline_denoisers: unknown {bad}; use any of {BASELINE_DENOISERS}"
            )

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["gen_workers"] = list(self.gen_workers)
        d["compare_batches"] = list(self.compare_batches)
        d["baseline_denoisers"] = list(self.baseline_denoisers)
        return d


def default_options(scale: str) -> SpeedOptions:
    """Per-scale defaults: smoke is quick (1 repeat, 2 generator scenes at 1 sample)."""
    if scale == "smoke":
        return SpeedOptions(compare_repeats=1, render_repeats=1, gen_scenes=2, gen_samples=1,
                            baseline_scenes=1, baseline_resolution=32, baseline_samples=1,
                            baseline_ref_samples=16, baseline_psnr_scenes=1,
                            baseline_denoisers=("factory",))  # fmt: skip
    if scale == "paper":
        return SpeedOptions(gen_scenes=16, gen_resolution=128, gen_samples=64)
    return SpeedOptions()


# ----------------------------------------------------------------------------- workers


def _available_mb() -> float | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def _loadavg() -> list[float] | None:
    """1/5/15-minute load averages (None where the OS has none): the machine's load."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def _worker(args: dict[str, Any]) -> dict[str, Any]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(Path(__file__).resolve().parents[2]), env.get("PYTHONPATH", "")]
    )
    proc = subprocess.run(
        [sys.executable, "-m", "benchmark.protocols._speed_worker", json.dumps(args)],
        capture_output=True,
        text=True,
        check=False,
        env=env,
    )
    if proc.returncode != 0:
        raise RuntimeError(
            f"speed worker failed (rc {proc.returncode}): {proc.stderr.strip()[-1500:]}"
        )
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _args(
    ctx: Context,
    job: ModelJob,
    batch_scenes: int | None,
    tag: str,
    *,
    warmup: int,
    steps: int,
    **extra: Any,
) -> dict[str, Any]:
    train = ctx.dataset(job.train_preset, "train")
    test = ctx.dataset(job.train_preset, "test")
    work = (
        ctx.out
        / "speed-work"
        / f"{tag}-{stable_hash([train.fingerprint, batch_scenes, ctx.device])}"
    )
    return {
        "scale": ctx.scale,
        "train_preset": job.train_preset,
        "variant": job.variant,
        "seed": ctx.seeds["train"],
        "device": ctx.device,
        "batch_scenes": batch_scenes,
        "warmup": int(warmup),
        "steps": int(steps),
        "train_dir": str(train.path),
        "test_dir": str(test.path),
        "work": str(work),
        **extra,
    }


def _measure(
    ctx: Context, job: ModelJob, batch_scenes: int | None, tag: str, render_repeats: int = 1
) -> dict[str, Any]:
    return _worker(
        _args(
            ctx,
            job,
            batch_scenes,
            tag,
            warmup=ctx.settings.speed_warmup,
            steps=ctx.settings.speed_steps,
            render_repeats=render_repeats,
        )
    )


def _row(table: str, model: str, m: dict[str, Any], epoch: bool) -> dict[str, Any]:
    step = m["s_per_step"]
    metrics: dict[str, float | None] = {
        "steps_per_s": 1.0 / step if step else None,
        "step_time_s": step,
        "peak_memory_mb": m["peak_memory_mb"],
        "render_s_per_view": m["render_s_per_view"],
    }
    if epoch:
        metrics = {
            "memory_gb": m["peak_memory_mb"] / 1024.0,
            "epoch_time_s": step * PAPER_EPOCH_SCENES / m["batch_scenes"] if step else None,
            **metrics,
        }
    reasons = {k: "not_measured" for k, v in metrics.items() if v is None}
    return {
        "id": row_id(table, model, "clevr567", "measured"),
        "table": table,
        "model": model,
        "dataset": "clevr567",
        "variant": "full",
        "source": "measured",
        "metrics": metrics,
        "null_reasons": reasons,
        "n_cases": int(m["timed_steps"]),
        "batch_scenes": m["batch_scenes"],
        "rays_per_scene": m["rays_per_scene"],
        "memory_kind": m["memory_kind"],
        "params": m.get("params"),
        "device": m["device"],
        "note": (
            f"{m['timed_steps']} timed steps after {m['warmup_steps']} warm-up; batch {m['batch_scenes']} "
            f"scene(s) x {m['rays_per_scene']} rays; memory = {m['memory_kind']}"
            + ("; epoch_time_s = 1000 scenes x step time" if epoch else "")
        ),
        "model_config": m["model_config"],
        "train_config": m["train_config"],
    }


def _inference_rows(m: dict[str, Any], scale: str) -> list[dict[str, Any]]:
    """``speed_inference``: novel-view and segmentation images/s from one measurement."""
    rows = []
    n = int(m.get("render_repeats", 1))
    for model, ips, spv, what in (
        (
            f"novel-view rendering (sVORF, {scale} config)",
            m.get("nvs_images_per_s"),
            m.get("render_s_per_view"),
            (
                f"every view ({m.get('render_views')}) of a test scene from one encode of "
                "its input view, RGB + depth + slot masks in one render; median over scenes"
            ),
        ),
        (
            f"segmentation rendering (sVORF, {scale} config)",
            m.get("seg_images_per_s"),
            m.get("seg_s_per_image"),
            (
                "encode + render of the input view only (its slot masks are the "
                "segmentation; RGB and depth come with them); median over scenes"
            ),
        ),
    ):
        metrics = {"images_per_s": ips, "render_s_per_view": spv}
        rows.append(
            {
                "id": row_id("speed_inference", model, "clevr567", "measured"),
                "table": "speed_inference",
                "model": model,
                "dataset": "clevr567",
                "variant": "full",
                "source": "measured",
                "metrics": metrics,
                "null_reasons": {k: "not_measured" for k, v in metrics.items() if v is None},
                "n_cases": n if ips is not None else 0,
                "device": m["device"],
                "note": f"{what}; {n} test scene(s) timed after one untimed render; the "
                "model is the few-step speed run (render time does not depend on training "
                "with the evaluation knobs off)",
            }
        )
    return rows


# ------------------------------------------------------------------- sVORF vs uORF-style


def _median(xs: list[float]) -> float | None:
    return float(statistics.median(xs)) if xs else None


def _compare_row(
    model: str, style: str, runs: list[dict[str, Any]], errors: list[str]
) -> dict[str, Any]:
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
    return {
        "id": row_id("speed_vs_uorf", model, "clevr567", "measured"),
        "table": "speed_vs_uorf",
        "model": model,
        "dataset": "clevr567",
        "variant": "full" if style == "svorf" else "uorf_style",
        "source": "measured",
        "metrics": metrics,
        "null_reasons": {
            k: (why_tensor if k == "tensor_peak_mb" else why)
            for k, v in metrics.items()
            if v is None
        },
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
    return {
        "id": row_id("speed_vs_uorf", label, "clevr567", "measured"),
        "table": "speed_vs_uorf",
        "model": label,
        "dataset": "clevr567",
        "variant": "ratio",
        "source": "measured",
        "metrics": metrics,
        "null_reasons": reasons,
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
    avail = _available_mb()
    limit = None if avail is None else avail * options.memory_fraction
    runs: dict[str, list[dict[str, Any]]] = {"svorf": [], "uorf": []}
    errors: dict[str, list[str]] = {"svorf": [], "uorf": []}
    for i in range(options.compare_repeats):
        for style in ("svorf", "uorf"):
            rid = f"speed_vs_uorf|raw|{style}|{i}|b{batch}|s{steps}|w{warmup}"
            raw = store.get(rid) if store is not None else None
            if raw is None:
                load_before = _loadavg()
                m = _worker(
                    _args(
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
                m["load_avg_before"], m["load_avg_after"] = load_before, _loadavg()
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
    svorf = _compare_row(_batch_label(SVORF_LABEL, batch), "svorf", runs["svorf"], errors["svorf"])
    uorf = _compare_row(_batch_label(UORF_LABEL, batch), "uorf", runs["uorf"], errors["uorf"])
    return [svorf, uorf, ratio_row(svorf, uorf, _batch_label(RATIO_LABEL, batch))]


# ------------------------------------------------------------------------- generator


def _gen_row(model: str, metrics: dict[str, float | None], reason: str, **extra: Any):
    return {
        "id": row_id("speed_generator", model, "clevr567", "measured"),
        "table": "speed_generator",
        "model": model,
        "dataset": "clevr567",
        "source": "measured",
        "metrics": metrics,
        "null_reasons": {k: reason for k, v in metrics.items() if v is None},
        **extra,
    }


def _bare_cycles(root: Path, threads: int) -> dict[str, Any]:
    """``bare_render_s_per_view`` in a fresh interpreter (bpy must not load in this one)."""
    code = (
        "import json, sys; from generators.bench_overhead import bare_render_s_per_view as f; "
        "print(json.dumps(f(sys.argv[1], None, int(sys.argv[2]))))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, str(root), str(threads)],
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"bare Cycles render failed: {proc.stderr.strip()[-800:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _generator_unavailable(ctx: Context, options: SpeedOptions) -> str | None:
    if options.generator is False:
        return "generator measurement switched off (SpeedOptions.generator=False)"
    if options.generator is None and ctx.data_source != "generator":
        return f"data source {ctx.data_source!r}: no Blender generator in this run"
    if importlib.util.find_spec("bpy") is None:
        return "bpy (Blender as a Python module) is not installed"
    return None


def generator_rows(ctx: Context, options: SpeedOptions) -> list[dict[str, Any]]:
    """``speed_generator`` rows: generate s/view per worker count, bare Cycles, overhead.

    Reuses :func:`benchmark.scaling.measure_generation` (one ``generate`` command per
    worker count, 1 Cycles thread each) and :func:`generators.bench_overhead.
    bare_render_s_per_view` on the 1st count's output (1 thread, render calls only).
    Without Blender: one row of nulls saying why.
    """
    why = _generator_unavailable(ctx, options)
    setting = (
        f"clevr567 train, {options.gen_scenes} scenes x 4 views at {options.gen_resolution}x"
        f"{options.gen_resolution}, {options.gen_samples} Cycles samples"
    )
    if why is not None:
        return [
            _gen_row(
                "generate vs bare Cycles",
                {"s_per_view": None, "overhead_ratio": None},
                why,
                n_cases=0,
                note=setting,
            )
        ]
    from benchmark.scaling import measure_generation

    work = ctx.out / "speed-work" / "generator"
    scal = measure_generation(
        work,
        list(options.gen_workers),
        scenes=options.gen_scenes,
        resolution=options.gen_resolution,
        samples=options.gen_samples,
    )
    ctx.timers["data"] += sum(r["wall_s"] for r in scal)
    first = options.gen_workers[0]
    bare = _bare_cycles(work / f"gen_local_{first}", threads=1)
    ctx.timers["data"] += bare["render_s_per_view"] * bare["views"]
    views = options.gen_scenes * 4
    rows = []
    for r in scal:
        over = r["s_per_view"] / bare["render_s_per_view"] if r["workers"] == first else None
        metrics = {
            "s_per_view": r["s_per_view"],
            "scaling_speedup": r["speedup"],
            "overhead_ratio": None if over is None else round(over, 3),
        }
        rows.append(
            _gen_row(
                f"generate ({r['workers']} worker(s) x 1 thread)",
                metrics,
                f"overhead_ratio is given for the {first}-worker command (bare Cycles uses 1 thread)",
                n_cases=views,
                workers=r["workers"],
                wall_s=r["wall_s"],
                same_bytes_as_first=r["same_bytes_as_first"],
                load_before=r["load_before"],
                load_after=r["load_after"],
                note=(
                    f"{setting}; wall of the whole `generate` command (process start-up, bpy "
                    "import, scene building, writing every output) / views"
                ),
            )
        )
    rows.append(
        _gen_row(
            "bare Cycles render (1 thread)",
            {"s_per_view": bare["render_s_per_view"]},
            "",
            n_cases=int(bare["views"]),
            build_s_per_scene=bare["build_s_per_scene"],
            note=(
                f"{setting}; the same scene JSONs rendered by one BlenderSession, only the "
                "bpy.ops.render.render calls timed (generators.bench_overhead)"
            ),
        )
    )
    return rows


#: Row labels of the straightforward-script comparisons, per ``baseline_denoisers`` entry.
BASELINE_LABELS: dict[str, str] = {
    "factory": "generate vs straightforward bpy script (Blender's default denoiser)",
    "tuned": "generate vs straightforward bpy script (given generate's denoiser settings)",
}


def _compare_with_script(options: SpeedOptions, denoiser: str, out_root: Path) -> dict[str, Any]:
    """:func:`generators.bench_baseline.compare` with the options' settings (a seam for tests)."""
    from generators import bench_baseline
    from generators.spec import RenderSettings

    samples = options.baseline_samples or RenderSettings.samples
    return bench_baseline.compare(
        "clevr567", options.baseline_scenes, options.baseline_resolution,
        options.baseline_ref_samples, None, None, out_root, options.baseline_psnr_scenes,
        samples=samples, baseline_denoiser=denoiser,
    )  # fmt: skip


def baseline_rows(ctx: Context, options: SpeedOptions) -> list[dict[str, Any]]:
    """``speed_generator`` rows: ``generate`` against the straightforward bpy script.

    One row per ``options.baseline_denoisers`` entry, each from one
    :func:`generators.bench_baseline.compare` run (both sides fresh processes, one after
    the other, on the same scenes; PSNR of both against the same no-denoiser reference).
    ``baseline_speedup`` = script wall / ``generate`` wall. The issue's target applies to
    the ``factory`` script (a straightforward script switches the denoiser on and keeps
    Blender's settings): ``target_met`` is true when the speed-up reaches
    :data:`GENERATOR_BASELINE_TARGET` *and* ``generate``'s PSNR is at least the script's
    (the target is at equal PSNR) *and* masks and depth are identical. The ``tuned``
    script is a stricter control (it shows how much of the speed-up is the denoiser
    settings): ``target`` and ``target_met`` are None there.
    Without Blender: one row of nulls per entry, saying why.
    """
    why = _generator_unavailable(ctx, options)
    keys = ("baseline_speedup", "s_per_view", "baseline_s_per_view", "psnr", "baseline_psnr")
    rows = []
    for denoiser in options.baseline_denoisers:
        label = BASELINE_LABELS[denoiser]
        target = GENERATOR_BASELINE_TARGET if denoiser == "factory" else None
        if why is not None:
            rows.append(_gen_row(label, dict.fromkeys(keys), why, n_cases=0, variant=denoiser,
                                 target=target, target_met=None))  # fmt: skip
            continue
        r = _compare_with_script(options, denoiser, ctx.out / "speed-work" / f"baseline_{denoiser}")
        g, n, st = r["generate"], r["naive"], r["settings"]
        ctx.timers["data"] += g["wall_s"] + n["wall_s"]
        exact = bool(r["masks_identical"] and r["depth_identical"])
        metrics = {
            "baseline_speedup": round(r["speedup"], 3),
            "s_per_view": g["s_per_view"],
            "baseline_s_per_view": n["s_per_view"],
            "psnr": round(g["psnr_db"], 3),
            "baseline_psnr": round(n["psnr_db"], 3),
        }
        met = (
            None
            if target is None
            else bool(r["speedup"] >= target and g["psnr_db"] >= n["psnr_db"] and exact)
        )
        dn = st["naive"]["denoiser"]
        rows.append(
            _gen_row(
                label,
                metrics,
                "",
                n_cases=st["views"],
                variant=denoiser,
                target=target,
                target_met=met,
                masks_identical=r["masks_identical"],
                depth_identical=r["depth_identical"],
                wall_s={"generate": g["wall_s"], "baseline": n["wall_s"]},
                load_before=r["load_before"],
                load_after=r["load_after"],
                settings=st,
                note=(
                    f"clevr567 {st['split']}, {st['n_scenes']} scenes x 4 views at "
                    f"{st['resolution']}x{st['resolution']}, {st['generate']['render']['samples']} "
                    f"samples both sides; script: one process on {st['naive']['threads']} "
                    "thread(s), factory reset per scene, Blender's default light paths and "
                    f"adaptive sampling, OIDN prefilter {dn['denoising_prefilter']} quality "
                    f"{dn['denoising_quality']}; wall of each side's whole process; PSNR of "
                    f"the first {st['psnr_scenes']} scene(s)' PNGs against a "
                    f"{st['reference']['samples']}-sample render without denoiser"
                ),
            )
        )
    return rows


# ---------------------------------------------------------------------------- protocol


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
            "code": code_fingerprint(("generators",)),
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
            m = _measure(
                ctx,
                job,
                batch,
                "b1" if batch == 1 else "scale",
                render_repeats=options.render_repeats if table == "speed" else 1,
            )
            ctx.timers["training"] += m["timed_wall_s"] + m["warmup_wall_s"]
            ctx.timers["evaluation"] += m["render_wall_s"]
            row = _row(table, model, m, epoch)
            if table == "speed":  # the inference rows are made from this measurement
                row["raw"] = {k: v for k, v in m.items() if "config" not in k}
            store.put(row)
        if table == "speed":
            inference = _inference_rows(row["raw"], ctx.scale)
            row = {k: v for k, v in row.items() if k != "raw"}
        rows.append(row)
    cmp_rows = [
        r for b in compare_batches(ctx, options) for r in compare_training(ctx, options, store, b)
    ]
    rows.extend(cmp_rows)
    rows.extend(inference)
    ids = _gen_ids(options)
    gen = [r for r in (store.get(i) for i in ids) if r is not None]
    if len(gen) != len(ids):
        gen = generator_rows(ctx, options)
        if all(r["n_cases"] for r in gen):
            for r in gen:
                store.put(r)
    rows.extend(gen)
    base_ids = _baseline_ids(options)
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
        *(_ratio_note(r) for r in cmp_rows if r["variant"] == "ratio"),
        *(_baseline_note(r) for r in base),
        *ctx.settings.notes,
    ]
    from benchmark.figures import speed_chart, speed_compare_chart

    report["figures"] = [
        speed_chart(ctx.report_dir / "speed.png", rows, ctx.scale),
        speed_compare_chart(ctx.report_dir / "speed_vs_uorf.png", rows, ctx.scale),
    ]
    return ctx.finish(report)


def _gen_ids(options: SpeedOptions) -> list[str]:
    ids = [
        row_id("speed_generator", f"generate ({w} worker(s) x 1 thread)", "clevr567", "measured")
        for w in options.gen_workers
    ]
    return ids + [
        row_id("speed_generator", "bare Cycles render (1 thread)", "clevr567", "measured")
    ]


#: Source whose change makes cached speed rows stale: the model, the generator and the
#: worker that measures them (repository-relative; folders mean their ``*.py`` files).
MEASURED_CODE: tuple[str, ...] = ("svorf", "generators", "benchmark/protocols/_speed_worker.py")


def code_fingerprint(paths: tuple[str, ...] = MEASURED_CODE) -> str:
    """sha256 (16 hex) of the named source files, so that a cached timing or memory row
    is measured again after the code it measured has changed (not after docs or tests)."""
    root = Path(__file__).resolve().parents[2]
    h = hashlib.sha256()
    for rel in paths:
        p = root / rel
        files = sorted(p.rglob("*.py")) if p.is_dir() else [p] if p.is_file() else []
        for f in files:
            h.update(f.relative_to(root).as_posix().encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _baseline_ids(options: SpeedOptions) -> list[str]:
    return [
        row_id("speed_generator", BASELINE_LABELS[d], "clevr567", "measured")
        for d in options.baseline_denoisers
    ]


def _baseline_note(row: dict[str, Any]) -> str:
    m = row["metrics"]
    if m["baseline_speedup"] is None:
        return f"{row['model']}: null ({row['null_reasons']['baseline_speedup']})"
    if row["target"] is None:
        verdict = "a stricter control than the issue's straightforward script, no target"
    else:
        ok = "met" if row["target_met"] else "NOT met"
        verdict = f"target >= {row['target']}x at equal or better PSNR {ok}"
    return (
        f"{row['model']}: {m['baseline_speedup']:.2f}x faster ({m['s_per_view']:.3f} vs "
        f"{m['baseline_s_per_view']:.3f} s/view) at {m['psnr']:.2f} vs {m['baseline_psnr']:.2f} "
        f"dB; masks identical {row['masks_identical']}, depth identical "
        f"{row['depth_identical']}; {verdict}"
    )


def _ratio_note(row: dict[str, Any]) -> str:
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
