"""``svorf render``: preset checks, output folders named after the data, --force, the
labelled grid and the depth colour convention shared with ``generate preview``."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from svorf.cli import main
from svorf.config import model_config
from svorf.synthetic import write_synthetic_split
from svorf.train import TrainConfig, train


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A one-step run at 16x16 on synthetic scenes whose manifest says clevr567."""
    root = tmp_path_factory.mktemp("render")
    data = write_synthetic_split(root / "train", n_scenes=2, resolution=32, seed=1,
                                 preset="clevr567")  # fmt: skip
    cfg = TrainConfig(steps=1, batch_scenes=1, rays_per_scene=16, warmup=0, log_every=1,
                      ckpt_every=1, device="cpu")  # fmt: skip
    train(data, root / "run", model_config("smoke", num_slots=4, image_size=16), cfg,
          progress=False)  # fmt: skip
    return root / "run"


def _split(root, preset, split="test"):
    return write_synthetic_split(root / f"{preset}-{split}", n_scenes=1, resolution=16, seed=2,
                                 preset=preset, split=split)  # fmt: skip


def _render(run, data, *extra):
    return main(["render", str(run), "--data", str(data), "--scene", "0", "--device", "cpu",
                 *extra])  # fmt: skip


def test_render_writes_a_folder_per_dataset_and_refuses_to_overwrite(run, tmp_path, capsys):
    test = _split(tmp_path, "clevr567")
    assert _render(run, test) == 0
    out = run / "render" / "clevr567-test" / "sc0000"
    assert (out / "grid.png").is_file() and str(out) in capsys.readouterr().out

    assert _render(run, test) == 2  # the same data again: refused
    err = capsys.readouterr().err.strip()
    assert err.startswith("svorf: error:") and len(err.splitlines()) == 1
    assert "already holds files" in err and "--force" in err

    (out / "v09_gt.png").write_bytes(b"stale")  # a view an earlier render had
    (out / "notes.txt").write_text("mine")
    before = (out / "grid.png").stat().st_mtime_ns
    assert _render(run, test, "--force") == 0
    assert (out / "grid.png").stat().st_mtime_ns >= before
    assert not (out / "v09_gt.png").exists() and (out / "notes.txt").read_text() == "mine"

    # Another dataset (the generalization test on packed scenes) gets its own folder.
    assert _render(run, _split(tmp_path, "packed-clevr11")) == 0
    assert "generalization test" in capsys.readouterr().out
    assert (run / "render" / "packed-clevr11-test" / "sc0000" / "grid.png").is_file()
    assert (out / "notes.txt").exists()


def test_render_refuses_a_preset_mismatch(run, tmp_path, capsys):
    room = _split(tmp_path, "room-chair")
    dest = tmp_path / "out"
    assert _render(run, room, "--out", str(dest)) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("svorf: error:") and len(err.splitlines()) == 1
    assert "'clevr567'" in err and "'room-chair'" in err and "--allow-preset-mismatch" in err
    assert not dest.exists()  # refused before anything was written
    assert _render(run, room, "--out", str(dest), "--allow-preset-mismatch") == 0
    assert "preset mismatch allowed" in capsys.readouterr().out
    assert (dest / "grid.png").is_file()


def test_grid_has_labels_and_a_depth_bar(run, tmp_path):
    dest = tmp_path / "g"
    assert _render(run, _split(tmp_path, "clevr567"), "--out", str(dest)) == 0
    grid = np.asarray(Image.open(dest / "grid.png").convert("RGB"))
    tile = np.asarray(Image.open(dest / "v00_gt.png")).shape[0]
    scale = -(-128 // tile)
    # Header, view labels and the colour bar add white margins around the 4 x 6 tiles.
    assert grid.shape[0] > 4 * tile * scale and grid.shape[1] > 6 * tile * scale
    head = grid[:8]
    assert (head.min(axis=2) < 100).any(), "no column headings drawn"


def test_depth_colours_near_bright_far_dark_in_render_and_preview():
    from generators.preview import colour_depth
    from svorf.viz import colorize_depth

    def luma(rgb):
        return rgb.astype(float) @ [0.299, 0.587, 0.114]

    d = np.array([[6.0, 20.0, np.inf]], np.float32)
    a, b = colorize_depth(d, 6.0, 20.0), colour_depth(d, 6.0, 20.0)
    for rgb in (a, b):
        near, far, miss = luma(rgb[0])
        assert near > 200 and far < 80 and miss == 0
    assert np.abs(a.astype(int) - b.astype(int)).max() <= 1  # one colour scale


def test_render_with_slot_refinement(run, tmp_path, capsys):
    test = _split(tmp_path, "clevr567")
    out = tmp_path / "refined"
    assert _render(run, test, "--refine-steps", "2", "--out", str(out)) == 0
    assert (out / "grid.png").is_file()
    assert _render(run, test, "--refine-steps", "-1", "--out", str(tmp_path / "x")) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--refine-steps must be >= 0" in err
    for args, needle in (
        (("--refine-steps", "2", "--refine-lr", "0"), "--refine-lr must be a positive number"),
        (("--refine-lr", "0.01"), "pass that too"),
    ):
        assert _render(run, test, *args, "--out", str(tmp_path / "y")) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and needle in err
