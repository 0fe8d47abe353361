"""``generate verify`` for a manipulation split: the files :mod:`generators.manip_writer` adds.

Data flow: ``verify.verify_split`` (a split whose manifest says ``"split": "manip"``) ->
:func:`manip_scene_problems` per scene -> problems (empty = valid). Reads only through
``scenefmt``; needs no bpy. Checks per scene: the JSON's ``manipulation`` record parses and
names an object of the scene; ``{scene:03d}_movement.txt`` equals its offset; per view,
every variant's RGB is uint8 [R, R, 3], its instance ids uint8 [R, R] (the providing
view's are the donor's objects) and its depth float32 [R, R] without NaN; the three
masks are binary (``MANIP_MASK_OFF`` / ``MANIP_MASK_ON``) and equal the ids they come
from (``_mask_for_moving``: the moved object in the ordinary view; ``_mask_for_bg``: the
objects of the changed view; ``_mask_for_providing_bg``: the objects of the providing view).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from scenefmt import (
    MANIP_VARIANTS,
    ManipLayout,
    manip_mask,
    read_depth_exr,
    read_instances,
    read_movement_txt,
    read_rgb,
)

__all__ = ["manip_scene_problems"]


def manip_scene_problems(layout: ManipLayout, meta: dict[str, Any], s: int, res: int) -> list[str]:
    """Problems of the manipulation files of scene ``s`` (see the module docstring).

    Args:
        layout: the split folder.
        meta: the scene's JSON.
        s: scene index.
        res: the manifest's resolution.
    """
    rec = meta.get("manipulation")
    if not isinstance(rec, dict):
        return [f"sc{s:04d}.json: no 'manipulation' record (not written by --split manip?)"]
    try:
        k = int(rec["move"]["instance_id"])
        dx, dy = (float(v) for v in rec["move"]["offset"])
        donor_ids = {int(o["instance_id"]) for o in rec["background"]["donor_objects"]}
    except (KeyError, TypeError, ValueError) as e:
        return [f"sc{s:04d}.json: unreadable 'manipulation' record ({type(e).__name__}: {e})"]
    own_ids = {int(o["instance_id"]) for o in meta.get("objects", [])}
    out: list[str] = []
    if k not in own_ids:
        out.append(f"sc{s:04d}.json: the moved object {k} is not an object of the scene")
    try:
        got = read_movement_txt(layout.movement(s))
        if not np.allclose(got, (dx, dy), atol=1e-8):
            out.append(f"{layout.movement(s).name}: {got} differs from the JSON offset {(dx, dy)}")
    except (OSError, ValueError) as e:
        out.append(f"{layout.movement(s).name}: unreadable ({e})")
    for v in range(layout.n_views):
        out += _view_problems(layout, s, v, res, k, own_ids, donor_ids)
    return out


def _view_problems(
    layout: ManipLayout, s: int, v: int, res: int, k: int, own: set[int], donor: set[int]
) -> list[str]:
    stem = layout.stem(s, v)
    out: list[str] = []
    try:
        ids: dict[str, np.ndarray] = {}
        for name in MANIP_VARIANTS:
            rgb = read_rgb(layout.variant_rgb(s, v, name))
            if rgb.shape != (res, res, 3):
                out.append(f"{stem}_{name}.png: shape {rgb.shape}, expected {(res, res, 3)}")
            ids[name] = read_instances(layout.variant_instances(s, v, name))
            if ids[name].shape != (res, res):
                out.append(f"instances/{stem}_{name}.png: shape {ids[name].shape}")
                return out
            allowed = donor if name == "providing_bg" else own
            extra = set(np.unique(ids[name]).tolist()) - {0} - allowed
            if extra:
                out.append(f"instances/{stem}_{name}.png: ids {sorted(extra)} not in the scene")
            depth = read_depth_exr(layout.variant_depth(s, v, name))
            if depth.shape != (res, res) or depth.dtype != np.float32 or np.isnan(depth).any():
                out.append(f"depth/{stem}_{name}.exr: {depth.dtype} {depth.shape}, NaN or bad size")
        base = read_instances(layout.instances(s, v))
        masks = (
            (layout.mask_for_moving(s, v), base == k),
            (layout.mask_for_bg(s, v), ids["changed"] != 0),
            (layout.mask_for_providing_bg(s, v), ids["providing_bg"] != 0),
        )
        for path, want in masks:
            m = read_instances(path)
            if not np.array_equal(m, manip_mask(want)):
                out.append(f"{path.name}: not the binary mask of its instance ids")
    except (OSError, ValueError, KeyError) as e:
        out.append(f"{stem}: unreadable manipulation file ({type(e).__name__}: {e})")
    return out
