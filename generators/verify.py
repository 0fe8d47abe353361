"""``generate verify DIR``: check a split folder against the dataset contract.

Data flow: split folder on disk -> :func:`verify_split` -> list of problems (empty =
valid). Reads only through ``scenefmt``; needs no bpy. Checks, per scene and view:
every file present; RGB uint8 [R, R, 3] at the manifest resolution; instance ids
uint8 [R, R], a subset of the scene JSON's instance ids, with the top-left sentinel
block (``scenefmt.sentinel_size``) = 0; ``_mask.png`` equal to
``uorf_mask_from_instances(ids)`` and obeying the uORF rule (after PIL
``convert('L')`` the second-lowest grey level is the background level and covers
exactly the id-0 pixels other than the sentinel block), also after uORF's PIL NEAREST
resize to its ``mask_size`` (checked at 64, 96, 128 and R, those in [64, R]: the
second-lowest level covers exactly the equally resized id-0 pixels other than the
sentinel's); depth float32 [R, R],
finite and positive wherever geometry was hit (every pixel here: the ground
is hit everywhere; objects always), never NaN; ``_RT.txt`` / ``_azi_rot.txt`` equal to
the JSON camera; no stray ``*.png`` that the uORF loader would take for a view. A
manipulation split (``"split": "manip"``) also gets ``manip_verify.manip_scene_problems``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from generators import geometry
from generators.manip_verify import manip_scene_problems
from scenefmt import (
    MANIP_SPLIT,
    MASK_BG_LEVEL,
    MASK_SENTINEL_LEVEL,
    MIN_UORF_MASK_SIZE,
    Manifest,
    ManipLayout,
    SceneRecord,
    SplitLayout,
    read_depth_exr,
    read_instances,
    read_json,
    read_matrix_txt,
    read_rgb,
    sentinel_size,
    uorf_mask_from_instances,
)

#: The file-name endings uORF's loaders drop from ``glob('*.png')`` (KovenYu/uORF
#: ``data/multiscenes_dataset.py`` and ``data/multiscenes_manip_dataset.py``, the same
#: seven); every other PNG in a split folder is read as a view.
UORF_NON_VIEW_SUFFIXES = (
    "_mask.png", "_mask_for_moving.png", "_mask_for_bg.png", "_mask_for_providing_bg.png",
    "_moved.png", "_changed.png", "_providing_bg.png",
)  # fmt: skip


def uorf_background_level(mask_path: str | Path) -> int:
    """The uORF loader's background: the second-lowest grey level after convert('L')."""
    with Image.open(mask_path) as im:
        levels = np.unique(np.asarray(im.convert("L")))
    if len(levels) < 2:
        raise ValueError(f"{mask_path}: only {len(levels)} grey level(s); uORF needs >= 2")
    return int(levels[1])


#: uORF ``mask_size`` values :func:`uorf_resize_problem` tries (those in [64, R]), plus R.
UORF_CHECK_MASK_SIZES = (MIN_UORF_MASK_SIZE, 96, 128)


def uorf_resize_problem(mask_path: str | Path, ids: np.ndarray) -> str | None:
    """Whether uORF's background rule survives its resize of ``_mask.png``.

    As uORF's loader does: ``convert('L')``, PIL NEAREST resize to ``(n, n)`` for each
    ``n`` of ``UORF_CHECK_MASK_SIZES`` within ``[64, R]`` and ``n = R``; the
    second-lowest grey level must be exactly where the equally resized instance ids
    are 0, except the (resized) sentinel pixels.

    Args:
        mask_path: the view's ``_mask.png``.
        ids: uint8 [R, R] instance ids of the view.

    Returns:
        None when it holds, else a one-line problem naming the first failing size.
    """
    r = max(ids.shape)
    sizes = sorted({n for n in UORF_CHECK_MASK_SIZES if n <= r} | ({r} if r >= 64 else set()))
    if not sizes:
        return None
    with Image.open(mask_path) as im:
        mask_l = im.convert("RGB").convert("L")
    ids_im = Image.fromarray(np.ascontiguousarray(ids, dtype=np.uint8))
    for n in sizes:
        m = np.asarray(mask_l.resize((n, n), Image.Resampling.NEAREST))
        bg_ids = np.asarray(ids_im.resize((n, n), Image.Resampling.NEAREST)) == 0
        levels = np.unique(m)
        if len(levels) < 2:
            return f"only {len(levels)} grey level(s) after uORF's resize to mask_size {n}"
        bgpix = m == levels[1]
        want = bg_ids & (m != MASK_SENTINEL_LEVEL)
        if not np.array_equal(bgpix, want):
            return (
                f"uORF's background rule fails after its NEAREST resize to mask_size {n} "
                f"(second-lowest level {int(levels[1])} covers {int(bgpix.sum())} pixels, "
                f"id 0 {int(want.sum())}; sentinel lost?)"
            )
    return None


def _view_problems(layout: SplitLayout, meta: SceneRecord, s: int, v: int, res: int) -> list[str]:
    out: list[str] = []
    stem = layout.stem(s, v)
    ids_json = {int(o["instance_id"]) for o in meta.objects}
    try:
        rgb = read_rgb(layout.rgb(s, v))
        with Image.open(layout.rgb(s, v)) as im:
            if im.mode != "RGB":
                out.append(f"{stem}.png: mode {im.mode}, expected RGB")
        if rgb.shape != (res, res, 3):
            out.append(f"{stem}.png: shape {rgb.shape}, expected {(res, res, 3)}")
        ids = read_instances(layout.instances(s, v))
        if ids.shape != (res, res):
            out.append(f"instances/{stem}.png: shape {ids.shape}, expected {(res, res)}")
            return out
        extra = set(np.unique(ids).tolist()) - {0} - ids_json
        if extra:
            out.append(f"instances/{stem}.png: ids {sorted(extra)} not in sc{s:04d}.json objects")
        b = sentinel_size(*ids.shape)
        if ids[:b, :b].any():
            out.append(
                f"instances/{stem}.png: the top-left {b}x{b} sentinel block must be background"
            )
            return out
        mask = read_instances(layout.mask(s, v))
        if mask.shape != ids.shape or not np.array_equal(mask, uorf_mask_from_instances(ids)):
            out.append(f"{stem}_mask.png: does not match uorf_mask_from_instances("
                       f"instances/{stem}.png) (a {b}x{b} sentinel block at {res} px)")  # fmt: skip
        else:
            bg = uorf_background_level(layout.mask(s, v))
            if bg != MASK_BG_LEVEL:
                out.append(f"{stem}_mask.png: uORF background level {bg} != {MASK_BG_LEVEL}")
            bgpix = mask == bg
            want = ids == 0
            want[:b, :b] = False
            if not np.array_equal(bgpix, want):
                out.append(f"{stem}_mask.png: uORF background pixels differ from id-0 pixels")
        why = uorf_resize_problem(layout.mask(s, v), ids)
        if why is not None:
            out.append(f"{stem}_mask.png: {why}")
        depth = read_depth_exr(layout.depth(s, v))
        if depth.shape != (res, res) or depth.dtype != np.float32:
            out.append(
                f"depth/{stem}.exr: {depth.dtype} {depth.shape}, expected float32 {(res, res)}"
            )
        else:
            if np.isnan(depth).any():
                out.append(f"depth/{stem}.exr: NaN values")
            hit = ids > 0
            if not (np.isfinite(depth[hit]).all() and (depth[hit] > 0).all()):
                out.append(f"depth/{stem}.exr: non-finite or non-positive depth on object pixels")
            if meta.extra.get("ground") is not None and not np.isfinite(depth).all():
                out.append(f"depth/{stem}.exr: {int((~np.isfinite(depth)).sum())} pixels miss "
                           "the ground")  # fmt: skip
        vm = meta.views[v]
        if Path(vm.image).name != layout.rgb(s, v).name:
            out.append(f"sc{s:04d}.json: view {v} image {vm.image!r} != {layout.rgb(s, v).name}")
        c2w = np.asarray(vm.cam_to_world, dtype=np.float64)
        if not np.allclose(read_matrix_txt(layout.rt(s, v)), c2w, atol=1e-8):
            out.append(f"{stem}_RT.txt: differs from sc{s:04d}.json cam_to_world")
        azi = geometry.azimuth_rotation(float(vm.extra["azimuth_deg"]))
        if not np.allclose(read_matrix_txt(layout.azi_rot(s, v)), azi, atol=1e-8):
            out.append(f"{stem}_azi_rot.txt: differs from the JSON azimuth")
        K = np.asarray(vm.K, dtype=np.float64)
        if (
            K.shape != (3, 3)
            or not np.isclose(K[0, 2], res / 2)
            or not np.isclose(K[1, 2], res / 2)
        ):
            out.append(f"sc{s:04d}.json: view {v} K {K.tolist()} is not a {res}px pixel-centre K")
    except (OSError, ValueError, KeyError, TypeError, IndexError) as e:
        out.append(f"{stem}: unreadable ({type(e).__name__}: {e})")
    return out


def verify_split(root: str | Path, *, max_problems: int = 200) -> list[str]:
    """Problems of split folder ``root`` (empty list = valid).

    Args:
        root: a split folder made by ``generate``.
        max_problems: stop after this many.
    """
    root = Path(root)
    if not root.is_dir():
        return [f"{root}: not a folder"]
    mpath = root / "manifest.json"
    if not mpath.is_file():
        return [f"{mpath}: missing"]
    try:
        mf = Manifest.from_json(read_json(mpath))
    except (OSError, ValueError) as e:
        return [f"{mpath}: unreadable or incomplete ({e})"]
    n, n_views, (res, w) = mf.n_scenes, mf.n_views, mf.image_hw
    if w != res:
        return [f"{mpath}: resolution {res}x{w} is not square (views are square)"]
    manip = mf.split == MANIP_SPLIT
    layout = (ManipLayout if manip else SplitLayout)(root, n_views=n_views)
    problems: list[str] = []
    for s in range(n):
        missing = [p for p in layout.scene_files(s) if not p.is_file()]
        if missing:
            problems.append(
                f"scene {s}: {len(missing)} file(s) missing, e.g. {missing[0].relative_to(root)}"
            )
            continue
        try:
            raw = read_json(layout.scene_json(s))
            meta = SceneRecord.from_json(raw)
        except (OSError, ValueError) as e:
            problems.append(f"sc{s:04d}.json: unreadable ({e})")
            continue
        for key, want in (("camera_convention", "opencv"), ("depth", "planar_z"),
                          ("index", s), ("preset", mf.preset), ("seed", mf.seed)):  # fmt: skip
            if raw.get(key) != want:
                problems.append(f"sc{s:04d}.json: {key}={raw.get(key)!r}, expected {want!r}")
        if meta.n_views != n_views:
            problems.append(f"sc{s:04d}.json: {meta.n_views} views, expected {n_views}")
            continue
        for v in range(n_views):
            problems += _view_problems(layout, meta, s, v, res)
        if manip:
            assert isinstance(layout, ManipLayout)
            problems += manip_scene_problems(layout, raw, s, res)
        if len(problems) >= max_problems:
            return problems[:max_problems] + ["... (stopped)"]
    known = {layout.rgb(s, v).name for s in range(n) for v in range(n_views)}
    for p in sorted(root.glob("*.png")):
        if p.name.endswith(UORF_NON_VIEW_SUFFIXES):
            continue
        if p.name not in known:
            problems.append(f"{p.name}: stray PNG the uORF loader would read as a view")
    extra = [s for s in layout.scene_indices() if s >= n]
    if extra:
        problems.append(f"scene JSONs beyond n_scenes={n}: {extra[:5]}")
    return problems
