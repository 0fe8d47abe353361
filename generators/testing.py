"""bpy-free fixtures: a split folder whose passes come from the embree ray cast.

Data flow: ``sampling.make_scene`` -> ``raycast.cast_view`` (ids, planar depth) ->
flat-shaded RGB (object colour / ground grey, no lighting) -> ``writer``. The files
follow the same contract as a Cycles render, so format, verify and uORF-loader tests
run in milliseconds without Blender.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from generators.presets import get_preset
from generators.raycast import cast_view
from generators.sampling import make_scene
from generators.spec import RenderSettings
from generators.writer import ViewImages, manifest, write_scene
from scenefmt import SplitLayout, atomic_write_json


def write_raycast_split(
    out: str | Path, preset: str = "clevr567", split: str = "train", n: int = 2,
    resolution: int = 32, seed: int = 0,
) -> Path:  # fmt: skip
    """Write ``n`` scenes of ``preset``/``split`` with ray-cast passes into ``out``."""
    p = get_preset(preset)
    render = RenderSettings(resolution=resolution, samples=1, denoise=False)
    out = Path(out)
    layout = SplitLayout(out, n_views=p.camera.n_views)
    atomic_write_json(layout.manifest, manifest(p, split, n, resolution, seed, render))
    for i in range(n):
        spec = make_scene(p, split, i, seed, render)
        meshes = spec.meshes()
        colours = np.zeros((256, 3), np.uint8)
        colours[0] = (128, 128, 128)
        for o in spec.objects:
            colours[o.instance_id] = o.rgb
        views = []
        for v in range(spec.n_views):
            c = cast_view(spec, v, resolution, meshes=meshes)
            views.append(ViewImages(colours[c.ids], c.ids, c.depth_z))
        write_scene(layout, spec, views)
    return out
