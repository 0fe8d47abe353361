"""Generator config, CLI errors, writer/verify and the benchmark bridge (no rendering)."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest

from generators import cli
from generators.pipeline import GenerateConfig, generate_dataset
from generators.testing import write_raycast_split
from generators.verify import verify_split
from scenefmt import (
    MASK_BG_LEVEL,
    MASK_SENTINEL_LEVEL,
    SceneRecord,
    SplitLayout,
    atomic_write_json,
    read_instances,
    read_json,
    uorf_mask_from_instances,
    write_instances,
    write_mask,
    write_rgb,
)


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return write_raycast_split(tmp_path_factory.mktemp("gen") / "train", n=2, resolution=32)


def _copy(split: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "copy"
    shutil.copytree(split, dst)
    return dst


def test_config_defaults_and_validation():
    c = GenerateConfig(preset="clevr567")
    assert c.split_name() == "train" and c.n_scenes() == 1000
    assert c.out_dir() == Path("data/clevr567/train")
    assert GenerateConfig(preset="packed-clevr11").split_name() == "test"
    r = GenerateConfig(preset="clevr567", samples=3, denoise=False, bounces=2).render_settings()
    assert (r.samples, r.denoise, r.max_bounces, r.diffuse_bounces) == (3, False, 2, 2)
    for kw, msg in [({"preset": "nope"}, "choose from clevr567"), ({"n": 0}, "--n"),
                    ({"resolution": 15}, "--resolution"), ({"split": "val"}, "split"),
                    ({"shard": (2, 2)}, "--shard"), ({"workers": 0}, "--workers")]:  # fmt: skip
        with pytest.raises(ValueError, match=msg):
            GenerateConfig(**{"preset": "clevr567", **kw})
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.n = 3  # type: ignore[misc]


@pytest.mark.parametrize(
    "args,msg",
    [
        (["--preset", "nope"], "unknown preset 'nope' (choose from clevr567"),
        (["--preset", "clevr567", "--n", "0"], "--n"),
        (["--preset", "clevr567", "--n", "-3"], "--n"),
        (["--preset", "clevr567", "--resolution", "8"], "--resolution"),
        (["--preset", "clevr567", "--shard", "x"], "--shard"),
    ],
)
def test_cli_bad_input_one_line_exit_2_nothing_written(args, msg, tmp_path, capsys):
    out = tmp_path / "out"
    with pytest.raises(SystemExit) if "--shard" in args else _nullctx():
        rc = cli.main([*args, "--out", str(out)])
        assert rc == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and msg in err
    assert not out.exists()


class _nullctx:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False


def test_cli_unwritable_out(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    rc = cli.main(["--preset", "clevr567", "--n", "1", "--out", str(f / "sub")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "--out" in err
    assert not (f / "sub").exists()


def test_cli_missing_bpy(tmp_path, capsys, monkeypatch):
    import generators.blender_backend as bb

    monkeypatch.setattr(bb, "bpy_available", lambda: False)
    out = tmp_path / "o"
    rc = cli.main(["--preset", "clevr567", "--n", "1", "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "bpy" in err
    assert not out.exists()
    with pytest.raises(ImportError):
        generate_dataset(GenerateConfig(preset="clevr567", n=1, out=out, progress=False))
    assert not out.exists()


def test_existing_folder_with_other_resolution_is_refused(split, tmp_path):
    d = _copy(split, tmp_path)
    with pytest.raises(ValueError, match="resolution"):
        generate_dataset(GenerateConfig(preset="clevr567", n=2, out=d, resolution=64))


def test_complete_scenes_are_skipped_without_bpy(split, tmp_path, monkeypatch):
    import generators.blender_backend as bb

    monkeypatch.setattr(bb, "bpy_available", lambda: False)
    d = _copy(split, tmp_path)
    s = generate_dataset(GenerateConfig(preset="clevr567", n=2, out=d, resolution=32,
                                        samples=1, denoise=False, progress=False))  # fmt: skip
    assert s.scenes_this_run == 0 and s.scenes_skipped == 2


def test_verify_passes_on_a_good_split(split, capsys):
    assert verify_split(split) == []
    assert cli.main(["verify", str(split)]) == 0


@pytest.mark.parametrize("damage", ["missing", "mask", "ids", "rt", "rgb_shape", "stray"])
def test_verify_finds_problems(split, tmp_path, damage, capsys):
    d = _copy(split, tmp_path)
    layout = SplitLayout(d)
    if damage == "missing":
        layout.depth(1, 2).unlink()
    elif damage == "mask":
        m = np.asarray(__import__("PIL.Image").Image.open(layout.mask(0, 1))).copy()
        m[5, 5] = 200
        write_instances(layout.mask(0, 1), m)
    elif damage == "ids":
        ids = np.zeros((32, 32), np.uint8)
        ids[3, 3] = 12  # not an instance of the scene
        write_instances(layout.instances(0, 0), ids)
    elif damage == "rt":
        layout.rt(1, 0).write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    elif damage == "rgb_shape":
        write_rgb(layout.rgb(0, 3), np.zeros((16, 16, 3), np.uint8))
    elif damage == "stray":
        write_rgb(d / "extra.png", np.zeros((32, 32, 3), np.uint8))
    problems = verify_split(d)
    assert problems, damage
    assert cli.main(["verify", str(d)]) != 0


@pytest.fixture(scope="module")
def split256(tmp_path_factory):
    return write_raycast_split(tmp_path_factory.mktemp("gen256") / "train", n=1, resolution=256)


def test_verify_passes_at_256_and_catches_a_one_pixel_sentinel(split256, tmp_path):
    """At 256 px the sentinel is a 3x3 block; a format 1.0 mask (pixel (0, 0) only) loses
    its sentinel in uORF's NEAREST resize to mask_size 128 (or 64), and verify says so."""
    assert verify_split(split256) == []
    assert read_json(split256 / "manifest.json")["conventions"]["mask"]["sentinel_block"] == 3
    d = _copy(split256, tmp_path)
    layout = SplitLayout(d)
    ids = read_instances(layout.instances(0, 2))
    old = uorf_mask_from_instances(ids)
    old[:3, :3] = MASK_BG_LEVEL
    old[0, 0] = MASK_SENTINEL_LEVEL
    write_mask(layout.mask(0, 2), old)
    problems = verify_split(d)
    assert any("00002_sc0000_az02_mask.png" in p and "resize to mask_size" in p for p in problems)
    assert all("\n" not in p for p in problems)


def test_format_1_0_split_at_64_px_verifies_and_resumes(tmp_path, monkeypatch):
    """A 64 px split written by format 1.0 (single sentinel pixel, no sentinel_block
    key) is byte-identical in its masks, passes verify and resumes (skips its scenes)."""
    import generators.blender_backend as bb

    d = write_raycast_split(tmp_path / "train", n=2, resolution=64)
    layout = SplitLayout(d)
    for s_ in range(2):
        for v in range(4):
            ids = read_instances(layout.instances(s_, v))
            want = (MASK_BG_LEVEL + ids.astype(np.int32) * 18).astype(np.uint8)
            want[0, 0] = MASK_SENTINEL_LEVEL
            np.testing.assert_array_equal(read_instances(layout.mask(s_, v)), want)
    m = read_json(d / "manifest.json")
    assert m["conventions"]["mask"]["sentinel_block"] == 1
    m["format_version"] = "1.0"
    del m["conventions"]["mask"]["sentinel_block"]
    atomic_write_json(d / "manifest.json", m)
    assert verify_split(d) == []
    monkeypatch.setattr(bb, "bpy_available", lambda: False)
    s = generate_dataset(GenerateConfig(preset="clevr567", n=2, out=d, resolution=64,
                                        samples=1, denoise=False, progress=False))  # fmt: skip
    assert s.scenes_this_run == 0 and s.scenes_skipped == 2
    assert verify_split(d) == []


def test_manifest_and_scene_json_contents(split):
    m = read_json(split / "manifest.json")
    for k in ("format_version", "preset", "split", "n_scenes", "n_views", "resolution", "seed",
              "generator_version", "conventions"):  # fmt: skip
        assert k in m
    assert m["generator"].startswith("generators ")
    j = read_json(split / "sc0001.json")
    assert j["index"] == 1 and j["scene_seed"] == 1 and j["camera_convention"] == "opencv"
    assert j["views"][0]["image"] == "00004_sc0001_az00.png"
    assert np.asarray(j["views"][0]["K"]).shape == (3, 3)


def test_benchmark_bridge_finds_our_entry_point_and_fields():
    from benchmark import generator_bridge as gb

    cls, fn = gb.entry_point()
    assert cls is GenerateConfig and fn.__module__ == "generators.pipeline"
    fields = {f.name for f in dataclasses.fields(cls)}
    assert {"preset", "split", "n", "out", "resolution", "seed", "progress", "samples",
            "denoise", "workers", "backend", "address"} <= fields  # fmt: skip
    assert set(gb.known_presets()) >= {"clevr567", "clevr567-gray"}


def test_bridge_call_reaches_generate_dataset(tmp_path, monkeypatch):
    import generators.pipeline as pl
    from benchmark import generator_bridge as gb

    seen = []
    monkeypatch.setattr(pl, "generate_dataset", lambda cfg: seen.append(cfg))
    gb.generate(tmp_path, preset="clevr567", split="test", n_scenes=3, resolution=32,
                samples=2, denoise=False, seed=5, progress=False, workers=1)  # fmt: skip
    gb.generate(tmp_path, preset="clevr567", split="test", n_scenes=3, resolution=32,
                samples=None, denoise=None, seed=5, progress=False)  # fmt: skip
    cfg, default = seen
    assert (cfg.preset, cfg.split, cfg.n, cfg.out, cfg.resolution, cfg.samples, cfg.denoise,
            cfg.seed, cfg.workers) == ("clevr567", "test", 3, tmp_path, 32, 2, False, 5, 1)  # fmt: skip
    # None keeps the generator's own defaults.
    fresh = GenerateConfig(preset="clevr567", split="test", n=3, out=tmp_path)
    assert (default.samples, default.denoise) == (fresh.samples, fresh.denoise)
    with pytest.raises(gb.DatasetUnavailable, match="not registered"):
        gb.generate(tmp_path, preset="clever567", split="test", n_scenes=1, resolution=32,
                    samples=None, denoise=None, seed=0)  # fmt: skip


def test_contact_sheet_shape(split):
    from generators.preview import contact_sheet

    sheet = contact_sheet(split)
    assert sheet.dtype == np.uint8 and sheet.shape == (2 * 36, 12 * 36, 3)


def test_camera_radius_override_changes_the_rig_and_the_identity(tmp_path):
    from generators.sampling import make_scene

    cfg = GenerateConfig(preset="clevr567", camera_radius=8.0, n=1, resolution=32)
    p = cfg.preset_obj()
    assert p.camera.radius == 8.0
    s = make_scene(p, "train", 0, 0)
    assert all(abs(v.radius - 8.0) <= p.camera.radius_jitter + 1e-9 for v in s.views)
    with pytest.raises(ValueError, match="camera_radius"):
        GenerateConfig(preset="clevr567", camera_radius=0.1)


def test_gray_scene_json_differs_only_by_flags():
    from generators.imageops import GRAYSCALE_FORMULA, grayscale_rec601
    from generators.writer import grayscale_json

    d = SceneRecord.from_json({"preset": "clevr567", "seed": 0, "objects": [], "views": []})
    g = grayscale_json(d, "clevr567-gray", "converted")
    assert g.to_json() == {**d.to_json(), "preset": "clevr567-gray",
                           "grayscale": GRAYSCALE_FORMULA, "rgb_source": "converted"}  # fmt: skip
    rgb = np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255], [10, 20, 30]]], np.uint8)
    y = grayscale_rec601(rgb)
    assert y[..., 0].tolist() == [[76, 150, 29, 18]] and (y == y[..., :1]).all()


def test_manifest_is_deterministic_and_has_status(split):
    m = read_json(split / "manifest.json")
    assert "status" not in m or m["status"] in ("in_progress", "complete")
    for k in m:
        assert "time" not in k and "host" not in k
