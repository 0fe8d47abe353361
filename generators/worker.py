"""The render task of ``generate``: one Blender session per worker process.

Where this sits: :func:`generators.pipeline.generate_dataset` runs :func:`render_one` in
a local process pool whose initializer is :func:`init_worker`; the Ray backend
(:mod:`generators.ray_backend`) runs the same task on Ray actors, which call
:func:`init_worker` when they start and :func:`close_worker_session` when they retire. So
the bytes on disk do not depend on the backend. A worker opens its Blender session
(:class:`generators.blender_backend.BlenderSession`) on its first scene and reuses it for
the next ones. Nothing here imports bpy at import time.
"""

from __future__ import annotations

import atexit
import time

import scenefmt
from generators.presets import Preset
from generators.spec import RenderSettings

__all__ = ["close_worker_session", "init_worker", "render_manip_one", "render_one"]

_SESSION = None
_THREADS = 1


def init_worker(threads: int) -> None:
    """Set up this process as a render worker (the pool initializer; a Ray actor calls it
    too): remember the Cycles thread count of its Blender session, which
    :func:`render_one` opens on first use, and die with the parent (Linux)."""
    global _THREADS
    _THREADS = threads
    try:  # PR_SET_PDEATHSIG = 1: a killed driver takes its workers with it
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        pass


def close_worker_session() -> None:
    """Close this worker's Blender session, if one is open (a retiring Ray actor calls it);
    the next :func:`render_one` opens a fresh one."""
    global _SESSION
    if _SESSION is not None:
        _SESSION.close()
        _SESSION = None


def render_one(
    preset: Preset, split: str, index: int, seed: int, render: RenderSettings, out: str
) -> dict[str, float]:
    """Sample, render and write scene ``index`` in this process (the pool task).

    Returns:
        ``{"index", "render_s" (Cycles time, all views), "scene_s" (wall)}``.
    """
    global _SESSION
    from generators.blender_backend import BlenderSession
    from generators.imageops import linear_to_srgb8
    from generators.sampling import make_scene
    from generators.writer import ViewImages, write_scene

    t0 = time.perf_counter()
    if _SESSION is None:
        _SESSION = BlenderSession(threads=_THREADS)
        atexit.register(_SESSION.close)
    spec = make_scene(preset, split, index, seed, render)
    passes = _SESSION.render_scene(spec)
    views = [ViewImages(linear_to_srgb8(v.rgb_linear), v.ids, v.depth_z) for v in passes]
    layout = scenefmt.SplitLayout(out, n_views=preset.camera.n_views)
    write_scene(layout, spec, views, grayscale_preset=preset.name if preset.grayscale else None)
    return {
        "index": index,
        "render_s": sum(v.render_s for v in passes),
        "scene_s": time.perf_counter() - t0,
    }


def render_manip_one(
    preset: Preset, index: int, n: int, seed: int, render: RenderSettings, out: str
) -> dict[str, float]:
    """Sample, edit, render and write scene ``index`` of the manipulation split (the pool
    task of ``generate --split manip``): the ordinary views and every variant of
    :mod:`generators.manip`. The changed variant is not rendered when the donor's
    background equals the scene's own (it would be the ordinary views again).

    Returns:
        ``{"index", "render_s" (Cycles time, all views of all variants), "scene_s"}``.
    """
    global _SESSION
    from generators.blender_backend import BlenderSession
    from generators.imageops import linear_to_srgb8
    from generators.manip import make_manip_scene, variant_spec
    from generators.manip_writer import write_manip_scene
    from generators.writer import ViewImages

    t0 = time.perf_counter()
    if _SESSION is None:
        _SESSION = BlenderSession(threads=_THREADS)
        atexit.register(_SESSION.close)
    spec, edit = make_manip_scene(preset, index, n, seed, render)
    render_s = 0.0

    def draw(s) -> list[ViewImages]:
        nonlocal render_s
        passes = _SESSION.render_scene(s)
        render_s += sum(v.render_s for v in passes)
        return [ViewImages(linear_to_srgb8(v.rgb_linear), v.ids, v.depth_z) for v in passes]

    views = draw(spec)
    variants = {
        "moved": draw(variant_spec(spec, edit, "moved")),
        "changed": draw(variant_spec(spec, edit, "changed")) if edit.background.differs else views,
        "providing_bg": draw(variant_spec(spec, edit, "providing_bg")),
    }
    layout = scenefmt.ManipLayout(out, n_views=preset.camera.n_views)
    write_manip_scene(layout, spec, edit, views, variants)
    return {"index": index, "render_s": render_s, "scene_s": time.perf_counter() - t0}
