"""Round trips of the on-disk contract (scenefmt): names, mask rule, atomic I/O."""

import numpy as np
import pytest
from PIL import Image

from scenefmt import (
    MASK_BG_LEVEL,
    SplitLayout,
    atomic_write_json,
    instances_from_uorf_mask,
    is_scene_complete,
    read_depth_exr,
    read_instances,
    read_json,
    read_matrix_txt,
    read_rgb,
    uorf_mask_from_instances,
    write_depth_exr,
    write_instances,
    write_mask,
    write_matrix_txt,
    write_rgb,
)


def test_stem_names_and_parse():
    lay = SplitLayout("/x", n_views=4)
    assert lay.stem(3, 2) == "00014_sc0003_az02"
    assert lay.rgb(0, 0).name == "00000_sc0000_az00.png"
    assert lay.mask(1, 3).name == "00007_sc0001_az03_mask.png"
    assert lay.rt(1, 3).name == "00007_sc0001_az03_RT.txt"
    assert lay.azi_rot(1, 3).name == "00007_sc0001_az03_azi_rot.txt"
    assert lay.instances(1, 3).parent.name == "instances"
    assert lay.depth(1, 3).suffix == ".exr"
    assert lay.scene_json(12).name == "sc0012.json"
    assert SplitLayout.parse_stem("00014_sc0003_az02") == (14, 3, 2)
    with pytest.raises(ValueError, match="view"):
        lay.stem(0, 4)
    with pytest.raises(ValueError, match="stem"):
        SplitLayout.parse_stem("foo")


def test_mask_rule_background_second_lowest_even_without_objects():
    for ids in (np.zeros((8, 8), np.uint8), np.pad(np.full((4, 4), 3, np.uint8), 2)):
        mask = uorf_mask_from_instances(ids)
        levels = np.unique(mask)
        assert levels[1] == MASK_BG_LEVEL  # uORF: bg = second-lowest grey
        np.testing.assert_array_equal(instances_from_uorf_mask(mask), ids)


def test_mask_rejects_object_on_sentinel_pixel():
    ids = np.ones((4, 4), np.uint8)
    with pytest.raises(ValueError, match="sentinel"):
        uorf_mask_from_instances(ids)


def test_file_round_trips_bit_exact(tmp_path):
    lay = SplitLayout(tmp_path)
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (6, 5, 3), dtype=np.uint8)
    ids = rng.integers(0, 5, (6, 5)).astype(np.uint8)
    ids[0, 0] = 0
    depth = rng.uniform(6, 20, (6, 5)).astype(np.float32)
    depth[0, :] = np.inf
    rt = rng.normal(size=(4, 4))
    write_rgb(lay.rgb(0, 0), rgb)
    write_instances(lay.instances(0, 0), ids)
    write_mask(lay.mask(0, 0), uorf_mask_from_instances(ids))
    write_depth_exr(lay.depth(0, 0), depth)
    write_matrix_txt(lay.rt(0, 0), rt)
    atomic_write_json(lay.scene_json(0), {"seed": 1, "a": [1.5, 2]})
    np.testing.assert_array_equal(read_rgb(lay.rgb(0, 0)), rgb)
    np.testing.assert_array_equal(read_instances(lay.instances(0, 0)), ids)
    np.testing.assert_array_equal(read_depth_exr(lay.depth(0, 0)), depth)
    np.testing.assert_allclose(read_matrix_txt(lay.rt(0, 0)), rt, atol=1e-9)
    assert read_json(lay.scene_json(0)) == {"seed": 1, "a": [1.5, 2]}
    # The uORF loader's view: mask PNG converts to L unchanged.
    m = np.asarray(Image.open(lay.mask(0, 0)).convert("L"))
    assert np.unique(m)[1] == MASK_BG_LEVEL
    # No temp files left behind.
    assert not list(tmp_path.rglob("*.tmp"))


def test_scene_complete_only_with_json_last(tmp_path):
    lay = SplitLayout(tmp_path, n_views=1)
    assert not is_scene_complete(lay, 0)
    for p in lay.view_files(0, 0):
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"x")
    assert not is_scene_complete(lay, 0)
    lay.scene_json(0).write_text("{}")
    assert is_scene_complete(lay, 0)
    assert lay.scene_indices() == [0]
