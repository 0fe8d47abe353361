"""``generate_dataset(cfg)``: the importable generator (the ``generate`` CLI wraps it).

Data flow::

    GenerateConfig -> for each scene index of this shard (skipping complete ones):
        sampling.make_scene (pure Python, seeded) -> blender_backend.BlenderSession
        (one per worker process, recycled every ``recycle_after`` scenes)
        -> imageops (linear -> sRGB 8-bit, optional Rec.601 grey) -> writer
    -> GenerateSummary

``manifest.json`` is written first (it describes the target split, identical for
every shard); scenes are complete only once their ``sc%04d.json`` exists, so a
killed run resumes where it stopped. ``clevr567-gray`` converts the matching
``clevr567`` render (sibling folder ``<out>/../../clevr567/<split>`` or
``cfg.source``) instead of rendering again when that scene is there.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field, replace
from multiprocessing import get_context
from pathlib import Path

from generators.imageops import GRAYSCALE_FORMULA, grayscale_rec601, linear_to_srgb8
from generators.presets import Preset, get_preset
from generators.spec import RenderSettings, SceneSpec
from generators.writer import ViewImages, manifest, write_scene
from scenefmt import (
    SplitLayout,
    atomic_write_bytes,
    atomic_write_json,
    is_scene_complete,
    read_json,
    read_rgb,
    write_rgb,
)

__all__ = ["GenerateConfig", "GenerateSummary", "cpu_cores", "default_out", "generate_dataset"]

_DEFAULT = RenderSettings()


def cpu_cores() -> int:
    """CPU cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def default_out(preset: str, split: str) -> Path:
    """``data/{preset}/{split}`` (relative to the working directory)."""
    return Path("data") / preset / split


@dataclass(frozen=True)
class GenerateConfig:
    """What to generate (every field is a ``generate`` CLI option).

    Attributes:
        preset: registered preset name (``generators.presets.PRESETS``).
        split: ``train`` or ``test``; None = the preset's first split.
        n: scenes in the split (indices 0..n-1); None = the preset's split size.
        out: split folder; None = ``data/{preset}/{split}``.
        resolution: square image size in pixels (>= 16).
        seed: dataset seed (>= 0); scene seeds derive from it.
        samples: Cycles samples per pixel.
        denoise: OpenImageDenoise on the colour pass.
        bounces: max light bounces (total and diffuse).
        workers: worker processes; None = cores // 2 (>= 1). 1 renders in this process.
        threads: Cycles threads per worker; None = cores // workers (>= 1).
        shard: (i, n): render only scene indices with ``index % n == i``.
        progress: tqdm progress bar and end summary on stderr.
        recycle_after: scenes per Blender session before it is restarted.
        source: folder of the ``scene_source`` preset's split whose renders a derived
            preset (``clevr567-gray``) converts; None = the sibling default.
    """

    preset: str = "clevr567"
    split: str | None = None
    n: int | None = None
    out: Path | None = None
    resolution: int = 128
    seed: int = 0
    samples: int = _DEFAULT.samples
    denoise: bool = _DEFAULT.denoise
    bounces: int = _DEFAULT.max_bounces
    workers: int | None = None
    threads: int | None = None
    shard: tuple[int, int] = (0, 1)
    progress: bool = True
    recycle_after: int = 40
    source: Path | None = None

    def __post_init__(self) -> None:
        p = get_preset(self.preset)  # ValueError listing the known presets
        if self.split is not None:
            p.split_size(self.split)  # ValueError naming the preset's splits
        if self.n is not None and int(self.n) <= 0:
            raise ValueError(f"n (--n) must be a positive scene count, got {self.n}")
        if self.n is not None and int(self.n) > 10_000:
            raise ValueError(f"n (--n) must be <= 10000 (sc%04d file names), got {self.n}")
        if int(self.resolution) < 16:
            raise ValueError(f"resolution (--resolution) must be >= 16, got {self.resolution}")
        if int(self.seed) < 0:
            raise ValueError(f"seed (--seed) must be >= 0, got {self.seed}")
        if int(self.samples) < 1:
            raise ValueError(f"samples (--samples) must be >= 1, got {self.samples}")
        if int(self.bounces) < 0:
            raise ValueError(f"bounces (--bounces) must be >= 0, got {self.bounces}")
        if self.workers is not None and int(self.workers) < 1:
            raise ValueError(f"workers (--workers) must be >= 1, got {self.workers}")
        if self.threads is not None and int(self.threads) < 1:
            raise ValueError(f"threads must be >= 1, got {self.threads}")
        i, n = self.shard
        if not (n >= 1 and 0 <= i < n):
            raise ValueError(f"shard (--shard i/n) needs 0 <= i < n, got {i}/{n}")
        if self.recycle_after < 1:
            raise ValueError(f"recycle_after must be >= 1, got {self.recycle_after}")

    # ------------------------------------------------------------- resolved values

    def preset_obj(self) -> Preset:
        return get_preset(self.preset)

    def split_name(self) -> str:
        return self.split if self.split is not None else self.preset_obj().split_names()[0]

    def n_scenes(self) -> int:
        return (
            int(self.n) if self.n is not None else self.preset_obj().split_size(self.split_name())
        )

    def out_dir(self) -> Path:
        return (
            Path(self.out) if self.out is not None else default_out(self.preset, self.split_name())
        )

    def n_workers(self) -> int:
        # Measured on 2 cores (docs/format.md, ENV.md): one 2-thread Cycles process beats
        # two 1-thread processes (1.38 vs 1.99 s/view), so pair cores per worker.
        return int(self.workers) if self.workers is not None else max(1, cpu_cores() // 2)

    def n_threads(self) -> int:
        if self.threads is not None:
            return int(self.threads)
        return max(1, cpu_cores() // self.n_workers())

    def render_settings(self) -> RenderSettings:
        b = int(self.bounces)
        return replace(
            _DEFAULT,
            resolution=int(self.resolution),
            samples=int(self.samples),
            denoise=bool(self.denoise),
            max_bounces=b,
            diffuse_bounces=min(_DEFAULT.diffuse_bounces, b),
            glossy_bounces=min(_DEFAULT.glossy_bounces, b),
        )

    def source_dir(self) -> Path | None:
        p = self.preset_obj()
        if p.scene_source is None:
            return None
        if self.source is not None:
            return Path(self.source)
        return self.out_dir().parent.parent / p.scene_source / self.split_name()


@dataclass(frozen=True)
class GenerateSummary:
    """What one ``generate_dataset`` call did.

    Attributes:
        out: the split folder.
        n_scenes: scenes in the split (all shards).
        scenes_this_run: scenes of this shard that were missing and were made now.
        scenes_skipped: scenes of this shard already complete on disk.
        scenes_converted: scenes made by converting a source render (no Cycles).
        n_views: views per scene.
        wall_s: wall time of the call.
        render_s: summed seconds inside Cycles' render calls.
        s_per_view: wall seconds per view made now (nan if none).
        render_s_per_view: Cycles seconds per rendered view (nan if none).
    """

    out: Path
    preset: str
    split: str
    n_scenes: int
    scenes_this_run: int
    scenes_skipped: int
    scenes_converted: int
    n_views: int
    wall_s: float
    render_s: float
    views_rendered: int
    workers: int
    threads: int
    s_per_view: float = float("nan")
    render_s_per_view: float = float("nan")
    indices: tuple[int, ...] = field(default=(), repr=False)

    def line(self) -> str:
        """One-line human summary."""
        return (
            f"{self.preset}/{self.split}: {self.scenes_this_run} scenes "
            f"({self.scenes_this_run * self.n_views} views) made, {self.scenes_skipped} already "
            f"complete, in {self.wall_s:.1f} s = {self.s_per_view:.3f} s/view "
            f"(Cycles {self.render_s_per_view:.3f} s/view; {self.workers} worker(s) x "
            f"{self.threads} thread(s)) -> {self.out}"
        )


# --------------------------------------------------------------------------- checks


def check_writable(out: Path) -> None:
    """ValueError unless ``out`` exists as a writable folder or can be created."""
    p = Path(out).absolute()
    if p.exists() and not p.is_dir():
        raise ValueError(f"out (--out) {out} exists and is not a folder")
    q = p
    while not q.exists():
        q = q.parent
    if not q.is_dir() or not os.access(q, os.W_OK | os.X_OK):
        raise ValueError(f"out (--out) {out} is not writable ({q} does not allow writing)")
    # os.access says yes to root everywhere: probe with a real (deleted) temp folder.
    try:
        probe = Path(tempfile.mkdtemp(prefix=".generate-probe-", dir=q))
        probe.rmdir()
    except OSError as e:
        raise ValueError(f"out (--out) {out} is not writable ({q}: {e.strerror})") from None


# --------------------------------------------------------------------------- one scene


@dataclass(frozen=True)
class _Job:
    preset: str
    split: str
    index: int
    seed: int
    render: RenderSettings
    out: Path
    source: Path | None


_SESSION = None  # the worker process's BlenderSession
_SESSION_SCENES = 0


def _session(threads: int, recycle_after: int):
    global _SESSION, _SESSION_SCENES
    if _SESSION is not None and _SESSION_SCENES >= recycle_after:
        _SESSION.close()
        _SESSION = None
    if _SESSION is None:
        from generators.blender_backend import BlenderSession

        _SESSION = BlenderSession(threads=threads)
        _SESSION_SCENES = 0
    _SESSION_SCENES += 1
    return _SESSION


def close_session() -> None:
    """Close this process's Blender session (if any)."""
    global _SESSION
    if _SESSION is not None:
        _SESSION.close()
        _SESSION = None


def _convert_from_source(job: _Job, spec: SceneSpec, layout: SplitLayout) -> SceneSpec | None:
    """Write a grey scene by converting the source preset's render; None if unusable."""
    if job.source is None:
        return None
    src = SplitLayout(job.source, n_views=layout.n_views)
    if not is_scene_complete(src, job.index):
        return None
    try:
        meta = read_json(src.scene_json(job.index))
        same = (
            int(meta["scene_seed"]) == spec.scene_seed
            and int(meta["attempt"]) == spec.attempt
            and int(meta["render"]["width"]) == job.render.resolution
        )
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if not same:
        return None
    src_render = RenderSettings.from_json(meta["render"])
    s = job.index
    for v in range(layout.n_views):
        write_rgb(layout.rgb(s, v), grayscale_rec601(read_rgb(src.rgb(s, v))))
        for a, b in zip(src.view_files(s, v)[1:], layout.view_files(s, v)[1:], strict=True):
            atomic_write_bytes(b, a.read_bytes())
    out = replace(spec, render=src_render, extra=spec.extra + (("rgb_source", "converted"),))
    atomic_write_json(
        layout.scene_json(s), out.to_json([layout.rgb(s, v).name for v in range(layout.n_views)])
    )
    return out


def render_one(job: _Job, threads: int, recycle_after: int) -> dict:
    """Sample, render and write one scene (runs in a worker process or in-process).

    Returns:
        ``{"index", "views", "render_s", "wall_s", "converted"}``.
    """
    from generators.sampling import make_scene

    t0 = time.perf_counter()
    preset = get_preset(job.preset)
    layout = SplitLayout(job.out, n_views=preset.camera.n_views)
    spec = make_scene(preset, job.split, job.index, job.seed, job.render)
    spec = replace(spec, preset=preset.name)
    if preset.grayscale:
        spec = replace(spec, extra=(("grayscale", GRAYSCALE_FORMULA),))
        if _convert_from_source(job, spec, layout) is not None:
            return {"index": job.index, "views": 0, "render_s": 0.0,
                    "wall_s": time.perf_counter() - t0, "converted": True}  # fmt: skip
        spec = replace(spec, extra=spec.extra + (("rgb_source", "rendered"),))
    sess = _session(threads, recycle_after)
    passes = sess.render_scene(spec)
    views = []
    for p in passes:
        rgb8 = linear_to_srgb8(p.rgb_linear)
        if preset.grayscale:
            rgb8 = grayscale_rec601(rgb8)
        views.append(ViewImages(rgb8, p.ids, p.depth_z))
    write_scene(layout, spec, views)
    return {
        "index": job.index,
        "views": len(views),
        "render_s": float(sum(p.render_s for p in passes)),
        "wall_s": time.perf_counter() - t0,
        "converted": False,
    }


def _worker_init() -> None:
    import signal
    import sys

    # Workers ignore Ctrl-C; the parent cancels them.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # spawn copies the parent's sys.path; if the parent imported bpy, that holds
    # bpy's own scripts/modules folder, whose ``bpy`` package would shadow the real
    # module (-> "No module named '_bpy'"). bpy re-adds these paths on import.
    marker = os.sep + "bpy" + os.sep
    sys.path[:] = [p for p in sys.path if marker not in p]


# --------------------------------------------------------------------------- driver


def generate_dataset(cfg: GenerateConfig) -> GenerateSummary:
    """Generate (or complete) one split folder.

    Args:
        cfg: what to make (validated on construction).

    Returns:
        :class:`GenerateSummary`.

    Raises:
        ValueError: bad config (unknown preset, bad count, unwritable folder, ...);
            nothing is written.
        generators.blender_backend.BpyMissingError (an ImportError): bpy missing;
            nothing is written.
        RuntimeError: a scene failed to render (completed scenes stay on disk).
    """
    from generators.blender_backend import BpyMissingError, bpy_available

    t0 = time.perf_counter()
    preset = cfg.preset_obj()
    split = cfg.split_name()
    n = cfg.n_scenes()
    out = cfg.out_dir()
    render = cfg.render_settings()
    check_writable(out)
    layout = SplitLayout(out, n_views=preset.camera.n_views)
    i_shard, n_shard = cfg.shard
    indices = [s for s in range(n) if s % n_shard == i_shard]
    todo = [s for s in indices if not is_scene_complete(layout, s)]
    source = cfg.source_dir()
    need_bpy = bool(todo) and not (
        source is not None
        and all(is_scene_complete(SplitLayout(source, layout.n_views), s) for s in todo)
    )
    if need_bpy and not bpy_available():
        raise BpyMissingError(
            "cannot import bpy; install Blender's Python module: pip install bpy==5.0.1 "
            "(Python 3.11, numpy<2)"
        )
    mf = manifest(preset, split, n, render.resolution, cfg.seed, render)
    if layout.manifest.is_file():
        try:
            old = read_json(layout.manifest)
        except (OSError, ValueError):
            old = {}
        for key in ("preset", "split", "seed", "resolution", "n_views"):
            if key in old and old[key] != mf[key]:
                raise ValueError(
                    f"out (--out) {out} holds {key}={old[key]!r}, this run asks for "
                    f"{mf[key]!r}; pass another --out or delete the folder"
                )
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(f"out (--out) {out} cannot be created ({e.strerror})") from None
    mf = manifest(preset, split, n, render.resolution, cfg.seed, render)
    if not layout.manifest.is_file() or read_json(layout.manifest) != mf:
        atomic_write_json(layout.manifest, mf)

    jobs = [_Job(preset.name, split, s, int(cfg.seed), render, out, source) for s in todo]
    workers = max(1, min(cfg.n_workers(), len(jobs)))
    threads = cfg.n_threads()
    results: list[dict] = []
    from tqdm import tqdm

    bar = tqdm(
        total=len(jobs), unit="scene", disable=not cfg.progress or not jobs,
        desc=f"{preset.name}/{split}", dynamic_ncols=True,
    )  # fmt: skip
    try:
        if workers == 1:
            try:
                for job in jobs:
                    results.append(render_one(job, threads, cfg.recycle_after))
                    bar.update(1)
            finally:
                close_session()
        else:
            ctx = get_context("spawn")  # bpy is not fork-safe
            with ProcessPoolExecutor(
                max_workers=workers, mp_context=ctx, initializer=_worker_init,
                max_tasks_per_child=cfg.recycle_after,
            ) as pool:  # fmt: skip
                futs = {pool.submit(render_one, j, threads, cfg.recycle_after): j for j in jobs}
                pending = set(futs)
                while pending:
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for f in done:
                        err = f.exception()
                        if err is not None:
                            for p in pending:
                                p.cancel()
                            raise RuntimeError(
                                f"scene {futs[f].index} failed: {type(err).__name__}: {err}"
                            ) from err
                        results.append(f.result())
                        bar.update(1)
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    n_views_made = sum(r["views"] for r in results)
    made_views = len(results) * preset.camera.n_views
    render_s = float(sum(r["render_s"] for r in results))
    summary = GenerateSummary(
        out=out,
        preset=preset.name,
        split=split,
        n_scenes=n,
        scenes_this_run=len(results),
        scenes_skipped=len(indices) - len(todo),
        scenes_converted=sum(bool(r["converted"]) for r in results),
        n_views=preset.camera.n_views,
        wall_s=wall,
        render_s=render_s,
        views_rendered=n_views_made,
        workers=workers,
        threads=threads,
        s_per_view=wall / made_views if made_views else float("nan"),
        render_s_per_view=render_s / n_views_made if n_views_made else float("nan"),
        indices=tuple(sorted(r["index"] for r in results)),
    )
    return summary


def remove_split(out: Path) -> None:  # pragma: no cover - convenience for notebooks
    """Delete a split folder (only if it holds a manifest: guards against typos)."""
    out = Path(out)
    if not (out / "manifest.json").is_file():
        raise ValueError(f"{out} holds no manifest.json; refusing to delete it")
    shutil.rmtree(out)
