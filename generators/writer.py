"""Writes a split's files through ``scenefmt`` (atomic, scene JSON last) + the manifest.

Data flow: ``blender_backend.ViewPasses`` -> ``imageops`` -> :class:`ViewImages` ->
:func:`write_scene` -> the split folder; derived presets (``clevr567-gray``) go
through :func:`convert_scene_grayscale` from an existing colour split instead.
Every file is written to a temp file beside its target and renamed into place
(``scenefmt`` writers); the scene JSON goes last, so ``scenefmt.is_scene_complete``
is true only once every file of the scene is in place. A kill at any moment leaves
either a complete scene or an incomplete one that the next run renders again.

:func:`manifest` builds the split's :class:`scenefmt.Manifest`; it holds no clock or host
fields, so two runs of the same command write identical bytes. Scene records are
:class:`scenefmt.SceneRecord` (``SceneSpec.record``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

import scenefmt
from generators import geometry
from generators.imageops import GRAYSCALE_FORMULA, grayscale_rec601
from generators.presets import Preset
from generators.spec import RenderSettings, SceneSpec

GENERATOR_VERSION = "0.1.0"


@dataclass(frozen=True)
class ViewImages:
    """Final per-view arrays as they go to disk.

    Attributes:
        rgb: uint8 [H, W, 3] sRGB.
        ids: uint8 [H, W] instance ids, 0 = background; pixel (0, 0) must be 0.
        depth_z: float32 [H, W] planar depth, world units (inf = no hit).
    """

    rgb: np.ndarray
    ids: np.ndarray
    depth_z: np.ndarray


def manifest(
    preset: Preset,
    split: str,
    n: int,
    resolution: int,
    seed: int,
    render: RenderSettings,
    status: str | None = None,
) -> scenefmt.Manifest:
    """The ``manifest.json`` of a split (documented in ``docs/format.md``).

    Args:
        preset: the dataset's preset (``preset_config`` is saved verbatim).
        split: split name.
        n: number of scenes of the split.
        resolution: square image size.
        seed: dataset seed.
        render: render settings of every scene.
        status: optional ``"in_progress"`` / ``"complete"`` (deterministic, no clock).
    """
    return scenefmt.Manifest(
        preset=preset.name,
        split=split,
        n_scenes=int(n),
        n_views=preset.camera.n_views,
        resolution=int(resolution),
        seed=int(seed),
        generator=f"generators {GENERATOR_VERSION}",
        status=status,
        conventions={
            "camera_convention": "opencv",
            "cam_to_world": "4x4, columns = camera x (right), y (down), z (forward), centre",
            "intrinsics": "K = [[f,0,W/2],[0,f,H/2],[0,0,1]], f = lens_mm/sensor_width_mm*W, "
            "pixel (u,v) centre at (u+0.5, v+0.5)",
            "world": "right-handed, +z up, origin = scene centre, world units",
            "depth": "planar_z",
            "depth_units": "world units; inf where the ray hits nothing",
            "instance_ids": "uint8, 0 = background (ground), k = objects[k-1] of sc%04d.json",
            "mask": {
                "sentinel_pixel": [0, 0],
                "sentinel_block": scenefmt.sentinel_size(int(resolution), int(resolution)),
                "sentinel_level": scenefmt.MASK_SENTINEL_LEVEL,
                "background_level": scenefmt.MASK_BG_LEVEL,
                "object_level": f"{scenefmt.MASK_BG_LEVEL} + 18 * instance_id",
            },
            "rgb": "8-bit sRGB (sRGB OETF of linear Cycles output)",
            "azi_rot": "3x3 rotation about world z by the view azimuth",
        },
        extra={
            "format": scenefmt.MANIFEST_FORMAT,
            "generator_version": GENERATOR_VERSION,
            "description": preset.description,
            "scene_seed_rule": "seed * 1_000_000 + split_code * 100_000 + index (train 0, test 1)",
            "num_slots": preset.num_slots,
            "grayscale": preset.grayscale,
            "render": render.to_json(),
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
        },
    )


def grayscale_json(
    record: scenefmt.SceneRecord, preset_name: str, rgb_source: str
) -> scenefmt.SceneRecord:
    """Scene record of the grayscale variant: the colour scene's record with ``preset``
    renamed and ``grayscale`` (the formula) and ``rgb_source`` added."""
    if rgb_source not in ("converted", "rendered"):
        raise ValueError(f"rgb_source must be 'converted' or 'rendered', got {rgb_source!r}")
    extra = {**record.extra, "grayscale": GRAYSCALE_FORMULA, "rgb_source": rgb_source}
    return replace(record, preset=preset_name, extra=extra)


def write_scene(
    layout: scenefmt.SplitLayout,
    spec: SceneSpec,
    views: list[ViewImages],
    *,
    grayscale_preset: str | None = None,
) -> scenefmt.SceneRecord:
    """Write every file of scene ``spec.index``; the scene JSON last.

    Args:
        layout: the split folder.
        spec: the scene (its JSON is written).
        views: one :class:`ViewImages` per view, in view order.
        grayscale_preset: if set, RGB is converted with Rec.601 luma and the JSON
            becomes :func:`grayscale_json` with this preset name (``rgb_source``
            ``"rendered"``).

    Returns:
        The scene record written.
    """
    write_view_files(layout, spec, views, grayscale=grayscale_preset is not None)
    scene = spec.index
    rec = spec.record([layout.rgb(scene, v).name for v in range(spec.n_views)])
    if grayscale_preset:
        rec = grayscale_json(rec, grayscale_preset, "rendered")
    scenefmt.atomic_write_json(layout.scene_json(scene), rec.to_json())
    return rec


def write_view_files(
    layout: scenefmt.SplitLayout,
    spec: SceneSpec,
    views: list[ViewImages],
    *,
    grayscale: bool = False,
) -> None:
    """Write the ordinary per-view files of scene ``spec.index`` (not its JSON).

    Args:
        layout: the split folder.
        spec: the scene (its cameras go to ``_RT.txt`` / ``_azi_rot.txt``).
        views: one :class:`ViewImages` per view, in view order.
        grayscale: convert RGB with Rec.601 luma.
    """
    if len(views) != spec.n_views or spec.n_views != layout.n_views:
        raise ValueError(
            f"views: expected {layout.n_views} views, got {len(views)} (spec has {spec.n_views})"
        )
    scene = spec.index
    for v, (img, vs) in enumerate(zip(views, spec.views, strict=True)):
        rgb = grayscale_rec601(img.rgb) if grayscale else img.rgb
        scenefmt.write_rgb(layout.rgb(scene, v), rgb)
        scenefmt.write_matrix_txt(layout.rt(scene, v), vs.c2w())
        scenefmt.write_matrix_txt(
            layout.azi_rot(scene, v), geometry.azimuth_rotation(vs.azimuth_deg)
        )
        scenefmt.write_mask(layout.mask(scene, v), scenefmt.uorf_mask_from_instances(img.ids))
        scenefmt.write_instances(layout.instances(scene, v), img.ids)
        scenefmt.write_depth_exr(layout.depth(scene, v), img.depth_z)


def convert_scene_grayscale(
    src: scenefmt.SplitLayout, dst: scenefmt.SplitLayout, scene: int, preset_name: str
) -> scenefmt.SceneRecord:
    """Make scene ``scene`` of ``dst`` from the complete colour scene of ``src``.

    Every file except the RGB images is copied byte for byte (the depth EXR
    included); the RGB images are converted with Rec.601 luma; the JSON becomes
    :func:`grayscale_json` (``rgb_source: "converted"``), written last.
    """
    if not scenefmt.is_scene_complete(src, scene):
        raise ValueError(f"scene: source scene {scene} in {src.root} is not complete")
    for v in range(src.n_views):
        gray = grayscale_rec601(scenefmt.read_rgb(src.rgb(scene, v)))
        scenefmt.write_rgb(dst.rgb(scene, v), gray)
        for name in ("rt", "azi_rot", "mask", "instances", "depth"):
            data = getattr(src, name)(scene, v).read_bytes()
            scenefmt.atomic_write_bytes(getattr(dst, name)(scene, v), data)
    colour = scenefmt.SceneRecord.from_json(scenefmt.read_json(src.scene_json(scene)))
    rec = grayscale_json(colour, preset_name, "converted")
    scenefmt.atomic_write_json(dst.scene_json(scene), rec.to_json())
    return rec
