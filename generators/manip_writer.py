"""Writes a manipulation scene (uORF's manipulation layout) and the split's manifest.

Data flow: ``worker.render_manip_one`` renders the ordinary views and the variants of
:mod:`generators.manip` -> :func:`write_manip_scene` -> the split folder
(``scenefmt.ManipLayout``). Like :func:`generators.writer.write_scene` every file is
written atomically and the scene JSON (with its ``"manipulation"`` record) goes last, so
``scenefmt.is_scene_complete(ManipLayout(...), i)`` is true only once every file is there.
"""

from __future__ import annotations

from dataclasses import replace

import scenefmt
from generators.manip import ManipEdit
from generators.presets import Preset
from generators.spec import RenderSettings, SceneSpec
from generators.writer import ViewImages, manifest, write_view_files

__all__ = ["manip_manifest", "write_manip_scene"]


def manip_manifest(
    preset: Preset,
    n: int,
    resolution: int,
    seed: int,
    render: RenderSettings,
    status: str | None = None,
) -> scenefmt.Manifest:
    """``manifest.json`` of a manipulation split: the ordinary manifest plus ``manip``
    (the variant files, the mask rule and the scene count the donors were drawn from)."""
    m = manifest(preset, scenefmt.MANIP_SPLIT, n, resolution, seed, render, status)
    manip = {
        "n_scenes": int(n),
        "variants": list(scenefmt.MANIP_VARIANTS),
        "files": {
            "moved": "{stem}_moved.png",
            "mask_for_moving": "{stem}_mask_for_moving.png",
            "movement": "{scene:03d}_movement.txt",
            "changed": "{stem}_changed.png",
            "providing_bg": "{stem}_providing_bg.png",
            "mask_for_bg": "{stem}_mask_for_bg.png",
            "mask_for_providing_bg": "{stem}_mask_for_providing_bg.png",
            "instances": "instances/{stem}_{variant}.png",
            "depth": "depth/{stem}_{variant}.exr",
        },
        "masks": f"binary, {scenefmt.MANIP_MASK_OFF} / {scenefmt.MANIP_MASK_ON} (uORF takes the "
        "lowest level as background): _mask_for_moving is the moved object in the ordinary "
        "view; _mask_for_bg / _mask_for_providing_bg are the objects of the changed / "
        "providing view (background 0)",
        "movement": "x then y, one per line, world units (world frame, +z up)",
        "edits": "sc%04d.json 'manipulation': moved object and offset, donor scene, its "
        "background, objects and lights",
    }
    return replace(m, extra={**m.extra, "manip": manip})


def write_manip_scene(
    layout: scenefmt.ManipLayout,
    spec: SceneSpec,
    edit: ManipEdit,
    views: list[ViewImages],
    variants: dict[str, list[ViewImages]],
) -> scenefmt.SceneRecord:
    """Write every file of manipulation scene ``spec.index``; the scene JSON last.

    Args:
        layout: the split folder.
        spec: the unedited scene.
        edit: its edits (saved as the JSON's ``manipulation`` record).
        views: the ordinary views, in view order.
        variants: ``{variant: views}`` for every one of ``scenefmt.MANIP_VARIANTS``.

    Returns:
        The scene record written.
    """
    missing = [v for v in scenefmt.MANIP_VARIANTS if v not in variants]
    if missing:
        raise ValueError(f"variants: missing {missing}")
    for name, vs in variants.items():
        if len(vs) != layout.n_views:
            raise ValueError(f"variants[{name!r}]: {len(vs)} views, expected {layout.n_views}")
    scene = spec.index
    write_view_files(layout, spec, views)
    k = edit.move.instance_id
    for v in range(layout.n_views):
        for name in scenefmt.MANIP_VARIANTS:
            img = variants[name][v]
            scenefmt.write_rgb(layout.variant_rgb(scene, v, name), img.rgb)
            scenefmt.write_instances(layout.variant_instances(scene, v, name), img.ids)
            scenefmt.write_depth_exr(layout.variant_depth(scene, v, name), img.depth_z)
        scenefmt.write_mask(
            layout.mask_for_moving(scene, v), scenefmt.manip_mask(views[v].ids == k)
        )
        scenefmt.write_mask(
            layout.mask_for_bg(scene, v), scenefmt.manip_mask(variants["changed"][v].ids != 0)
        )
        scenefmt.write_mask(
            layout.mask_for_providing_bg(scene, v),
            scenefmt.manip_mask(variants["providing_bg"][v].ids != 0),
        )
    scenefmt.write_movement_txt(layout.movement(scene), *edit.move.offset)
    rec = spec.record([layout.rgb(scene, v).name for v in range(spec.n_views)])
    rec = replace(rec, extra={**rec.extra, "manipulation": edit.to_json()})
    scenefmt.atomic_write_json(layout.scene_json(scene), rec.to_json())
    return rec
