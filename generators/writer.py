"""Writer: rendered passes of one scene -> the files of the dataset contract.

Data flow: ``pipeline`` -> ``blender_backend`` passes -> :func:`write_scene` ->
``scenefmt`` atomic writers. Per-view files go first, in ``SplitLayout.view_files``
order, the scene JSON last (it marks the scene complete, see
``scenefmt.is_scene_complete``). Also writes ``manifest.json``.
"""

from __future__ import annotations

import importlib.metadata
from dataclasses import dataclass
from typing import Any

import numpy as np

from generators import geometry
from generators.presets import Preset
from generators.spec import RenderSettings, SceneSpec
from scenefmt import (
    FORMAT_VERSION,
    MASK_BG_LEVEL,
    MASK_SENTINEL_LEVEL,
    SplitLayout,
    atomic_write_json,
    uorf_mask_from_instances,
    write_depth_exr,
    write_instances,
    write_mask,
    write_matrix_txt,
    write_rgb,
)
from scenefmt.layout import MASK_STEP


def generator_version() -> str:
    """Version of the installed toolkit (``pyproject`` version)."""
    try:
        return importlib.metadata.version("svorf-toolkit")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - not installed
        return "0.0.0+unknown"


@dataclass(frozen=True)
class ViewImages:
    """Final per-view arrays, as they go to disk.

    Attributes:
        rgb8: uint8 [H, W, 3] sRGB.
        ids: uint8 [H, W] instance ids, 0 = background.
        depth_z: float32 [H, W] planar depth (camera z, world units), inf = no hit.
    """

    rgb8: np.ndarray
    ids: np.ndarray
    depth_z: np.ndarray


def write_scene(layout: SplitLayout, spec: SceneSpec, views: list[ViewImages]) -> None:
    """Write every file of scene ``spec.index``; the scene JSON last.

    Raises:
        ValueError: wrong number of views, or a view whose pixel (0, 0) is not
            background (the uORF mask sentinel needs it).
    """
    if len(views) != spec.n_views or spec.n_views != layout.n_views:
        raise ValueError(
            f"views: expected {layout.n_views} views for scene {spec.index}, got {len(views)}"
        )
    s = spec.index
    names = []
    for v, (img, view) in enumerate(zip(views, spec.views, strict=True)):
        if img.ids[0, 0] != 0:
            raise ValueError(
                f"scene {s} view {v}: pixel (0, 0) shows instance {img.ids[0, 0]}, "
                "but the uORF mask sentinel needs background there"
            )
        write_rgb(layout.rgb(s, v), img.rgb8)
        write_matrix_txt(layout.rt(s, v), view.c2w())
        write_matrix_txt(layout.azi_rot(s, v), geometry.azimuth_rotation(view.azimuth_deg))
        write_mask(layout.mask(s, v), uorf_mask_from_instances(img.ids))
        write_instances(layout.instances(s, v), img.ids)
        write_depth_exr(layout.depth(s, v), img.depth_z)
        names.append(layout.rgb(s, v).name)
    atomic_write_json(layout.scene_json(s), spec.to_json(names))


def manifest(
    preset: Preset, split: str, n_scenes: int, resolution: int, seed: int, render: RenderSettings
) -> dict[str, Any]:
    """The split-level ``manifest.json`` (deterministic: no clock, no host names)."""
    return {
        "format": "svorf-dataset",
        "format_version": FORMAT_VERSION,
        "preset": preset.name,
        "description": preset.description,
        "split": split,
        "n_scenes": int(n_scenes),
        "n_views": preset.camera.n_views,
        "resolution": int(resolution),
        "seed": int(seed),
        "scene_seed_rule": "seed * 1_000_000 + split_code * 100_000 + index (train 0, test 1)",
        "generator": f"generators {generator_version()}",
        "generator_version": generator_version(),
        "num_slots": preset.num_slots,
        "grayscale": preset.grayscale,
        "render": render.to_json(),
        "conventions": {
            "world": "right-handed, +z up, origin = scene centre, world units",
            "camera_convention": "opencv",
            "cam_to_world": "4x4, columns = camera x (right), y (down), z (forward), centre",
            "intrinsics": "K = [[f,0,W/2],[0,f,H/2],[0,0,1]], f = lens_mm/sensor_width_mm*W, "
            "pixel (u,v) centre at (u+0.5, v+0.5)",
            "depth": "planar_z",
            "depth_units": "world units; inf where the ray hits nothing",
            "instance_ids": "uint8, 0 = background (ground), k = objects[k-1] of sc%04d.json",
            "mask": {
                "sentinel_pixel": [0, 0],
                "sentinel_level": MASK_SENTINEL_LEVEL,
                "background_level": MASK_BG_LEVEL,
                "object_level": f"{MASK_BG_LEVEL} + {MASK_STEP} * instance_id",
            },
            "rgb": "8-bit sRGB (sRGB OETF of linear Cycles output)",
            "azi_rot": "3x3 rotation about world z by the view azimuth",
        },
        "files": {
            "rgb": "{idx:05d}_sc{scene:04d}_az{view:02d}.png",
            "rt": "{stem}_RT.txt",
            "azi_rot": "{stem}_azi_rot.txt",
            "mask": "{stem}_mask.png",
            "instances": "instances/{stem}.png",
            "depth": "depth/{stem}.exr",
            "scene": "sc{scene:04d}.json",
        },
        "preset_config": preset.to_json(),
    }
