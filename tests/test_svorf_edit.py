"""``svorf edit`` and ``svorf.edit_scene`` on a ray-cast manipulation split (no bpy)."""

from __future__ import annotations

import json

import pytest
import torch

from generators.testing import write_raycast_manip_split, write_raycast_split
from scenefmt import read_json
from svorf.edit_scene import edit_scene, pick_slot, read_manip_truth


def test_pick_slot_is_uorfs_iou_argmax_without_the_background():
    labels = torch.tensor([[0, 0, 1, 1], [0, 0, 1, 1], [2, 2, 2, 2], [2, 2, 2, 2]])
    target = torch.zeros(4, 4, dtype=torch.bool)
    target[:2, 2:] = True  # exactly slot 1
    assert pick_slot(labels, target, 3) == (1, [0.0, 1.0])
    # slot 2 is the background (last): never picked even where it covers the target
    target = labels == 2
    slot, ious = pick_slot(labels, target, 3)
    assert slot == 0 and len(ious) == 2
    with pytest.raises(ValueError, match="differ"):
        pick_slot(labels, target[:2], 3)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from svorf.cli import main

    base = tmp_path_factory.mktemp("edit")
    train = write_raycast_split(base / "train", "clevr567", "train", n=2, resolution=32)
    manip = write_raycast_manip_split(base / "manip", "clevr567", n=2, resolution=32)
    run = base / "run"
    rc = main(["train", "--data", str(train), "--preset", "clevr567", "--scale", "smoke",
               "--out", str(run), "--steps", "2", "--no-progress", "--device", "cpu"])  # fmt: skip
    assert rc == 0
    return run, manip


def test_identity_edits_reproduce_the_unedited_render(trained):
    from svorf.data import MultiViewDataset
    from svorf.train import load_run

    run, manip = trained
    model, _ = load_run(run)
    ds = MultiViewDataset(manip, scenes=[0])
    truth = read_manip_truth(manip, 0)
    res = edit_scene(model, ds, 0, target_mask=truth.mask_for_moving[0], offset=(0.0, 0.0),
                     donor_image=ds[0].images[0])  # fmt: skip
    assert torch.allclose(res.moved, res.recon, atol=1e-5)
    assert torch.allclose(res.changed, res.recon, atol=1e-5)
    assert res.recon.shape == truth.moved.shape and res.slot is not None


def test_svorf_edit_writes_renders_beside_ground_truth(trained, tmp_path, capsys):
    from svorf.cli import main

    run, manip = trained
    rec = read_json(manip / "sc0001.json")["manipulation"]
    k, (dx, dy) = rec["move"]["instance_id"], rec["move"]["offset"]
    donor = rec["background"]["donor_scene"]
    out = tmp_path / "e"
    argv = ["edit", str(run), "--data", str(manip), "--scene", "1", "--move-object", str(k),
            "--offset", repr(dx), repr(dy), "--swap-background", str(donor), "--out", str(out),
            "--device", "cpu"]  # fmt: skip
    assert main(argv) == 0
    names = {p.name for p in out.iterdir()}
    for v in range(4):
        for f in ("recon", "moved", "moved_gt", "moved_labels", "changed", "changed_gt"):
            assert f"v{v:02d}_{f}.png" in names
    e = json.loads((out / "edit.json").read_text())
    assert e["move"]["ground_truth"] and e["background"]["ground_truth"]
    assert len(e["move"]["psnr"]) == 4 and len(e["move"]["ious"]) >= 1
    assert "slot" in capsys.readouterr().out
    # Rerun without --force: one-line error, status 2.
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("svorf: error:") and "--force" in err and "\n" not in err
    assert main([*argv, "--force"]) == 0


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--move-object", "1"], "go together"),
        ([], "nothing to edit"),
        (["--swap-background", "0"], "another scene"),
        (["--move-object", "99", "--offset", "1", "0"], "not visible"),
    ],
)
def test_svorf_edit_bad_input_is_one_line(trained, tmp_path, capsys, extra, words):
    from svorf.cli import main

    run, manip = trained
    argv = ["edit", str(run), "--data", str(manip), "--scene", "0", "--out", str(tmp_path / "x"),
            "--device", "cpu", *extra]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("svorf: error:") and words in err and "\n" not in err
