"""``generate`` against a straightforward bpy script, side by side (the target: ``generate``
at least 1.5x faster, at equal or better PSNR against a high-sample reference).

Data flow: one :class:`~generators.pipeline.GenerateConfig` fixes the scenes
(``make_scene(preset, split, i, seed, cfg.render_settings())``, as ``render_one``) ->
three fresh subprocesses, each into its own split folder under ``out_root``:

- ``generate/``: the ``generate`` command with the shipped defaults (timed, wall);
- ``naive/``: :func:`naive_render_split`, the baseline script (timed, wall): one
  process, a factory reset before every scene, Cycles CPU on all threads at the same
  samples with OpenImageDenoise switched on, and otherwise Blender's defaults: light
  paths (bounces, caustics, adaptive sampling) and denoiser prefilter/quality
  (``--baseline-denoiser tuned`` gives it ``generate``'s denoiser settings instead),
  written through the same ``writer.write_scene``;
- ``reference/``: the first ``psnr_scenes`` scenes at ``ref_samples``, no denoiser
  (the reference of ``bench_quality``);

-> PSNR of the written 8-bit sRGB PNGs against the reference, exact equality of the
masks, instance ids and depth of ``generate/`` and ``naive/`` -> one JSON dict.
The driver never imports bpy (tests call :func:`compare` in-process).

    python -m benchmark.tools.bench_baseline --preset clevr567 --n 20 --resolution 128 \\
        --ref-samples 512 --psnr-scenes 2 --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

import scenefmt
from benchmark.tools.bench_quality import reference_settings
from generators.pipeline import GenerateConfig, cpu_cores
from generators.presets import Preset
from generators.spec import RenderSettings, SceneSpec
from scenefmt.cli_util import doc_summary

#: Cycles fields the baseline leaves as a factory-reset scene has them, and the
#: RenderSettings field each one is recorded as in the naive split's JSON.
LIGHT_PATH_FIELDS: dict[str, str | None] = {
    "max_bounces": "max_bounces",
    "diffuse_bounces": "diffuse_bounces",
    "glossy_bounces": "glossy_bounces",
    "transmission_bounces": "transmission_bounces",
    "volume_bounces": "volume_bounces",
    "transparent_max_bounces": "transparent_bounces",
    "caustics_reflective": "caustics",
    "caustics_refractive": None,  # RenderSettings has one caustics flag
    "use_adaptive_sampling": None,  # not a RenderSettings field (the JSON says False)
}

#: OpenImageDenoise fields a straightforward script leaves at their factory values (it
#: only switches the denoiser on), and the RenderSettings field each one is recorded as.
DENOISER_FIELDS: dict[str, str | None] = {
    "denoising_input_passes": None,  # RGB_ALBEDO_NORMAL on both sides
    "denoising_prefilter": "denoise_prefilter",
    "denoising_quality": "denoise_quality",
}

#: ``--baseline-denoiser`` choices: ``factory`` = the script switches OIDN on and keeps
#: Blender's defaults (prefilter ACCURATE, quality HIGH): the straightforward script
#: of the 1.5x target; ``tuned`` = a stricter baseline that borrows ``generate``'s denoiser settings.
BASELINE_DENOISERS = ("factory", "tuned")


def check_baseline_denoiser(denoiser: str) -> None:
    """ValueError naming ``--baseline-denoiser`` unless ``denoiser`` is a known choice."""
    if denoiser not in BASELINE_DENOISERS:
        raise ValueError(
            f"baseline_denoiser (--baseline-denoiser) must be one of {BASELINE_DENOISERS}, "
            f"got {denoiser!r}"
        )


def _naive_session_class():
    """:class:`BlenderSession` subclass of the baseline (defined lazily: bpy stays out)."""
    from generators.blender_backend import BlenderSession, quiet_output

    class NaiveSession(BlenderSession):
        """Factory reset before every scene; Blender's default light paths (and, with
        ``denoiser="factory"``, its default denoiser settings)."""

        def __init__(self, threads: int = 1, denoiser: str = "factory") -> None:
            check_baseline_denoiser(denoiser)
            super().__init__(threads=threads)
            self.fields = dict(LIGHT_PATH_FIELDS)
            if denoiser == "factory":
                self.fields.update(DENOISER_FIELDS)
            self.factory_resets = 0
            self.light_path: dict[str, Any] = {}
            self.denoiser: dict[str, Any] = {}
            self.rna_defaults: dict[str, Any] = {}

        def build(self, spec: SceneSpec) -> None:
            with quiet_output():
                self.bpy.ops.wm.read_factory_settings(use_empty=True)
            self.factory_resets += 1
            c = self.bpy.context.scene.cycles
            self._factory = {k: getattr(c, k) for k in self.fields}
            super().build(spec)

        def _configure(self, render: RenderSettings) -> None:
            super()._configure(render)
            c = self.bpy.context.scene.cycles
            for k, v in self._factory.items():
                setattr(c, k, v)
            self.light_path = {k: getattr(c, k) for k in LIGHT_PATH_FIELDS}
            self.denoiser = {k: getattr(c, k) for k in DENOISER_FIELDS}
            rna = type(c).bl_rna.properties  # recorded to show factory == RNA default
            self.rna_defaults = {k: rna[k].default for k in self.fields}

        def rendered_settings(self, render: RenderSettings) -> RenderSettings:
            """``render`` with the light-path and denoiser values this session really used."""
            used = {**self.light_path, **self.denoiser}
            kw = {f: used[k] for k, f in {**LIGHT_PATH_FIELDS, **DENOISER_FIELDS}.items() if f}
            return replace(render, **kw)

    return NaiveSession


def _render_split(
    sess, specs: list[SceneSpec], out_dir: str | os.PathLike, preset: Preset | None
) -> float:
    """Render and write ``specs`` with ``sess`` as ``render_one`` does; Cycles seconds."""
    from generators.imageops import linear_to_srgb8
    from generators.writer import ViewImages, manifest, write_scene

    render_s = 0.0
    gray = preset.name if preset is not None and preset.grayscale else None
    written = None
    for spec in specs:
        passes = sess.render_scene(spec)
        render_s += sum(v.render_s for v in passes)
        views = [ViewImages(linear_to_srgb8(v.rgb_linear), v.ids, v.depth_z) for v in passes]
        if hasattr(sess, "rendered_settings"):  # the JSON records what was rendered
            spec = spec.with_render(sess.rendered_settings(spec.render))
        write_scene(scenefmt.SplitLayout(out_dir, n_views=spec.n_views), spec, views,
                    grayscale_preset=gray)  # fmt: skip
        written = spec
    if preset is not None and written is not None:
        s = written
        m = manifest(preset, s.split, len(specs), s.render.resolution, s.seed, s.render,
                     "complete")  # fmt: skip
        scenefmt.atomic_write_json(Path(out_dir) / "manifest.json", m.to_json())
    return render_s


def naive_render_split(
    specs: list[SceneSpec],
    out_dir: str | os.PathLike,
    threads: int,
    *,
    preset: Preset | None = None,
    denoiser: str = "factory",
) -> dict[str, Any]:
    """The straightforward bpy script: render and write ``specs`` in this process.

    For every scene: ``read_factory_settings(use_empty=True)``, build the scene
    (``BlenderSession.build``), Cycles CPU with ``threads`` threads at the spec's
    samples with OpenImageDenoise, light paths (bounces, caustics, adaptive sampling)
    and (``denoiser="factory"``) the denoiser's prefilter and quality as the
    factory-reset scene has them; every view is written with
    ``writer.write_scene`` (the same files as ``generate``; the JSON records the
    bounces really used).

    Args:
        specs: scenes to render (their ``render`` gives resolution, samples, denoiser).
        out_dir: split folder to write.
        threads: Cycles threads (>= 1), all cores for the baseline.
        preset: if given, ``manifest.json`` is written too (as ``generate`` does).
        denoiser: one of :data:`BASELINE_DENOISERS` (``factory``: Blender's defaults;
            ``tuned``: the spec's own prefilter and quality).

    Returns:
        ``{"scenes", "views", "render_s" (Cycles seconds), "factory_resets",
        "light_path" / "denoiser" (Cycles field -> value rendered with),
        "rna_defaults" (the factory-kept fields' RNA defaults)}``.
    """
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    sess = _naive_session_class()(threads=threads, denoiser=denoiser)
    try:
        render_s = _render_split(sess, specs, out_dir, preset)
    finally:
        sess.close()
    return {"scenes": len(specs), "views": sum(s.n_views for s in specs), "render_s": render_s,
            "factory_resets": sess.factory_resets, "light_path": sess.light_path,
            "denoiser": sess.denoiser, "rna_defaults": sess.rna_defaults}  # fmt: skip


def _specs(cfg: GenerateConfig) -> list[SceneSpec]:
    """The scenes ``generate_dataset(cfg)`` renders (``render_one``'s arguments)."""
    from generators.sampling import make_scene

    p, split, render = cfg.preset_obj(), cfg.split_name(), cfg.render_settings()
    return [make_scene(p, split, i, cfg.seed, render) for i in cfg.indices()]


# ---------------------------------------------------------------------------- driver


def _run(cmd: list[str]) -> float:
    """Wall seconds of ``cmd`` (a fresh process); RuntimeError with its last line on failure."""
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        tail = (r.stderr or r.stdout).strip().splitlines()[-1:] or ["(no output)"]
        raise RuntimeError(f"{cmd[2]} failed (status {r.returncode}): {tail[0]}")
    return wall


def _files(root: Path) -> list[str]:
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())


def _load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def compare(
    preset_name: str = "clevr567",
    n_scenes: int = 20,
    resolution: int = 128,
    ref_samples: int = 512,
    threads: int | None = None,
    workers: int | None = None,
    out_root: str | os.PathLike | None = None,
    psnr_scenes: int = 2,
    *,
    samples: int = RenderSettings.samples,
    seed: int = 0,
    generate_samples: int | None = None,
    baseline_denoiser: str = "factory",
) -> dict[str, Any]:
    """Time ``generate`` and the naive script on the same scenes; PSNR and exactness.

    Args:
        preset_name: preset of the scenes (its first split, as ``generate``).
        n_scenes: scenes (>= 1), each with the preset's views.
        resolution: square image size.
        ref_samples: samples of the no-denoiser reference (>= 1).
        threads: Cycles threads of the naive script (default all cores).
        workers: ``generate --workers`` (default None: the shipped default).
        out_root: its ``generate/``, ``naive/`` and ``reference/`` folders are replaced
            (default a temporary folder, deleted afterwards).
        psnr_scenes: the first this many scenes are compared with the reference.
        samples: samples of both timed sides (default the shipped setting).
        generate_samples: samples of the ``generate`` side only (default ``samples``): the
            equal-PSNR comparison, e.g. ``generate`` at 4 against the naive script at 8.
        seed: dataset seed.
        baseline_denoiser: one of :data:`BASELINE_DENOISERS`: ``factory`` (default) is
            the straightforward script, which switches OpenImageDenoise on and keeps
            Blender's prefilter and quality; ``tuned`` gives it ``generate``'s.

    Returns:
        Plain-JSON dict: ``generate`` / ``naive`` (``wall_s``, ``s_per_view``,
        ``psnr_db``), ``speedup`` (naive wall / generate wall), ``masks_identical``,
        ``depth_identical``, ``same_files``, ``settings``, ``machine``, ``load_before`` /
        ``load_after`` (1/5/15-min load averages).

    Raises:
        ValueError: a bad argument (named). RuntimeError: a subprocess failed.
    """
    if not isinstance(n_scenes, int) or n_scenes < 1:
        raise ValueError(f"n_scenes (--n) must be an integer >= 1, got {n_scenes!r}")
    if ref_samples < 1:
        raise ValueError(f"ref_samples (--ref-samples) must be >= 1, got {ref_samples}")
    if not 1 <= psnr_scenes <= n_scenes:
        raise ValueError(
            f"psnr_scenes (--psnr-scenes) must be in [1, n_scenes={n_scenes}], got {psnr_scenes}"
        )
    check_baseline_denoiser(baseline_denoiser)
    gen_samples = samples if generate_samples is None else generate_samples
    if gen_samples < 1:
        raise ValueError(f"generate_samples (--generate-samples) must be >= 1, got {gen_samples}")
    threads = cpu_cores() if threads is None else threads
    if threads < 1:
        raise ValueError(f"threads (--threads) must be >= 1, got {threads}")
    cfg = GenerateConfig(preset=preset_name, n=n_scenes, resolution=resolution, seed=seed,
                         samples=samples, workers=workers, progress=False)  # fmt: skip
    tmp = None if out_root is not None else tempfile.mkdtemp(prefix="bench_baseline_")
    root = Path(out_root if out_root is not None else tmp)
    dirs = {k: root / k for k in ("generate", "naive", "reference")}
    for d in dirs.values():
        shutil.rmtree(d, ignore_errors=True)
    stats_path = root / "naive_stats.json"
    stats_path.unlink(missing_ok=True)
    common = ["--preset", preset_name, "--n", str(n_scenes), "--resolution", str(resolution),
              "--seed", str(seed), "--samples", str(samples)]  # fmt: skip
    me = [sys.executable, "-m", "benchmark.tools.bench_baseline", *common]
    try:
        load_before = _load()
        gen_cmd = [sys.executable, "-m", "generators.cli", *common[:-1], str(gen_samples),
                   "--split", cfg.split_name(), "--out", str(dirs["generate"]),
                   "--no-progress"]  # fmt: skip
        gen_wall = _run(gen_cmd + (["--workers", str(workers)] if workers else []))
        naive_wall = _run([*me, "--threads", str(threads), "--naive-only", str(dirs["naive"]),
                           "--baseline-denoiser", baseline_denoiser,
                           "--stats", str(stats_path)])  # fmt: skip
        load_after = _load()  # the reference render is not part of the timing
        _run([*me, "--threads", str(threads), "--psnr-scenes", str(psnr_scenes),
              "--ref-samples", str(ref_samples), "--reference-only", str(dirs["reference"])])  # fmt: skip
        naive_stats = scenefmt.read_json(stats_path)
        result = _evaluate(cfg, dirs, psnr_scenes)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    views = n_scenes * cfg.preset_obj().camera.n_views
    result["generate"].update(wall_s=round(gen_wall, 3), s_per_view=gen_wall / views)
    result["naive"].update(wall_s=round(naive_wall, 3), s_per_view=naive_wall / views,
                           render_s=naive_stats["render_s"],
                           factory_resets=naive_stats["factory_resets"])  # fmt: skip
    result.update(
        speedup=naive_wall / gen_wall,
        settings={
            "preset": cfg.preset, "split": cfg.split_name(), "n_scenes": n_scenes, "views": views,
            "resolution": resolution, "seed": seed, "psnr_scenes": psnr_scenes,
            "generate": {"command": " ".join(gen_cmd[1:]), "workers": cfg.n_workers(),
                         "threads": cfg.n_threads(),
                         "render": replace(cfg, samples=gen_samples).render_settings().to_json()},
            "naive": {"threads": threads, "light_path": naive_stats["light_path"],
                      "baseline_denoiser": baseline_denoiser,
                      "denoiser": naive_stats["denoiser"],
                      "rna_defaults": naive_stats["rna_defaults"],
                      "render": naive_stats["render"]},
            "reference": reference_settings(cfg.render_settings(), ref_samples).to_json(),
        },
        machine={"cores": cpu_cores(), "cpu_count": os.cpu_count(),
                 "platform": platform.platform(), "python": platform.python_version()},
        load_before=load_before, load_after=load_after,
    )  # fmt: skip
    return result


def _evaluate(cfg: GenerateConfig, dirs: dict[str, Path], psnr_scenes: int) -> dict[str, Any]:
    """PSNR of both sides' PNGs against the reference; exact masks/ids/depth equality."""
    from benchmark.tools.bench_quality import psnr8

    nv = cfg.preset_obj().camera.n_views
    lay = {k: scenefmt.SplitLayout(d, n_views=nv) for k, d in dirs.items()}
    for k in ("generate", "naive"):
        missing = [i for i in cfg.indices() if not scenefmt.is_scene_complete(lay[k], i)]
        if missing:
            raise RuntimeError(f"{k}: scenes {missing} were not written to {dirs[k]}")
    psnr: dict[str, list[float]] = {"generate": [], "naive": []}
    for i in cfg.indices()[:psnr_scenes]:
        for v in range(nv):
            ref = scenefmt.read_rgb(lay["reference"].rgb(i, v))
            for k, vals in psnr.items():
                vals.append(psnr8(scenefmt.read_rgb(lay[k].rgb(i, v)), ref))
    g, n = lay["generate"], lay["naive"]
    masks = ids = depth = True
    for i in cfg.indices():
        for v in range(nv):
            masks &= np.array_equal(_png(g.mask(i, v)), _png(n.mask(i, v)))
            ids &= np.array_equal(scenefmt.read_instances(g.instances(i, v)),
                                  scenefmt.read_instances(n.instances(i, v)))  # fmt: skip
            depth &= np.array_equal(scenefmt.read_depth_exr(g.depth(i, v)),
                                    scenefmt.read_depth_exr(n.depth(i, v)), equal_nan=True)  # fmt: skip
    return {
        **{k: {"psnr_db": float(np.mean(p)), "psnr_db_per_view": p} for k, p in psnr.items()},
        "masks_identical": bool(masks and ids), "depth_identical": bool(depth),
        "same_files": _files(dirs["generate"]) == _files(dirs["naive"]),
    }  # fmt: skip


def _png(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im)


# ---------------------------------------------------------------------------- CLI


def _subprocess_role(a: argparse.Namespace, cfg: GenerateConfig) -> int:
    """``--naive-only`` / ``--reference-only``: the bpy side, run by :func:`compare`."""
    specs = _specs(cfg)
    if a.naive_only:
        st = naive_render_split(specs, a.naive_only, a.threads, preset=cfg.preset_obj(),
                                denoiser=a.baseline_denoiser)  # fmt: skip
        st["render"] = json.loads(Path(a.naive_only, "manifest.json").read_text())["render"]
        if a.stats:
            scenefmt.atomic_write_json(a.stats, st)
        return 0
    from generators.blender_backend import BlenderSession

    ref = reference_settings(cfg.render_settings(), a.ref_samples)
    sess = BlenderSession(threads=a.threads)
    try:
        _render_split(sess, [s.with_render(ref) for s in specs[: a.psnr_scenes]],
                      a.reference_only, None)  # fmt: skip
    finally:
        sess.close()
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmark.tools.bench_baseline",
                                 description=doc_summary(__doc__))  # fmt: skip
    ap.add_argument("--preset", default="clevr567", help="preset (its first split)")
    ap.add_argument("--n", type=int, default=20, help="scenes rendered by each side")
    ap.add_argument("--resolution", type=int, default=128, help="square image size")
    ap.add_argument("--samples", type=int, default=RenderSettings.samples,
                    help=f"samples of both timed sides (default {RenderSettings.samples})")  # fmt: skip
    ap.add_argument("--generate-samples", type=int, default=None,
                    help="samples of the generate side only (equal-PSNR comparison; "
                         "default --samples)")  # fmt: skip
    ap.add_argument("--seed", type=int, default=0, help="dataset seed")
    ap.add_argument("--baseline-denoiser", choices=BASELINE_DENOISERS, default="factory",
                    help="the script's OIDN prefilter/quality: Blender's defaults (factory, "
                         "the straightforward script) or generate's (tuned); default factory")  # fmt: skip
    ap.add_argument("--ref-samples", type=int, default=512, help="reference samples (no denoiser)")
    ap.add_argument("--psnr-scenes", type=int, default=2, help="first scenes compared for PSNR")
    ap.add_argument("--threads", type=int, default=None,
                    help="Cycles threads of the naive script (default all cores)")  # fmt: skip
    ap.add_argument("--workers", type=int, default=None,
                    help="generate --workers (default: generate's own default)")  # fmt: skip
    ap.add_argument("--out-root", default=None,
                    help="keep the three split folders here (default a deleted temp folder)")  # fmt: skip
    ap.add_argument("--json", default=None, help="also write the result to this JSON file")
    ap.add_argument("--naive-only", metavar="DIR", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--reference-only", metavar="DIR", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--stats", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    try:
        if a.naive_only or a.reference_only:
            a.threads = a.threads or cpu_cores()
            cfg = GenerateConfig(preset=a.preset, n=a.n, resolution=a.resolution, seed=a.seed,
                                 samples=a.samples, progress=False)  # fmt: skip
            return _subprocess_role(a, cfg)
        r = compare(a.preset, a.n, a.resolution, a.ref_samples, a.threads, a.workers,
                    a.out_root, a.psnr_scenes, samples=a.samples, seed=a.seed,
                    generate_samples=a.generate_samples,
                    baseline_denoiser=a.baseline_denoiser)  # fmt: skip
    except (ValueError, RuntimeError, ImportError) as e:
        print(f"bench_baseline: error: {str(e).splitlines()[0]}", file=sys.stderr)
        return 2
    if a.json:
        scenefmt.atomic_write_json(a.json, r)
    g, nv = r["generate"], r["naive"]
    print(f"generate {g['s_per_view']:.3f} s/view {g['psnr_db']:.2f} dB | naive "
          f"{nv['s_per_view']:.3f} s/view {nv['psnr_db']:.2f} dB | speedup {r['speedup']:.2f}x | "
          f"masks {r['masks_identical']} depth {r['depth_identical']}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
