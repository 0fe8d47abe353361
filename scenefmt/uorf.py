"""Reader of plain uORF-layout split folders (PNG views, ``_RT.txt`` cameras, grey masks).

Where this sits: in the format layer (numpy and PIL, no torch), below ``svorf.data``;
``MultiViewDataset(root, uorf_layout=True)`` asks :func:`uorf_view_files` which view images
the folder holds and :func:`read_uorf_scene` for each scene's arrays, then resizes and
serves them like a split of our own layout. Failures are
:class:`~scenefmt.errors.DatasetError` lines.

The layout stores no manifest, scene JSON, intrinsics or depth. What this reader assumes
(uORF's loader and projection, which store none of it):

- view images are the ``*.png`` files directly in the folder whose name does not end in
  one of :data:`UORF_EXCLUDED_SUFFIXES`, grouped into scenes by the ``sc%04d`` in their
  names and ordered by name;
- ``K`` has its principal point at the image centre and the field of view
  :data:`UORF_FOV_DEG` unless told otherwise (:func:`uorf_intrinsics`);
- ``{stem}_RT.txt`` is camera-to-world with OpenCV axes (``"opencv"``, uORF's
  ``models/projection.py``) or OpenGL axes (``"opengl"``, Blender's ``matrix_world``);
- ``{stem}_depth.npy`` (optional) holds planar z, else depth is NaN;
- instance ids come from ``{stem}_mask.png`` by uORF's second-lowest-grey-level
  background rule (:func:`uorf_instance_ids`); all background without a mask.

Arrays are returned as numpy, per scene: V views of H x W pixels.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np
from PIL import Image

from scenefmt.errors import DatasetError, read_file
from scenefmt.io import read_matrix_txt, read_rgb
from scenefmt.layout import sentinel_size

__all__ = [
    "UORF_EXCLUDED_SUFFIXES",
    "UORF_FOV_DEG",
    "UorfScene",
    "read_grey",
    "read_uorf_scene",
    "uorf_instance_ids",
    "uorf_intrinsics",
    "uorf_view_files",
]

#: Field of view (x, y) in degrees assumed for uORF-layout folders, which store no
#: intrinsics: uORF's ``models/projection.py`` uses focal lengths of ``350/320 * W`` and
#: ``350/240 * H`` pixels, i.e. ``2 * atan(0.5 / ratio)``.
UORF_FOV_DEG = (
    math.degrees(2.0 * math.atan(0.5 / (350.0 / 320.0))),
    math.degrees(2.0 * math.atan(0.5 / (350.0 / 240.0))),
)

#: File-name endings the uORF loader excludes from its view-image glob, plus the
#: auxiliary images seen in uORF-derived repositories (``_dist``, ``_depth``, ``_seg``).
UORF_EXCLUDED_SUFFIXES = (
    "_mask",
    "_mask_for_moving",
    "_moved",
    "_mask_for_bg",
    "_mask_for_providing_bg",
    "_changed",
    "_providing_bg",
    "_dist",
    "_depth",
    "_seg",
)

# OpenGL camera axes (x right, y up, z backward) -> OpenCV: negate the y and z columns.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


class UorfScene(NamedTuple):
    """One scene of a uORF-layout folder, as numpy arrays (V views of H x W pixels)."""

    rgb: np.ndarray
    """uint8 [V, H, W, 3]."""
    ids: np.ndarray | None
    """uint8 [V, H, W] instance ids, 0 = background; None when read without truth."""
    depth: np.ndarray | None
    """float32 [V, H, W] planar depth, NaN = none; None when read without truth."""
    K: np.ndarray
    """float64 [V, 3, 3] intrinsics in pixels."""
    cam_to_world: np.ndarray
    """float64 [V, 4, 4], OpenCV axes."""


def uorf_view_files(root: Path) -> dict[int, list[Path]]:
    """The view images of a uORF-layout folder by scene number, each list sorted by name.

    Raises:
        DatasetError: no ``*sc%04d*.png`` view image in ``root``.
    """
    pngs = sorted(root.glob("*.png"))
    views = [p for p in pngs if not p.stem.endswith(UORF_EXCLUDED_SUFFIXES)]
    by_scene: dict[int, list[Path]] = {}
    for p in views:
        m = re.search(r"sc(\d{4})", p.name)
        if m:
            by_scene.setdefault(int(m.group(1)), []).append(p)
    if not by_scene:
        raise DatasetError(f"{root}: no view images named *sc%04d*.png - not a uORF-layout folder")
    return {s: sorted(files) for s, files in by_scene.items()}


def uorf_intrinsics(h: int, w: int, fov_deg: float | tuple[float, float]) -> np.ndarray:
    """float64 [3, 3] ``K`` of an ``h x w`` view: principal point at the image centre,
    field of view ``fov_deg`` (x, y) or one value for both, in degrees."""
    fx_deg, fy_deg = (fov_deg, fov_deg) if isinstance(fov_deg, (int, float)) else fov_deg
    fx = 0.5 * w / math.tan(math.radians(fx_deg) / 2.0)
    fy = 0.5 * h / math.tan(math.radians(fy_deg) / 2.0)
    return np.array([[fx, 0.0, w / 2.0], [0.0, fy, h / 2.0], [0.0, 0.0, 1.0]])


def read_uorf_scene(
    root: Path,
    scene: int,
    files: list[Path],
    fov_deg: float | tuple[float, float],
    axes: str,
    truth: bool,
) -> UorfScene:
    """Read the views ``files`` (sorted, of :func:`uorf_view_files`) of scene ``scene``.

    Args:
        root: the split folder (named in error messages).
        fov_deg: field of view for :func:`uorf_intrinsics`.
        axes: camera axes of the ``_RT.txt`` matrices, ``"opencv"`` or ``"opengl"``.
        truth: also read depth (``_depth.npy``) and instance ids (``_mask.png``).

    Raises:
        DatasetError: views of different sizes, a missing or malformed ``_RT.txt``, a
            depth array of the wrong size, or an unreadable file.
    """
    s_rgb = [read_file(read_rgb, p, root) for p in files]
    if len({a.shape for a in s_rgb}) != 1:
        raise DatasetError(f"{root}: the views of scene sc{scene:04d} differ in size")
    h, w = s_rgb[0].shape[:2]
    Kv = uorf_intrinsics(h, w, fov_deg)
    s_c2w, s_depth, s_levels = [], [], []
    for p in files:
        rt = p.with_name(p.stem + "_RT.txt")
        if not rt.is_file():
            raise DatasetError(f"{rt}: missing - every uORF view image needs its _RT.txt")
        T = read_file(read_matrix_txt, rt, root)
        if T.shape != (4, 4):
            raise DatasetError(f"{rt}: expected a 4x4 matrix, got shape {T.shape}")
        s_c2w.append(T @ _GL_TO_CV if axes == "opengl" else T)
        if not truth:
            continue
        dpath = p.with_name(p.stem + "_depth.npy")
        if dpath.is_file():  # assumed planar z (what our writer stores there)
            dz = read_file(np.load, dpath, root)
            if dz.size != h * w:
                raise DatasetError(f"{dpath}: {dz.shape} does not match the {h}x{w} image")
            s_depth.append(dz.reshape(h, w).astype(np.float32))
        else:
            s_depth.append(np.full((h, w), np.nan, dtype=np.float32))
        mpath = p.with_name(p.stem + "_mask.png")
        if mpath.is_file():
            s_levels.append(read_file(read_grey, mpath, root))
        else:
            s_levels.append(None)
    return UorfScene(
        rgb=np.stack(s_rgb),
        ids=uorf_instance_ids(s_levels, h, w) if truth else None,
        depth=np.stack(s_depth) if truth else None,
        K=np.stack([Kv] * len(files)),
        cam_to_world=np.stack(s_c2w),
    )


def read_grey(path: Path) -> np.ndarray:
    """uint8 [H, W] grey levels of a mask image (``PIL`` ``convert("L")``)."""
    with Image.open(path) as im:
        return np.asarray(im.convert("L"))


def uorf_instance_ids(levels: list[np.ndarray | None], h: int, w: int) -> np.ndarray:
    """Instance ids [V, H, W] from uORF grey masks with the uORF background rule.

    Per view the background is the *second-lowest* grey level (uORF's loader); every
    other level is an object, with one exception: when the lowest level holds pixel
    (0, 0) and occupies only pixels of the top-left ``b x b`` block
    (``b = scenefmt.sentinel_size(h, w)`` of that view's mask) it is our writer's
    sentinel (``scenefmt.MASK_SENTINEL_LEVEL``, there so that the second-lowest rule
    holds) and reads as background. That covers the whole block (format >= 1.1) and
    the single pixel (0, 0) of format 1.0 files. uORF's own loader would see it as a
    small object. Ids 1..n follow the sorted union of object levels over the scene's
    views, so one object keeps its id across views (assumes a grey level means the
    same object in every view of a scene, as in uORF's data). Views without a mask
    read as all background.

    Args:
        levels: per view a uint8 [h, w] grey mask (after ``convert('L')``) or None.
        h, w: the views' image size (each mask is [h, w]).
    """
    out = np.zeros((len(levels), h, w), dtype=np.uint8)
    bgs: list[set[int] | None] = []
    fg_levels: set[int] = set()
    for m in levels:
        if m is None:
            bgs.append(None)
            continue
        uniq = np.unique(m)
        bg = {int(uniq[1] if len(uniq) > 1 else uniq[0])}
        corner = int(m[0, 0])
        if len(uniq) > 1 and corner == int(uniq[0]):
            b = sentinel_size(*m.shape)
            low = m == corner
            if int(low.sum()) == int(low[:b, :b].sum()):
                bg.add(corner)  # the sentinel block (or format 1.0's pixel (0, 0))
        bgs.append(bg)
        fg_levels.update(int(u) for u in uniq if int(u) not in bg)
    lut = {lv: k + 1 for k, lv in enumerate(sorted(fg_levels))}
    if len(lut) > 255:
        raise DatasetError("uORF masks have more than 255 object grey levels")
    for j, (m, bg) in enumerate(zip(levels, bgs)):
        if m is None or bg is None:
            continue
        table = np.zeros(256, dtype=np.uint8)
        for lv, k in lut.items():
            table[lv] = k
        for lv in bg:
            table[lv] = 0
        out[j] = table[m]
    return out
