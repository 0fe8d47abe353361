"""Dataset generation: GenerateConfig -> process pool of Blender sessions -> split folder.

Data flow::

    GenerateConfig (validated on construction, writes nothing)
      -> checks: --out writable, an existing manifest describes the same dataset,
         bpy importable when something must be rendered
      -> manifest.json (atomic, "status": "in_progress")
      -> this shard's scene indices minus the complete ones
         -> derived presets: convert complete source scenes (no Cycles)
         -> worker processes (spawn; one BlenderSession each, recycled every
            ``recycle_after`` scenes): make_scene -> render_scene -> write_scene
            (``backend="ray"``: the same task on Ray actors, ``generators.ray_backend``)
      -> manifest.json ("status": "complete" once every scene of the split exists)
      -> GenerateSummary

:func:`generate_dataset` is the importable entry point: the ``generate`` CLI and
the benchmark (``benchmark.generator_bridge``) call it. Nothing here imports bpy;
only the worker processes do (the task :func:`generators.worker.render_one`, re-exported
here), through ``blender_backend``.
"""

from __future__ import annotations

import concurrent.futures as cf
import json
import multiprocessing as mp
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import scenefmt
from generators.presets import PRESETS, Preset, get_preset, scene_preset
from generators.spec import RenderSettings
from generators.worker import close_worker_session, init_worker, render_manip_one, render_one
from generators.writer import manifest
from scenefmt.cli_util import progress_kwargs

MAX_SCENES = 10_000  # sc%04d file names

#: Where scenes are rendered: a local process pool or Ray actors (``generators.ray_backend``).
BACKENDS = ("local", "ray")

#: Manifest keys that identify a dataset: a rerun into the same folder must match them.
IDENTITY_KEYS = (
    "preset", "split", "seed", "resolution", "n_views", "render", "preset_config", "manip",
)  # fmt: skip


def cpu_cores() -> int:
    """CPU cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - non-Linux
        return os.cpu_count() or 1


@dataclass(frozen=True)
class GenerateConfig:
    """One ``generate`` run (CLI flags map 1:1 onto these fields). Validated on creation.

    Attributes:
        preset: preset name (``generators.presets.PRESETS``).
        split: ``train`` / ``test``; default the preset's first split. ``manip``: the
            manipulation split (``generators.manip``: per scene a moved and a
            background-changed variant in uORF's manipulation layout; needs n >= 2).
        n: number of scenes (default: the preset's split size). Scene i does not
            depend on n, so a larger n extends a dataset.
        out: split folder (default ``data/{preset}/{split}``).
        resolution: square image size (>= 16).
        seed: dataset seed (>= 0).
        samples: Cycles samples per pixel.
        denoise: OpenImageDenoise on/off.
        bounces: max light bounces (diffuse bounces are capped by it too).
        workers: worker processes (default ``max(1, cores // 2)``: on 2 cores one
            2-thread Blender beat two 1-thread ones, see ``docs/format.md``).
        threads: Cycles threads per worker (default ``max(1, cores // workers)``).
        shard: ``(i, n)``: only scenes with ``index % n == i``.
        progress: tqdm progress bar on stderr.
        source: derived presets (``clevr567-gray``): the colour split to convert
            (default the sibling folder ``{out}/../../{source preset}/{split}``).
        camera_radius: override the preset's camera radius (closer cameras for
            small CPU-scale datasets); part of the dataset identity.
        recycle_after: scenes per worker process before it is replaced (Blender
            leaks a little memory per scene).
        backend: ``local`` (a process pool on this machine) or ``ray`` (Ray actors on
            a cluster; ``workers``/``threads`` then default to the cluster's CPUs, see
            ``generators.ray_backend.plan``). The bytes written do not depend on it.
        address: Ray cluster address (``auto``, ``host:6379``, ``ray://host:10001``);
            default the ``RAY_ADDRESS`` environment variable, else a local instance.
    """

    preset: str
    split: str | None = None
    n: int | None = None
    out: str | os.PathLike | None = None
    resolution: int = 128
    seed: int = 0
    samples: int = RenderSettings.samples
    denoise: bool = RenderSettings.denoise
    bounces: int = RenderSettings.max_bounces
    workers: int | None = None
    threads: int | None = None
    shard: tuple[int, int] = (0, 1)
    progress: bool = True
    source: str | os.PathLike | None = None
    camera_radius: float | None = None
    recycle_after: int = 40
    backend: str = "local"
    address: str | None = None

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            get_preset(self.preset)  # raises ValueError listing the known presets
        p = PRESETS[self.preset]
        if self.split is not None and self.split not in p.split_names():
            raise ValueError(
                f"--split: preset {p.name!r} has no split {self.split!r} "
                f"(it has: {', '.join(p.split_names())})"
            )
        if self.n is not None and (not isinstance(self.n, int) or self.n < 1):
            raise ValueError(f"--n must be a positive integer, got {self.n!r}")
        if self.n is not None and self.n > MAX_SCENES:
            raise ValueError(f"--n must be <= {MAX_SCENES} (sc%04d file names), got {self.n}")
        if not isinstance(self.resolution, int) or self.resolution < 16:
            raise ValueError(f"--resolution must be an integer >= 16, got {self.resolution!r}")
        if not isinstance(self.seed, int) or not 0 <= self.seed < 9_000_000_000:
            raise ValueError(f"--seed must be an integer in [0, 9e9), got {self.seed!r}")
        if self.samples < 1:
            raise ValueError(f"--samples must be >= 1, got {self.samples}")
        if self.bounces < 0:
            raise ValueError(f"--bounces must be >= 0, got {self.bounces}")
        i, k = self.shard
        if not (k >= 1 and 0 <= i < k):
            raise ValueError(f"--shard must be i/n with 0 <= i < n, got {i}/{k}")
        if self.workers is not None and self.workers < 1:
            raise ValueError(f"--workers must be >= 1, got {self.workers}")
        if self.threads is not None and self.threads < 1:
            raise ValueError(f"--threads must be >= 1, got {self.threads}")
        if self.recycle_after < 1:
            raise ValueError(f"recycle_after must be >= 1, got {self.recycle_after}")
        if self.camera_radius is not None:
            p.with_camera_radius(self.camera_radius)  # validates
        if self.backend not in BACKENDS:
            raise ValueError(
                f"--backend must be one of {', '.join(BACKENDS)}, got {self.backend!r}"
            )
        if self.address is not None and self.backend != "ray":
            raise ValueError("--address is a Ray cluster address; pass it with --backend ray")
        if self.split == scenefmt.MANIP_SPLIT:
            if self.n_scenes() < 2:
                raise ValueError(
                    f"--n must be >= 2 for --split {scenefmt.MANIP_SPLIT} (the background of a "
                    f"scene comes from another scene of the split), got {self.n_scenes()}"
                )
            if self.backend != "local":
                raise ValueError(
                    f"--split {scenefmt.MANIP_SPLIT} renders with --backend local only "
                    "(use --shard i/n to split it over machines)"
                )

    def is_manip(self) -> bool:
        """Whether this is the manipulation split."""
        return self.split_name() == scenefmt.MANIP_SPLIT

    # ---------------------------------------------------------------- resolved values

    def preset_obj(self) -> Preset:
        """The preset, with the camera-radius override applied."""
        p = get_preset(self.preset)
        return p if self.camera_radius is None else p.with_camera_radius(self.camera_radius)

    def split_name(self) -> str:
        return self.split if self.split is not None else get_preset(self.preset).split_names()[0]

    def n_scenes(self) -> int:
        return (
            self.n if self.n is not None else get_preset(self.preset).split_size(self.split_name())
        )

    def out_dir(self) -> Path:
        return (
            Path(self.out)
            if self.out is not None
            else Path("data") / self.preset / self.split_name()
        )

    def render_settings(self) -> RenderSettings:
        d = RenderSettings()
        return replace(
            d, resolution=self.resolution, samples=self.samples, denoise=self.denoise,
            max_bounces=self.bounces, diffuse_bounces=min(d.diffuse_bounces, self.bounces),
        )  # fmt: skip

    def n_workers(self) -> int:
        return self.workers if self.workers is not None else max(1, cpu_cores() // 2)

    def n_threads(self) -> int:
        return self.threads if self.threads is not None else max(1, cpu_cores() // self.n_workers())

    def indices(self) -> tuple[int, ...]:
        """Scene indices of this shard."""
        i, k = self.shard
        return tuple(s for s in range(self.n_scenes()) if s % k == i)

    def source_dir(self) -> Path | None:
        p = get_preset(self.preset)
        if p.scene_source is None:
            return None
        if self.source is not None:
            return Path(self.source)
        return self.out_dir().absolute().parent.parent / p.scene_source / self.split_name()


@dataclass(frozen=True)
class GenerateSummary:
    """What one :func:`generate_dataset` call did.

    Attributes:
        out: the split folder.
        indices: scene indices of this shard.
        scenes_this_run: scenes written now (rendered + converted).
        scenes_converted: of those, made from a source split without Cycles.
        scenes_skipped: complete before the run (not touched).
        views_rendered: views rendered by Cycles now.
        wall_s: wall time of the call.
        render_s: seconds inside Cycles' render calls, summed over workers.
        workers / threads: pool size and Cycles threads per worker.
        complete: every scene of the split (all shards) is complete.
        nodes: machines that rendered scenes now (distinct Ray nodes with ``--backend
            ray``; 1 for the local pool, 0 if nothing was rendered).
    """

    out: Path
    preset: str
    split: str
    n_scenes: int
    indices: tuple[int, ...]
    scenes_this_run: int
    scenes_converted: int
    scenes_skipped: int
    views_rendered: int
    wall_s: float
    render_s: float
    workers: int
    threads: int
    complete: bool
    n_views: int = 4
    failures: tuple[str, ...] = field(default=())
    nodes: int = 1

    @property
    def views_written(self) -> int:
        return self.scenes_this_run * self.n_views

    @property
    def s_per_view(self) -> float:
        """Wall seconds per written view (0 if nothing was written)."""
        return self.wall_s / self.views_written if self.views_written else 0.0

    def _on_nodes(self) -> str:
        return f" on {self.nodes} Ray nodes" if self.nodes > 1 else ""

    def line(self) -> str:
        """One-line human summary."""
        cyc = (
            f"Cycles {self.render_s / self.views_rendered:.3f} s/view; "
            if self.views_rendered
            else ""
        )
        conv = f", {self.scenes_converted} converted" if self.scenes_converted else ""
        return (
            f"{self.preset}/{self.split}: {self.scenes_this_run} scenes ({self.views_written} views) "
            f"made{conv}, {self.scenes_skipped} already complete, in {self.wall_s:.1f} s = "
            f"{self.s_per_view:.3f} s/view ({cyc}{self.workers} worker(s) x {self.threads} "
            f"thread(s){self._on_nodes()}) -> {self.out}"
            + ("" if self.complete else " [split not complete yet]")
        )


# ---------------------------------------------------------------------------- checks


def _check_writable(out: Path) -> None:
    p = out.absolute()
    while not p.exists() and p.parent != p:
        p = p.parent
    if not p.is_dir():
        raise ValueError(
            f"--out: {p} exists and is not a folder; pass a writable folder with --out"
        )
    if not os.access(p, os.W_OK | os.X_OK):
        raise ValueError(f"--out: {p} is not writable; pass a writable folder with --out")


def _identity(m: scenefmt.Manifest) -> dict[str, object]:
    """The :data:`IDENTITY_KEYS` of a manifest as read back from disk (None: absent)."""
    d = json.loads(json.dumps(m.to_json()))  # tuples -> lists
    return {k: d.get(k) for k in IDENTITY_KEYS}


def _read_manifest(path: Path) -> scenefmt.Manifest | None:
    """The manifest at ``path``; None if there is none or it is unreadable JSON.

    Raises:
        ValueError: JSON that is not a manifest (``scenefmt.Manifest.from_json``'s message).
    """
    if not path.is_file():
        return None
    try:
        raw = scenefmt.read_json(path)
    except (OSError, ValueError):
        return None
    return scenefmt.Manifest.from_json(raw)


def _check_existing_manifest(path: Path, new: scenefmt.Manifest) -> None:
    try:
        found = _read_manifest(path)
    except ValueError as e:  # not written by a generator: maybe another dataset
        raise ValueError(
            f"--out: {path.parent} holds a manifest.json that is not a dataset manifest ({e}); "
            "pass another --out or delete that folder"
        ) from e
    if found is None:
        return  # no manifest, or unreadable JSON: rewritten
    old, now = _identity(found), _identity(new)
    diff = [k for k in IDENTITY_KEYS if old[k] != now[k]]
    if diff:
        shown = ", ".join(f"{k} {old[k]!r} vs {now[k]!r}" for k in diff
                          if k not in ("render", "preset_config", "manip"))  # fmt: skip
        if "manip" in diff:  # the donors are drawn from the split's scene count
            n_diff = f"n_scenes {found.n_scenes!r} vs {new.n_scenes!r}"
            shown = ", ".join(x for x in (shown, n_diff) if x)
        raise ValueError(
            f"--out: {path.parent} holds another dataset (different {', '.join(diff)}"
            f"{': ' + shown if shown else ''}); pass another --out or delete that folder"
        )


def _remove_stale_temp_files(layout: scenefmt.SplitLayout, indices: set[int]) -> None:
    """Delete temp files (``.{name}.*.tmp*``) a killed run left for these scenes."""
    for folder in (layout.root, layout.root / "instances", layout.root / "depth"):
        if not folder.is_dir():
            continue
        for f in folder.iterdir():
            if not (f.name.startswith(".") and ".tmp" in f.name):
                continue
            target = f.name[1:].split(".")[0]  # ".00004_sc0001_az00_RT.txt.ab12.tmp" -> stem
            try:
                if target.endswith("_movement"):  # ".003_movement.txt.ab12.tmp"
                    scene = int(target.split("_")[0])
                elif target.startswith("sc"):
                    scene = int(target[2:])
                else:
                    scene = int(target.split("_sc")[1][:4])
            except (ValueError, IndexError):
                continue
            if scene in indices:
                f.unlink(missing_ok=True)


def _usable_source(cfg: GenerateConfig, render: RenderSettings) -> scenefmt.SplitLayout | None:
    """The colour split a derived preset may convert: same scenes, same render settings."""
    src = cfg.source_dir()
    try:
        m = None if src is None else _read_manifest(src / "manifest.json")
    except ValueError:
        return None  # not a manifest: rendered instead
    if m is None:
        return None
    sp = scene_preset(cfg.preset_obj())
    if cfg.camera_radius is not None:
        sp = sp.with_camera_radius(cfg.camera_radius)
    ok = (
        m.preset == sp.name
        and m.split == cfg.split_name()
        and m.seed == cfg.seed
        and m.resolution == cfg.resolution
        and m.n_views == sp.camera.n_views
        and m.extra.get("render") == render.to_json()
        and m.extra.get("preset_config") == json.loads(json.dumps(sp.to_json()))
    )
    return scenefmt.SplitLayout(src, n_views=sp.camera.n_views) if ok else None


# ---------------------------------------------------------------------------- driver


def generate_dataset(cfg: GenerateConfig) -> GenerateSummary:
    """Generate (or finish) one split; the function behind ``generate``.

    Resumable: complete scenes (``scenefmt.is_scene_complete``) are skipped and not
    touched, so a killed run finishes when run again. Deterministic: scenes, ids,
    masks, depth and JSON do not depend on ``workers``/``threads``/``shard``.

    Args:
        cfg: the run configuration.

    Returns:
        A :class:`GenerateSummary`.

    Raises:
        ValueError: bad ``--out`` or a folder holding another dataset (nothing written).
        generators.blender_backend.BpyMissingError (an ImportError): bpy is needed
            but not installed (nothing written).
    """
    t0 = time.perf_counter()
    preset = cfg.preset_obj()
    split, n, out = cfg.split_name(), cfg.n_scenes(), cfg.out_dir()
    render = cfg.render_settings()
    _check_writable(out)
    manip = cfg.is_manip()
    if manip:
        from generators.manip_writer import manip_manifest

        layout: scenefmt.SplitLayout = scenefmt.ManipLayout(out, n_views=preset.camera.n_views)

        def make_manifest(status: str) -> scenefmt.Manifest:
            return manip_manifest(preset, n, cfg.resolution, cfg.seed, render, status)
    else:
        layout = scenefmt.SplitLayout(out, n_views=preset.camera.n_views)

        def make_manifest(status: str) -> scenefmt.Manifest:
            return manifest(preset, split, n, cfg.resolution, cfg.seed, render, status)

    new_manifest = make_manifest("in_progress")
    _check_existing_manifest(layout.manifest, new_manifest)

    indices = cfg.indices()
    todo = [i for i in indices if not scenefmt.is_scene_complete(layout, i)]
    convert: list[int] = []
    if preset.scene_source and todo:
        src = _usable_source(cfg, render)
        if src is not None:
            convert = [i for i in todo if scenefmt.is_scene_complete(src, i)]
    convert_set = set(convert)
    to_render = [i for i in todo if i not in convert_set]
    if to_render and cfg.backend == "ray":
        from generators.ray_backend import import_ray

        import_ray()  # missing ray: one-line error before anything is written
    elif to_render:  # (Ray workers may run on other nodes: they check bpy themselves)
        from generators import blender_backend

        if not blender_backend.bpy_available():
            raise blender_backend.BpyMissingError(
                "bpy (Blender as a Python module) is not installed; fix: pip install bpy==5.0.1 "
                "(Python 3.11, numpy<2)"
            )

    out.mkdir(parents=True, exist_ok=True)
    scenefmt.atomic_write_json(layout.manifest, new_manifest.to_json())
    _remove_stale_temp_files(layout, set(indices))

    bar = None
    if cfg.progress and todo:
        from tqdm import tqdm

        bar = tqdm(
            total=len(todo),
            unit="scene",
            desc=f"{preset.name}/{split}",
            dynamic_ncols=True,
            **progress_kwargs(),
        )
    workers = min(cfg.n_workers(), max(1, len(to_render)))
    threads = cfg.n_threads()
    render_s = 0.0
    n_conv = n_rend = 0
    nodes: set[str] = set()
    try:
        if convert:
            from generators.writer import convert_scene_grayscale

            assert src is not None
            for i in convert:
                convert_scene_grayscale(src, layout, i, preset.name)
                n_conv += 1
                if bar is not None:
                    bar.update(1)
        if cfg.backend == "ray" and to_render:
            from generators.ray_backend import render_scenes

            def done(_res: dict[str, float]) -> None:
                if bar is not None:
                    bar.update(1)

            used, results = render_scenes(
                preset, split, to_render, cfg.seed, render, out,
                workers=cfg.workers, threads=cfg.threads, recycle_after=cfg.recycle_after,
                address=cfg.address, on_done=done,
            )  # fmt: skip
            render_s += sum(r["render_s"] for r in results)
            nodes.update(str(r["node"]) for r in results)
            n_rend += len(results)
            workers, threads = used.workers, used.threads
            to_render = []  # rendered: the local pool below has nothing left to do
        # Workers are recycled by giving each batch of workers * recycle_after scenes a
        # fresh pool. Not ProcessPoolExecutor(max_tasks_per_child=...): on Python 3.11 it
        # deadlocks when a worker retires with tasks still queued (seen here: generation
        # stopped for good after the first 40 scenes).
        batch = workers * cfg.recycle_after
        for start in range(0, len(to_render), batch):
            with cf.ProcessPoolExecutor(
                max_workers=workers,
                mp_context=mp.get_context("spawn"),
                initializer=init_worker,
                initargs=(cfg.n_threads(),),
            ) as pool:
                dest = str(out.absolute())
                futures = [
                    pool.submit(render_manip_one, preset, i, n, cfg.seed, render, dest)
                    if manip
                    else pool.submit(render_one, preset, split, i, cfg.seed, render, dest)
                    for i in to_render[start : start + batch]
                ]
                try:
                    for fut in cf.as_completed(futures):
                        render_s += fut.result()["render_s"]
                        n_rend += 1
                        if bar is not None:
                            bar.update(1)
                except BaseException:
                    pool.shutdown(wait=False, cancel_futures=True)
                    raise
    finally:
        if bar is not None:
            bar.close()

    complete = all(scenefmt.is_scene_complete(layout, i) for i in range(n))
    if complete:
        scenefmt.atomic_write_json(layout.manifest, make_manifest("complete").to_json())
    return GenerateSummary(
        out=out,
        preset=preset.name,
        split=split,
        n_scenes=n,
        indices=indices,
        scenes_this_run=n_rend + n_conv,
        scenes_converted=n_conv,
        scenes_skipped=len(indices) - len(todo),
        views_rendered=n_rend * preset.camera.n_views,
        wall_s=time.perf_counter() - t0,
        render_s=render_s,
        workers=workers if n_rend else 0,
        threads=threads,
        complete=complete,
        n_views=preset.camera.n_views,
        nodes=len(nodes) or (1 if n_rend else 0),
    )


__all__ = [
    "BACKENDS",
    "GenerateConfig",
    "GenerateSummary",
    "close_worker_session",
    "cpu_cores",
    "generate_dataset",
    "init_worker",
    "render_manip_one",
    "render_one",
]
