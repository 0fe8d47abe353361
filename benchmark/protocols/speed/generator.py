"""The ``speed`` protocol's generator measurements (table ``speed_generator``): ``generate``
against a bare Cycles render and against a straightforward bpy script.

Where this sits: :func:`benchmark.protocols.speed.run_speed` calls
:func:`generator_rows` (seconds per view per worker count, overhead over bare Cycles,
:func:`benchmark.scaling.measure_generation`) and :func:`baseline_rows` (the script
comparison, :func:`benchmark.tools.bench_baseline.compare`). Without Blender both make rows of
nulls with the reason.
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from benchmark.context import Context
from benchmark.protocols.speed.options import SpeedOptions
from benchmark.report_row import Row, row_id

__all__ = [
    "BASELINE_LABELS",
    "GENERATOR_BASELINE_TARGET",
    "baseline_note",
    "baseline_row_ids",
    "baseline_rows",
    "generator_row_ids",
    "generator_rows",
]

#: The generator's target: ``generate`` at least this much faster than a straightforward bpy script
#: rendering the same scenes, at equal (or better) PSNR against a high-sample reference.
GENERATOR_BASELINE_TARGET = 1.5


def _gen_row(model: str, metrics: dict[str, float | None], reason: str, **extra: Any):
    """A ``speed_generator`` row's dict; ``variant`` only where given (it measures no model)."""
    has_variant = "variant" in extra
    variant = extra.pop("variant", None)
    row = Row(
        table="speed_generator",
        model=model,
        dataset="clevr567",
        source="measured",
        metrics=metrics,
        null_reasons={k: reason for k, v in metrics.items() if v is None},
        variant=variant,
        extra=extra,
        has_variant=has_variant,
    )
    return row.to_dict()


def _bare_cycles(root: Path, threads: int) -> dict[str, Any]:
    """``bare_render_s_per_view`` in a fresh interpreter (bpy must not load in this one)."""
    code = (
        "import json, sys; "
        "from benchmark.tools.bench_overhead import bare_render_s_per_view as f; "
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
    worker count, 1 Cycles thread each) and :func:`benchmark.tools.bench_overhead.
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
                "bpy.ops.render.render calls timed (benchmark.tools.bench_overhead)"
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
    """:func:`benchmark.tools.bench_baseline.compare` with the options' settings (a seam for
    tests)."""
    from benchmark.tools import bench_baseline
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
    :func:`benchmark.tools.bench_baseline.compare` run (both sides fresh processes, one after
    the other, on the same scenes; PSNR of both against the same no-denoiser reference).
    ``baseline_speedup`` = script wall / ``generate`` wall. The target applies to
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


def generator_row_ids(options: SpeedOptions) -> list[str]:
    """Ids of the rows :func:`generator_rows` makes (to find them in the row store)."""
    ids = [
        row_id("speed_generator", f"generate ({w} worker(s) x 1 thread)", "clevr567", "measured")
        for w in options.gen_workers
    ]
    return ids + [
        row_id("speed_generator", "bare Cycles render (1 thread)", "clevr567", "measured")
    ]


def baseline_row_ids(options: SpeedOptions) -> list[str]:
    """Ids of the rows :func:`baseline_rows` makes (to find them in the row store)."""
    return [
        row_id("speed_generator", BASELINE_LABELS[d], "clevr567", "measured")
        for d in options.baseline_denoisers
    ]


def baseline_note(row: dict[str, Any]) -> str:
    """The report's note on a :func:`baseline_rows` row: speed-up, PSNR of both sides and
    whether the target is met."""
    m = row["metrics"]
    if m["baseline_speedup"] is None:
        return f"{row['model']}: null ({row['null_reasons']['baseline_speedup']})"
    if row["target"] is None:
        verdict = "a stricter control than the factory script (Blender's settings, denoiser on), no target"
    else:
        ok = "met" if row["target_met"] else "NOT met"
        verdict = f"target >= {row['target']}x at equal or better PSNR {ok}"
    return (
        f"{row['model']}: {m['baseline_speedup']:.2f}x faster ({m['s_per_view']:.3f} vs "
        f"{m['baseline_s_per_view']:.3f} s/view) at {m['psnr']:.2f} vs {m['baseline_psnr']:.2f} "
        f"dB; masks identical {row['masks_identical']}, depth identical "
        f"{row['depth_identical']}; {verdict}"
    )
