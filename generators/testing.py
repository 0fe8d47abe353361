"""bpy-free fixtures: a split folder whose passes come from the embree ray cast.

Data flow: ``sampling.make_scene`` -> ``raycast.cast_view`` (ids, planar depth) ->
flat-shaded RGB (object colour / ground grey, no lighting) -> ``writer``. The files
follow the same contract as a Cycles render, so format, verify and uORF-loader tests
run in milliseconds without Blender. :func:`write_raycast_manip_split` does the same for
a manipulation split (``generators.manip``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from generators.presets import get_preset
from generators.raycast import cast_view
from generators.sampling import make_scene
from generators.spec import RenderSettings, SceneSpec
from generators.writer import ViewImages, manifest, write_scene
from scenefmt import MANIP_VARIANTS, ManipLayout, SplitLayout, atomic_write_json


def write_raycast_split(
    out: str | Path, preset: str = "clevr567", split: str = "train", n: int = 2,
    resolution: int = 32, seed: int = 0,
) -> Path:  # fmt: skip
    """Write ``n`` scenes of ``preset``/``split`` with ray-cast passes into ``out``."""
    p = get_preset(preset)
    render = RenderSettings(resolution=resolution, samples=1, denoise=False)
    out = Path(out)
    layout = SplitLayout(out, n_views=p.camera.n_views)
    atomic_write_json(layout.manifest, manifest(p, split, n, resolution, seed, render).to_json())
    for i in range(n):
        spec = make_scene(p, split, i, seed, render)
        write_scene(layout, spec, raycast_views(spec, resolution))
    return out


def raycast_views(spec: SceneSpec, resolution: int) -> list[ViewImages]:
    """Flat-shaded ray-cast views of ``spec``: objects in their colour, the background grey
    (128), or for rooms a colour per ``background_id`` (so a changed background shows)."""
    meshes = spec.meshes()
    colours = np.zeros((256, 3), np.uint8)
    bg = spec.ground.background_id
    colours[0] = (128, 128, 128) if bg is None else (60 + 40 * (bg % 4), 90, 150 - 30 * (bg % 3))
    for o in spec.objects:
        colours[o.instance_id] = o.rgb
    views = []
    for v in range(spec.n_views):
        c = cast_view(spec, v, resolution, meshes=meshes)
        views.append(ViewImages(colours[c.ids], c.ids, c.depth_z))
    return views


def write_raycast_manip_split(
    out: str | Path, preset: str = "clevr567", n: int = 2, resolution: int = 32, seed: int = 0
) -> Path:
    """Write ``n`` scenes of ``preset``'s manipulation split with ray-cast passes."""
    from generators.manip import make_manip_scene, variant_spec
    from generators.manip_writer import manip_manifest, write_manip_scene

    p = get_preset(preset)
    render = RenderSettings(resolution=resolution, samples=1, denoise=False)
    out = Path(out)
    layout = ManipLayout(out, n_views=p.camera.n_views)
    m = manip_manifest(p, n, resolution, seed, render, "complete")
    atomic_write_json(layout.manifest, m.to_json())
    for i in range(n):
        spec, edit = make_manip_scene(p, i, n, seed, render)
        variants = {
            v: raycast_views(variant_spec(spec, edit, v), resolution) for v in MANIP_VARIANTS
        }
        write_manip_scene(layout, spec, edit, raycast_views(spec, resolution), variants)
    return out
