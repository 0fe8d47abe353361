"""Round trips of the on-disk contract (scenefmt): names, mask rule, atomic I/O."""

import numpy as np
import pytest
from PIL import Image

from scenefmt import (
    MASK_BG_LEVEL,
    MASK_SENTINEL_LEVEL,
    SplitLayout,
    atomic_write_json,
    instances_from_uorf_mask,
    is_scene_complete,
    read_depth_exr,
    read_instances,
    read_json,
    read_matrix_txt,
    read_rgb,
    sentinel_size,
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


def _nearest_keeps_block(r: int, b: int) -> bool:
    """PIL NEAREST (uORF's mask resize) of an r x r mask whose top-left b x b block is
    level 0 (rest 16) keeps level 0 at output pixel (0, 0) for every size 64..r."""
    m = np.full((r, r), 16, np.uint8)
    m[:b, :b] = 0
    im = Image.fromarray(m)
    return all(
        np.asarray(im.resize((n, n), Image.Resampling.NEAREST))[0, 0] == 0 for n in range(64, r + 1)
    )


@pytest.mark.parametrize("r", [64, 100, 128, 256, 512])
def test_sentinel_size_is_the_smallest_block_pil_nearest_keeps(r):
    """Brute force against PIL's own NEAREST at every output size 64..r (96, 100, 200 and
    other non-divisors included)."""
    b = sentinel_size(r, r)
    assert _nearest_keeps_block(r, b)
    assert b == 1 or not _nearest_keeps_block(r, b - 1)
    assert b == r // 128 + 1


def test_sentinel_size_values_and_non_square():
    sizes = (16, 32, 64, 100, 127, 128, 256, 512, 1024)
    want = (1, 1, 1, 1, 1, 2, 3, 5, 9)
    assert tuple(sentinel_size(r, r) for r in sizes) == want
    assert sentinel_size(96, 300) == sentinel_size(300, 96) == sentinel_size(300, 300) == 3
    with pytest.raises(ValueError, match="mask size"):
        sentinel_size(0, 4)


@pytest.mark.parametrize("r", [4, 16, 32, 64, 100, 127])
def test_mask_below_128_px_is_format_1_0_single_pixel(r):
    """Below 128 px the sentinel stays the one pixel (0, 0): files are byte-identical
    to format 1.0."""
    rng = np.random.default_rng(r)
    ids = rng.integers(0, 4, (r, r)).astype(np.uint8)
    ids[0, 0] = 0
    old = (MASK_BG_LEVEL + ids.astype(np.int32) * 18).astype(np.uint8)
    old[0, 0] = MASK_SENTINEL_LEVEL
    np.testing.assert_array_equal(uorf_mask_from_instances(ids), old)


def test_mask_sentinel_block_at_256_and_round_trip():
    ids = np.zeros((256, 256), np.uint8)
    ids[3:40, 3:90] = 2  # touches the block's corner diagonally, not the block
    mask = uorf_mask_from_instances(ids)
    assert (mask[:3, :3] == MASK_SENTINEL_LEVEL).all()
    assert int((mask == MASK_SENTINEL_LEVEL).sum()) == 9
    np.testing.assert_array_equal(instances_from_uorf_mask(mask), ids)
    ids[2, 2] = 1
    with pytest.raises(ValueError, match="3x3 block must be background") as e:
        uorf_mask_from_instances(ids)
    assert "\n" not in str(e.value)
    small = np.zeros((64, 64), np.uint8)
    small[1, 1] = 1  # outside the 1x1 block of a 64 px mask
    assert uorf_mask_from_instances(small)[1, 1] == MASK_BG_LEVEL + 18


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


# ----------------------------------------------------------------- scene record, manifest


def test_records_read_back_exactly_what_every_writer_wrote(tmp_path):
    """Scene records and manifests of the generator (ray-cast and manip fixtures) and of
    svorf.synthetic round-trip through the dataclasses unchanged."""
    from generators.testing import write_raycast_manip_split, write_raycast_split
    from scenefmt import Manifest, SceneRecord, SplitLayout, dataset_fingerprint, read_json
    from svorf.synthetic import write_synthetic_split

    roots = [
        write_raycast_split(tmp_path / "rc", n=1, resolution=32),
        write_raycast_manip_split(tmp_path / "manip", n=2, resolution=32),
        write_synthetic_split(tmp_path / "syn", n_scenes=1, resolution=16),
    ]
    for root in roots:
        m = read_json(root / "manifest.json")
        mf = Manifest.from_json(m)
        assert mf.to_json() == m
        d = read_json(SplitLayout(root).scene_json(0))
        rec = SceneRecord.from_json(d)
        assert rec.to_json() == d and rec.n_views == mf.n_views == 4
        assert rec.views[0].image == "00000_sc0000_az00.png" and len(rec.views[0].K) == 3
        assert len(dataset_fingerprint(root)) == 64
    assert Manifest.from_json(read_json(roots[0] / "manifest.json")).image_hw == (32, 32)
    syn = Manifest.from_json(read_json(roots[2] / "manifest.json"))
    assert syn.resolution == 16 and syn.image_hw == (16, 16)  # an int, as every writer
    old = Manifest.from_json({**read_json(roots[2] / "manifest.json"), "resolution": [16, 16]})
    assert old.image_hw == (16, 16)  # synthetic splits written before still read
    assert (
        "manipulation"
        in SceneRecord.from_json(read_json(SplitLayout(roots[1]).scene_json(0))).extra
    )


def test_fingerprint_ignores_last_bit_float_noise_but_not_a_changed_scene(tmp_path):
    """The same split written on two CPUs (whose BLAS kernels round camera matrices
    differently in the last bit) has one fingerprint; a changed number or name changes
    it. Also for a uORF-layout folder (_RT.txt only)."""
    import json
    import shutil

    import numpy as np

    from generators.testing import write_raycast_split
    from scenefmt import dataset_fingerprint

    root = write_raycast_split(tmp_path / "a", n=2, resolution=16)
    base = dataset_fingerprint(root)

    def rewrite(src, dst, fn):
        shutil.copytree(src, dst)
        for p in sorted(dst.glob("sc*.json")):
            p.write_text(json.dumps(fn(json.loads(p.read_text())), indent=1))
        return dst

    def walk(v, fn):
        if isinstance(v, float):
            return fn(v)
        if isinstance(v, dict):
            return {k: walk(x, fn) for k, x in v.items()}
        return [walk(x, fn) for x in v] if isinstance(v, list) else v

    ulp = rewrite(root, tmp_path / "ulp", lambda d: walk(d, lambda x: float(np.nextafter(x, 9e9))))
    assert dataset_fingerprint(ulp) == base  # 1 ulp on every float, another layout
    moved = rewrite(root, tmp_path / "moved", lambda d: {**d, "views": walk(
        d["views"], lambda x: x * (1 + 1e-4))})  # fmt: skip
    assert dataset_fingerprint(moved) != base
    renamed = rewrite(root, tmp_path / "renamed", lambda d: {**d, "preset": "other"})
    assert dataset_fingerprint(renamed) != base

    uorf = tmp_path / "uorf"
    uorf.mkdir()
    (uorf / "00000_sc0000_az00_RT.txt").write_text("0.1 0.2 0.3 1.0\n")
    fp = dataset_fingerprint(uorf)
    (uorf / "00000_sc0000_az00_RT.txt").write_text(f"{np.nextafter(0.1, 1)} 0.2 0.3 1\n")
    assert dataset_fingerprint(uorf) == fp
    (uorf / "00000_sc0000_az00_RT.txt").write_text("0.1 0.2 0.31 1.0\n")
    assert dataset_fingerprint(uorf) != fp


def test_records_read_old_files_and_name_what_is_wrong():
    from scenefmt import Manifest, SceneRecord

    view = {"K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "cam_to_world": [[0] * 4] * 4}
    old = SceneRecord.from_json({"preset": "p", "split": "train", "index": 0, "seed": 0,
                                 "views": [view]})  # fmt: skip
    assert (old.camera_convention, old.depth) == ("opencv", "planar_z")
    with pytest.raises(ValueError, match="view 0: K: expected a 3x3"):
        SceneRecord.from_json({"views": [{**view, "K": [[1, 0], [0, 1]]}]})
    with pytest.raises(ValueError, match="'views' must be a list"):
        SceneRecord.from_json({"views": None})
    with pytest.raises(ValueError, match="'n_views' must be an integer"):
        Manifest.from_json({"n_scenes": 1, "resolution": 32})
    with pytest.raises(ValueError, match="'resolution' must be an integer or"):
        Manifest.from_json({"n_scenes": 1, "n_views": 4, "resolution": "32"})
