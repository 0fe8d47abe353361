"""The manipulation split (``generate --split manip``) read by uORF's manipulation loader.

:func:`uorf_manip_load` re-implements the rules of KovenYu/uORF
``data/multiscenes_manip_dataset.py`` (``MultiscenesManipDataset.__init__``,
``__getitem__`` and ``collate_fn``) with PIL and numpy, and the slot choice of
``models/uorf_manip_model.py`` (IoU of each foreground slot's mask with the
``_mask_for_moving`` foreground of the first view). The fast tests run it on a ray-cast
fixture; the ``blender`` tests on tiny (32x32, 2 samples) Cycles renders of clevr567 and
room-chair made by ``generate_dataset``.
"""

from __future__ import annotations

import json
import os
from glob import glob
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from generators.blender_backend import bpy_available
from generators.manip import OFFSET_RANGE, make_manip_scene, variant_specs_from_json
from generators.presets import get_preset
from generators.spec import SceneSpec
from generators.testing import write_raycast_manip_split
from generators.verify import verify_split
from scenefmt import ManipLayout, read_instances, read_json

#: The suffix sets uORF subtracts from ``glob('*.png')`` (order as in its __init__).
_UORF_MANIP_SUFFIXES = ("_mask", "_mask_for_moving", "_moved", "_mask_for_bg",
                        "_mask_for_providing_bg", "_changed", "_providing_bg")  # fmt: skip


def _mask_levels(path: str, mask_size: int) -> np.ndarray:
    """uORF's ``_transform_mask`` of ``convert('L')`` (the order of grey levels is all its
    ``unique(sorted=True)`` looks at; the [-1, 1] normalisation keeps it)."""
    m = Image.open(path).convert("RGB").convert("L")
    return np.asarray(m.resize((mask_size, mask_size), Image.Resampling.NEAREST))


def uorf_manip_load(root: Path, n_scenes: int, n_img_each_scene: int = 4, mask_size: int = 128):
    """uORF's ``MultiscenesManipDataset`` (test mode, no shuffle) + ``collate_fn``, per scene."""
    image_filenames = set(glob(os.path.join(root, "*.png")))
    for suffix in _UORF_MANIP_SUFFIXES:
        image_filenames -= set(glob(os.path.join(root, f"*{suffix}.png")))
    filenames = sorted(image_filenames)
    scenes = [[x for x in filenames if f"sc{i:04d}" in x] for i in range(n_scenes)]
    batches = []
    for scene_idx, scene_filenames in enumerate(scenes):
        rets = []
        for path in scene_filenames[:n_img_each_scene]:
            ret = {"path": path}
            for key, suffix in (("img_data", ""), ("img_data_moved", "_moved"),
                                ("img_data_changed", "_changed"),
                                ("img_data_bg", "_providing_bg")):  # fmt: skip
                ret[key] = np.asarray(
                    Image.open(path.replace(".png", f"{suffix}.png")).convert("RGB")
                )
            ret["cam2world"] = np.loadtxt(path.replace(".png", "_RT.txt"))
            ret["azi_rot"] = np.loadtxt(path.replace(".png", "_azi_rot.txt"))
            mask_path = path.replace(".png", "_mask_for_moving.png")
            if os.path.isfile(mask_path):
                m = _mask_levels(mask_path, mask_size)
                ret["fg_idx"] = m != np.unique(m)[0]
            mv = os.path.join(os.path.dirname(path), f"{scene_idx:03d}_movement.txt")
            with open(mv) as f:
                x = float(f.readline())
                y = float(f.readline())
            ret["movement"] = np.array([x, y, 0.0])
            for key, suffix in (("bg_idx", "_mask_for_bg"),
                                ("providing_bg_idx", "_mask_for_providing_bg")):  # fmt: skip
                mask_path = path.replace(".png", f"{suffix}.png")
                if os.path.isfile(mask_path):
                    m = _mask_levels(mask_path, mask_size)
                    ret[key] = m == np.unique(m)[0]
            rets.append(ret)
        # collate_fn: stacks these unconditionally (a missing one is a KeyError there).
        batch = {k: np.stack([r[k] for r in rets]) for k in (
            "img_data", "img_data_moved", "img_data_changed", "img_data_bg", "cam2world",
            "azi_rot", "bg_idx", "providing_bg_idx")}  # fmt: skip
        if "fg_idx" in rets[0]:
            batch["fg_idx"] = np.stack([r["fg_idx"] for r in rets])
        batch["movement"] = rets[0]["movement"]
        batch["paths"] = [r["path"] for r in rets]
        batches.append(batch)
    return batches


def uorf_move_slot(labels: np.ndarray, fg_idx: np.ndarray, num_slots: int) -> int:
    """uORF's slot choice: ``argmax_k IoU(labels == k, fg_idx)`` over k = 1..K-1 (slot 0 is
    uORF's background), returned as the slot number k."""
    ious = []
    for k in range(1, num_slots):
        m = labels == k
        union = (fg_idx | m).sum()
        ious.append((fg_idx & m).sum() / union if union else 0.0)
    return int(np.argmax(ious)) + 1


def _nearest(ids: np.ndarray, size: int) -> np.ndarray:
    return np.asarray(Image.fromarray(ids).resize((size, size), Image.Resampling.NEAREST))


def check_split_against_uorf(root: Path, n: int) -> None:
    """Every rule of uORF's manipulation loader, on split ``root`` of ``n`` scenes."""
    layout = ManipLayout(root)
    for mask_size in (64, 128):
        batches = uorf_manip_load(root, n, mask_size=mask_size)
        for s, b in enumerate(batches):
            meta = read_json(layout.scene_json(s))
            rec = meta["manipulation"]
            assert b["paths"] == [str(layout.rgb(s, v)) for v in range(4)]
            assert b["img_data"].shape == b["img_data_moved"].shape == b["img_data_changed"].shape
            assert b["cam2world"].shape == (4, 4, 4) and b["azi_rot"].shape == (4, 3, 3)
            np.testing.assert_allclose(b["movement"][:2], rec["move"]["offset"], atol=1e-8)
            k = rec["move"]["instance_id"]
            for v in range(4):
                ids = read_instances(layout.instances(s, v))
                changed = read_instances(layout.variant_instances(s, v, "changed"))
                prov = read_instances(layout.variant_instances(s, v, "providing_bg"))
                assert np.array_equal(b["fg_idx"][v], _nearest(ids, mask_size) == k)
                assert np.array_equal(b["bg_idx"][v], _nearest(changed, mask_size) == 0)
                assert np.array_equal(b["providing_bg_idx"][v], _nearest(prov, mask_size) == 0)
            # uORF's slot choice with perfect slot masks (slot k = instance k) picks object k.
            if b["fg_idx"][0].any():
                labels = _nearest(read_instances(layout.instances(s, 0)), mask_size)
                assert uorf_move_slot(labels, b["fg_idx"][0], 8) == k


def _check_edit_rules(root: Path, preset: str, n: int) -> None:
    """Moved object in the box, collision-free, by the offset; variants re-made from JSON."""
    p = get_preset(preset)
    layout = ManipLayout(root)
    for s in range(n):
        meta = read_json(layout.scene_json(s))
        variants = variant_specs_from_json(json.loads(json.dumps(meta)))
        moved = variants["moved"]
        k = meta["manipulation"]["move"]["instance_id"]
        dx, dy = meta["manipulation"]["move"]["offset"]
        assert OFFSET_RANGE[0] <= np.hypot(dx, dy) <= OFFSET_RANGE[1]
        o = next(x for x in moved.objects if x.instance_id == k)
        before = next(x for x in meta["objects"] if x["instance_id"] == k)["position"]
        np.testing.assert_allclose(o.position, [before[0] + dx, before[1] + dy, before[2]])
        assert max(abs(o.position[0]), abs(o.position[1])) <= p.xy_range
        for q in moved.objects:
            if q.instance_id != k:
                gap = np.hypot(o.position[0] - q.position[0], o.position[1] - q.position[1])
                assert gap - o.bounding_radius_xy - q.bounding_radius_xy >= p.min_gap - 1e-9
        donor = meta["manipulation"]["background"]["donor_scene"]
        assert donor != s and 0 <= donor < n
        assert variants["changed"].objects == SceneSpec.from_json(meta).objects
        assert variants["providing_bg"].views == variants["changed"].views


# ------------------------------------------------------------------------ ray-cast tier


@pytest.fixture(scope="module", params=["clevr567", "room-chair"])
def raycast_split(request, tmp_path_factory):
    root = tmp_path_factory.mktemp(f"manip-{request.param}")
    return write_raycast_manip_split(root, request.param, n=3, resolution=32), request.param


def test_raycast_split_reads_with_uorf_rules(raycast_split):
    root, _ = raycast_split
    check_split_against_uorf(root, 3)


def test_raycast_split_verifies_and_follows_edit_rules(raycast_split):
    root, preset = raycast_split
    assert verify_split(root) == []
    _check_edit_rules(root, preset, 3)


def test_room_background_changes(tmp_path):
    root = write_raycast_manip_split(tmp_path, "room-chair", n=4, resolution=32)
    differs = [read_json(ManipLayout(root).scene_json(s))["manipulation"]["background"]["differs"]
               for s in range(4)]  # fmt: skip
    assert all(differs)


def test_edits_are_a_pure_function():
    p = get_preset("clevr567")
    a = make_manip_scene(p, 1, 5, 3)
    b = make_manip_scene(p, 1, 5, 3)
    assert a == b
    assert a[0].split == "manip" and a[0].scene_seed == 3 * 1_000_000 + 2 * 100_000 + 1


def test_verify_catches_a_wrong_movement_file(tmp_path):
    root = write_raycast_manip_split(tmp_path, "clevr567", n=2, resolution=32)
    ManipLayout(root).movement(1).write_text("0.5\n0.5\n")
    assert any("movement.txt" in p for p in verify_split(root))


def test_bad_manip_requests_are_one_line_errors(tmp_path):
    from generators.cli import main

    for argv in (["--preset", "clevr567", "--split", "manip", "--n", "1", "--out", str(tmp_path)],
                 ["--preset", "clevr567-gray", "--split", "manip", "--out", str(tmp_path)]):  # fmt: skip
        with pytest.raises(SystemExit) as e:
            raise SystemExit(main(argv))
        assert e.value.code == 2
    assert not any(tmp_path.iterdir())


# ------------------------------------------------------------------------ Blender tier


@pytest.mark.blender
@pytest.mark.skipif(not bpy_available(), reason="bpy not installed")
@pytest.mark.parametrize("preset", ["clevr567", "room-chair"])
def test_blender_manip_split_reads_with_uorf_rules(preset, tmp_path):
    from generators.pipeline import GenerateConfig, generate_dataset
    from generators.raycast import cast_view

    cfg = GenerateConfig(preset=preset, split="manip", n=2, out=tmp_path, resolution=32,
                         samples=2, workers=1, threads=1, progress=False)  # fmt: skip
    summary = generate_dataset(cfg)
    assert summary.complete and summary.scenes_this_run == 2
    assert verify_split(tmp_path) == []
    check_split_against_uorf(tmp_path, 2)
    _check_edit_rules(tmp_path, preset, 2)
    # The rendered ids of every variant equal a ray cast of the variant re-made from the JSON.
    layout = ManipLayout(tmp_path)
    for s in range(2):
        variants = variant_specs_from_json(read_json(layout.scene_json(s)))
        for name, spec in variants.items():
            for v in range(4):
                got = read_instances(layout.variant_instances(s, v, name))
                want = cast_view(spec, v, 32).ids
                assert (got != want).mean() < 0.02, (name, s, v)
    # A rerun finds every scene complete and renders nothing.
    again = generate_dataset(cfg)
    assert again.scenes_this_run == 0 and again.scenes_skipped == 2
