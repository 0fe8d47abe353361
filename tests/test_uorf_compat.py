"""The uORF loader's rules (KovenYu/uORF ``data/multiscenes_dataset.py``) hold on our files.

The loader (1) globs ``*.png`` in the split folder and drops names with its known
suffixes (``_mask``, ``_moved``, ...), (2) groups views by the ``sc%04d`` substring,
(3) reads ``_mask.png`` with PIL ``convert('L')`` and takes the *second-lowest* grey
level as background. Our fixture is written by the real writer from ray-cast passes
(no bpy).
"""

from __future__ import annotations

from glob import glob
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from generators.presets import get_preset
from generators.sampling import make_scene
from generators.spec import RenderSettings
from generators.testing import write_raycast_manip_split, write_raycast_split
from generators.verify import UORF_NON_VIEW_SUFFIXES
from generators.writer import ViewImages, write_scene
from scenefmt import (
    MASK_BG_LEVEL,
    MASK_SENTINEL_LEVEL,
    ManipLayout,
    SplitLayout,
    read_instances,
    uorf_mask_from_instances,
    write_mask,
)

#: The suffixes whose ``*{suffix}.png`` files uORF's loaders subtract from ``glob('*.png')``,
#: in the order of their subtraction (``MultiscenesDataset.__init__``; the manipulation
#: loader ``MultiscenesManipDataset`` subtracts the same seven). Every other PNG in the
#: folder is a view.
_UORF_SUFFIXES = ("_mask", "_mask_for_moving", "_moved", "_changed", "_providing_bg",
                  "_mask_for_bg", "_mask_for_providing_bg")  # fmt: skip


def uorf_filenames(root: Path, n_scenes: int) -> list[list[str]]:
    """Re-implementation of the uORF loader's file discovery."""
    filenames = set(glob(str(root / "*.png")))
    for suffix in _UORF_SUFFIXES:
        filenames -= set(glob(str(root / f"*{suffix}.png")))
    filenames = sorted(filenames)
    return [sorted(x for x in filenames if f"sc{i:04d}" in x) for i in range(n_scenes)]


def uorf_fg_after_resize(mask_path: str, mask_size: int) -> tuple[np.ndarray, np.ndarray]:
    """uORF's loader with its ``mask_size``: open, convert('RGB'), convert('L'), PIL
    NEAREST resize to (mask_size, mask_size) (torchvision ``TF.resize`` on a PIL image),
    background = second-lowest level. Returns (fg bool, resized grey uint8)."""
    mask_l = Image.open(mask_path).convert("RGB").convert("L")
    m = np.asarray(mask_l.resize((mask_size, mask_size), Image.Resampling.NEAREST))
    levels = np.unique(m)
    assert len(levels) >= 2, f"uORF needs 2 grey levels, got {levels}"
    return m != levels[1], m


def _synthetic_ids(r: int, seed: int) -> list[np.ndarray]:
    """Instance ids uint8 [r, r] of a few views: rectangles of ids 1..4 (one near the
    sentinel block), and a view with no object."""
    rng = np.random.default_rng(seed)
    views = []
    for _ in range(3):
        ids = np.zeros((r, r), np.uint8)
        for k in range(1, 5):
            y, x = rng.integers(0, r - r // 4, 2)
            hh, ww = rng.integers(r // 16, r // 3, 2)
            ids[y : y + hh, x : x + ww] = k
        ids[: r // 128 + 1, : r // 128 + 1] = 0  # the sentinel block is background
        views.append(ids)
    near = np.zeros((r, r), np.uint8)
    b = r // 128 + 1
    near[b : r // 2, b : r // 2] = 3  # diagonally next to the block
    near[0:b, b : r // 3] = 1  # beside it in the top rows
    return views + [near, np.zeros((r, r), np.uint8)]


@pytest.mark.parametrize("res", [64, 128, 256])
def test_uorf_rule_survives_nearest_resize_to_mask_size(res, tmp_path):
    """uORF resizes ``_mask.png`` to ``mask_size`` (default 128) with NEAREST before its
    second-lowest rule; fg/bg must equal the equally resized ids except the sentinel."""
    for j, ids in enumerate(_synthetic_ids(res, res)):
        path = tmp_path / f"v{j}_mask.png"
        write_mask(path, uorf_mask_from_instances(ids))
        ids_im = Image.fromarray(ids)
        for n in sorted({64, 128, res}):
            fg, m = uorf_fg_after_resize(str(path), n)
            ids_n = np.asarray(ids_im.resize((n, n), Image.Resampling.NEAREST))
            sentinel = m == MASK_SENTINEL_LEVEL
            assert sentinel[0, 0], (res, n, j)
            assert np.array_equal(fg[~sentinel], ids_n[~sentinel] > 0), (res, n, j)
            assert (ids_n[sentinel] == 0).all()


def test_one_pixel_sentinel_breaks_uorf_at_256():
    """The format 1.0 bug this guards against: at 256 px a lone sentinel pixel is
    dropped by the resize to 128 and an object becomes uORF's background."""
    ids = _synthetic_ids(256, 1)[0]
    mask = uorf_mask_from_instances(ids)
    mask[:3, :3] = MASK_BG_LEVEL
    mask[0, 0] = MASK_SENTINEL_LEVEL
    m = np.asarray(Image.fromarray(mask).resize((128, 128), Image.Resampling.NEAREST))
    assert np.unique(m)[0] == MASK_BG_LEVEL and np.unique(m)[1] != MASK_BG_LEVEL


def uorf_fg_mask(mask_path: str) -> np.ndarray:
    """uORF: background = second-lowest grey level after convert('L'); the rest is fg."""
    mask_l = np.asarray(Image.open(mask_path).convert("L"))
    greyscale = np.unique(mask_l)  # sorted
    bg_color = greyscale[1]
    return mask_l != bg_color, mask_l, greyscale


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return write_raycast_split(tmp_path_factory.mktemp("uorf") / "train", n=2, resolution=32)


def test_glob_and_grouping_find_exactly_our_views(split):
    groups = uorf_filenames(split, 2)
    layout = SplitLayout(split)
    for s, files in enumerate(groups):
        assert [Path(f).name for f in files] == [layout.rgb(s, v).name for v in range(4)]
    # nothing of ours (instances, depth) is picked up as a view
    assert not any("instances" in f or "depth" in f for g in groups for f in g)


def test_glob_and_grouping_find_exactly_our_views_in_a_manipulation_split(tmp_path):
    """The variants (``_moved``, ``_changed``, ``_providing_bg``) and their masks are not
    views; a suffix missing from the list above would make them views here."""
    root = write_raycast_manip_split(tmp_path / "manip", "clevr567", n=2, resolution=32)
    layout = ManipLayout(root)
    assert any(root.glob("*_providing_bg.png"))
    for s, files in enumerate(uorf_filenames(root, 2)):
        assert [Path(f).name for f in files] == [layout.rgb(s, v).name for v in range(4)]


def test_verify_skips_exactly_the_pngs_uorf_skips():
    """``generate verify`` flags every other PNG as a stray view, as uORF would read it."""
    assert set(UORF_NON_VIEW_SUFFIXES) == {f"{s}.png" for s in _UORF_SUFFIXES}


def test_second_lowest_grey_is_background_and_fg_matches_instances(split):
    layout = SplitLayout(split)
    for s in range(2):
        for v in range(4):
            fg, mask_l, levels = uorf_fg_mask(str(layout.mask(s, v)))
            ids = read_instances(layout.instances(s, v))
            assert levels[0] == 0 and levels[1] == MASK_BG_LEVEL
            want = ids > 0
            want[0, 0] = True  # the sentinel pixel reads as its own (lowest) level
            assert np.array_equal(fg, want)
            # every instance is its own grey level
            for k in np.unique(ids[ids > 0]):
                assert len(np.unique(mask_l[ids == k])) == 1


def test_view_without_objects_keeps_background_rule(tmp_path):
    """Even a view where no object is visible has background as second-lowest level."""
    p = get_preset("clevr567")
    spec = make_scene(p, "train", 0, 0, RenderSettings(resolution=16, samples=1))
    layout = SplitLayout(tmp_path)
    empty = np.zeros((16, 16), np.uint8)
    views = [ViewImages(np.zeros((16, 16, 3), np.uint8), empty, np.ones((16, 16), np.float32))] * 4
    write_scene(layout, spec, views)
    fg, _, levels = uorf_fg_mask(str(layout.mask(0, 0)))
    assert list(levels) == [0, MASK_BG_LEVEL]
    assert fg.sum() == 1 and fg[0, 0]


def test_rt_and_azi_rot_load_with_numpy(split):
    layout = SplitLayout(split)
    rt = np.loadtxt(layout.rt(0, 0))
    azi = np.loadtxt(layout.azi_rot(0, 0))
    assert rt.shape == (4, 4) and azi.shape == (3, 3)
    assert np.allclose(azi @ azi.T, np.eye(3))
