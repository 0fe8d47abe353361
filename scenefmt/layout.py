"""File names and the uORF mask rule: the single place that knows them."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Bumped whenever a file name, dtype or convention changes (see CHANGELOG.md).
FORMAT_VERSION = "1.1"

#: ``_mask.png`` grey levels. The uORF loader takes the background to be the
#: *second-lowest* grey level of the mask after ``convert('L')``. To make that rule
#: hold in every view (even a view with no visible object) a sentinel block, the
#: top-left ``b x b`` pixels with ``b = sentinel_size(H, W)`` (``H // 128 + 1`` for a
#: square view: 1 below 128 px, 2 at 128, 3 at 256, 5 at 512, 9 at 1024), which our
#: cameras always see as background, is written at level 0; the background is level
#: ``MASK_BG_LEVEL``; object ``k`` (1-based instance id) is
#: ``MASK_BG_LEVEL + k * MASK_STEP``. The block is a single pixel (0, 0) below 128 px;
#: above it is bigger so that uORF's PIL NEAREST resize to its ``mask_size`` (64 .. the
#: split's resolution) still samples it at output pixel (0, 0): a lone pixel is dropped
#: there, and the second-lowest level would then be an object. The lossless instance
#: ids in ``instances/`` do not carry the sentinel.
MASK_SENTINEL_LEVEL = 0
MASK_BG_LEVEL = 16
MASK_STEP = 18
MAX_INSTANCES = (255 - MASK_BG_LEVEL) // MASK_STEP  # 13

#: The grayscale presets' pixels (``clevr567-gray``): Rec.601 luma ``Y = 0.299 R + 0.587 G
#: + 0.114 B`` of the 8-bit sRGB values, stored in all three channels.
LUMA_REC601 = (0.299, 0.587, 0.114)

_STEM_RE = re.compile(r"^(?P<idx>\d{5})_sc(?P<scene>\d{4})_az(?P<view>\d{2})$")


@dataclass(frozen=True)
class SplitLayout:
    """Paths of every file of one split folder.

    Args:
        root: the split folder.
        n_views: views per scene (4 for every preset); sets the global index.
    """

    root: Path
    n_views: int = 4

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))
        if self.n_views < 1:
            raise ValueError(f"n_views must be >= 1, got {self.n_views}")

    def stem(self, scene: int, view: int) -> str:
        """``{idx:05d}_sc{scene:04d}_az{view:02d}`` with ``idx = scene * n_views + view``."""
        if not 0 <= view < self.n_views:
            raise ValueError(f"view must be in [0, {self.n_views}), got {view}")
        if not 0 <= scene <= 9999:
            raise ValueError(f"scene must be in [0, 9999] (sc%04d names), got {scene}")
        return f"{scene * self.n_views + view:05d}_sc{scene:04d}_az{view:02d}"

    def rgb(self, scene: int, view: int) -> Path:
        return self.root / f"{self.stem(scene, view)}.png"

    def rt(self, scene: int, view: int) -> Path:
        return self.root / f"{self.stem(scene, view)}_RT.txt"

    def azi_rot(self, scene: int, view: int) -> Path:
        return self.root / f"{self.stem(scene, view)}_azi_rot.txt"

    def mask(self, scene: int, view: int) -> Path:
        return self.root / f"{self.stem(scene, view)}_mask.png"

    def instances(self, scene: int, view: int) -> Path:
        return self.root / "instances" / f"{self.stem(scene, view)}.png"

    def depth(self, scene: int, view: int) -> Path:
        return self.root / "depth" / f"{self.stem(scene, view)}.exr"

    def scene_json(self, scene: int) -> Path:
        return self.root / f"sc{scene:04d}.json"

    @property
    def manifest(self) -> Path:
        return self.root / "manifest.json"

    def view_files(self, scene: int, view: int) -> list[Path]:
        """Every per-view file, in the order a writer produces them."""
        return [
            self.rgb(scene, view),
            self.rt(scene, view),
            self.azi_rot(scene, view),
            self.mask(scene, view),
            self.instances(scene, view),
            self.depth(scene, view),
        ]

    def scene_files(self, scene: int) -> list[Path]:
        """Every file of a scene; the scene JSON comes last (it marks completion)."""
        files = [p for v in range(self.n_views) for p in self.view_files(scene, v)]
        return files + [self.scene_json(scene)]

    def scene_indices(self) -> list[int]:
        """Indices of scenes whose JSON exists, sorted."""
        out = []
        for p in self.root.glob("sc[0-9][0-9][0-9][0-9].json"):
            out.append(int(p.stem[2:]))
        return sorted(out)

    @staticmethod
    def parse_stem(stem: str) -> tuple[int, int, int]:
        """Inverse of :meth:`stem`: ``(idx, scene, view)``."""
        m = _STEM_RE.match(stem)
        if m is None:
            raise ValueError(f"not a view file stem of the form 00000_sc0000_az00: {stem!r}")
        return int(m["idx"]), int(m["scene"]), int(m["view"])


#: The manipulation split (``generate --split manip``) and its per-view variants.
MANIP_SPLIT = "manip"
#: Variants of a manipulation scene that are rendered (each has ids and depth).
MANIP_VARIANTS = ("moved", "changed", "providing_bg")
#: Binary manipulation masks (``_mask_for_moving`` etc.): uORF's manipulation loader takes
#: the *lowest* grey level as the background, so "not selected" is 0 and "selected" 255.
MANIP_MASK_OFF = 0
MANIP_MASK_ON = 255


@dataclass(frozen=True)
class ManipLayout(SplitLayout):
    """Paths of a manipulation split: the ordinary files plus, per view, a moved and a
    background-changed variant in uORF's manipulation layout (KovenYu/uORF
    ``data/multiscenes_manip_dataset.py``)::

        {stem}_moved.png                  one object translated by the scene's movement
        {stem}_mask_for_moving.png        that object in the ordinary view (binary)
        {scene:03d}_movement.txt          x and y of the translation, one per line
        {stem}_changed.png                the scene with a donor scene's background
        {stem}_providing_bg.png           the donor scene seen from this camera
        {stem}_mask_for_bg.png            background of the changed view (binary)
        {stem}_mask_for_providing_bg.png  background of the providing view (binary)
        instances/{stem}_{variant}.png    ids of each variant (moved, changed, providing_bg)
        depth/{stem}_{variant}.exr        planar depth of each variant
    """

    def moved(self, scene: int, view: int) -> Path:
        return self.root / f"{self.stem(scene, view)}_moved.png"

    def mask_for_moving(self, scene: int, view: int) -> Path:
        return self.root / f"{self.stem(scene, view)}_mask_for_moving.png"

    def changed(self, scene: int, view: int) -> Path:
        return self.root / f"{self.stem(scene, view)}_changed.png"

    def providing_bg(self, scene: int, view: int) -> Path:
        return self.root / f"{self.stem(scene, view)}_providing_bg.png"

    def mask_for_bg(self, scene: int, view: int) -> Path:
        return self.root / f"{self.stem(scene, view)}_mask_for_bg.png"

    def mask_for_providing_bg(self, scene: int, view: int) -> Path:
        return self.root / f"{self.stem(scene, view)}_mask_for_providing_bg.png"

    def movement(self, scene: int) -> Path:
        """``{scene:03d}_movement.txt`` (uORF's name: at least three digits)."""
        if not 0 <= scene <= 9999:
            raise ValueError(f"scene must be in [0, 9999], got {scene}")
        return self.root / f"{scene:03d}_movement.txt"

    def variant_rgb(self, scene: int, view: int, variant: str) -> Path:
        """The RGB file of ``variant`` (one of :data:`MANIP_VARIANTS`)."""
        return getattr(self, _check_variant(variant))(scene, view)

    def variant_instances(self, scene: int, view: int, variant: str) -> Path:
        v = _check_variant(variant)
        return self.root / "instances" / f"{self.stem(scene, view)}_{v}.png"

    def variant_depth(self, scene: int, view: int, variant: str) -> Path:
        v = _check_variant(variant)
        return self.root / "depth" / f"{self.stem(scene, view)}_{v}.exr"

    def manip_view_files(self, scene: int, view: int) -> list[Path]:
        """The manipulation files of one view (not the ordinary ones)."""
        out = [
            self.mask_for_moving(scene, view),
            self.mask_for_bg(scene, view),
            self.mask_for_providing_bg(scene, view),
        ]
        for v in MANIP_VARIANTS:
            out += [
                self.variant_rgb(scene, view, v),
                self.variant_instances(scene, view, v),
                self.variant_depth(scene, view, v),
            ]
        return out

    def view_files(self, scene: int, view: int) -> list[Path]:
        return super().view_files(scene, view) + self.manip_view_files(scene, view)

    def scene_files(self, scene: int) -> list[Path]:
        """Every file of a scene; the movement file before the scene JSON (last)."""
        files = [p for v in range(self.n_views) for p in self.view_files(scene, v)]
        return files + [self.movement(scene), self.scene_json(scene)]


def _check_variant(variant: str) -> str:
    if variant not in MANIP_VARIANTS:
        raise ValueError(f"variant must be one of {MANIP_VARIANTS}, got {variant!r}")
    return variant


def manip_mask(selected: np.ndarray) -> np.ndarray:
    """A binary manipulation mask: uint8 [H, W], ``MANIP_MASK_ON`` where ``selected``.

    uORF's manipulation loader reads these masks (``_mask_for_moving``, ``_mask_for_bg``,
    ``_mask_for_providing_bg``) after ``convert('L')`` and a NEAREST resize and takes the
    lowest grey level as "not selected"; with only two levels 0 / 255 that holds at any
    size, and a mask with nothing selected is a single level (uORF then selects nothing).
    """
    selected = np.asarray(selected)
    if selected.ndim != 2:
        raise ValueError(f"selected must be [H, W], got shape {selected.shape}")
    return np.where(selected.astype(bool), MANIP_MASK_ON, MANIP_MASK_OFF).astype(np.uint8)


def is_scene_complete(layout: SplitLayout, scene: int) -> bool:
    """True when the scene JSON and every per-view file exist (the writer's rule).

    Writers move the per-view files into place first and the scene JSON last,
    each by atomic rename, so a scene killed mid-write is never complete.
    """
    return all(p.is_file() for p in reversed(layout.scene_files(scene)))


#: uORF's smallest mask size that :func:`sentinel_size` covers (its default is 128).
MIN_UORF_MASK_SIZE = 64


def sentinel_size(h: int, w: int) -> int:
    """Side ``b`` of the top-left sentinel block of a ``[h, w]`` ``_mask.png``.

    The smallest ``b`` such that PIL NEAREST resizing (what uORF's loader does to
    ``mask_size``) to any size from ``MIN_UORF_MASK_SIZE`` up to ``max(h, w)`` takes
    output pixel (0, 0) from inside the ``b x b`` block: PIL samples source index
    ``floor((0 + 0.5) * n_in / n_out)``, at most ``n_in // 128`` for ``n_out >= 64``, so
    ``b = max(h, w) // 128 + 1`` (1 below 128 px, so those files keep a single sentinel
    pixel; 2 at 128, 3 at 256, 5 at 512, 9 at 1024).

    Args:
        h, w: the mask's height and width in pixels (>= 1).
    """
    if h < 1 or w < 1:
        raise ValueError(f"mask size must be >= 1 x 1, got {h} x {w}")
    return max(int(h), int(w)) // (2 * MIN_UORF_MASK_SIZE) + 1


def uorf_mask_from_instances(ids: np.ndarray) -> np.ndarray:
    """Build the uORF-compatible grey mask from instance ids.

    Args:
        ids: uint8 [H, W], 0 = background, k >= 1 = object k; the top-left
            ``b x b`` block (``b = sentinel_size(H, W)``) must be background.

    Returns:
        uint8 [H, W]: sentinel ``MASK_SENTINEL_LEVEL`` on the top-left ``b x b`` block,
        background ``MASK_BG_LEVEL``, object k at ``MASK_BG_LEVEL + k * MASK_STEP``.
    """
    ids = np.asarray(ids)
    if ids.ndim != 2:
        raise ValueError(f"ids must be [H, W], got shape {ids.shape}")
    if ids.max(initial=0) > MAX_INSTANCES:
        raise ValueError(f"at most {MAX_INSTANCES} instances fit the mask, got id {ids.max()}")
    b = sentinel_size(*ids.shape)
    if np.any(ids[:b, :b] != 0):
        raise ValueError(
            f"the top-left {b}x{b} block must be background for the uORF mask sentinel"
        )
    mask = (MASK_BG_LEVEL + ids.astype(np.int32) * MASK_STEP).astype(np.uint8)
    mask[:b, :b] = MASK_SENTINEL_LEVEL
    return mask


def instances_from_uorf_mask(mask: np.ndarray) -> np.ndarray:
    """Inverse of :func:`uorf_mask_from_instances`: uint8 [H, W] mask -> uint8 [H, W] ids.

    The sentinel (level ``MASK_SENTINEL_LEVEL``, a single pixel (0, 0) or the
    ``sentinel_size`` block) reads as background.
    """
    mask = np.asarray(mask).astype(np.int32)
    ids = (mask - MASK_BG_LEVEL) // MASK_STEP
    ids[mask < MASK_BG_LEVEL] = 0
    bad = (mask >= MASK_BG_LEVEL) & ((mask - MASK_BG_LEVEL) % MASK_STEP != 0)
    if bad.any():
        raise ValueError("mask has grey levels that are not on the instance grid")
    return ids.astype(np.uint8)
