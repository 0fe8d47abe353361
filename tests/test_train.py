"""svorf.train, svorf.cli and svorf.viz: training, checkpoints, resume, prediction, CLI.

Runs a tiny model (smoke scale, 3 slots, 16x16) for a few dozen steps on a 2-scene
analytic split; the whole file takes well under a minute on 2 CPU cores.
"""

from __future__ import annotations

import json
import math

import pytest
import torch

from svorf import cli
from svorf.config import model_config
from svorf.data import MultiViewDataset
from svorf.synthetic import write_synthetic_split
from svorf.train import (
    CHECKPOINT_NAME,
    CheckpointError,
    TrainConfig,
    TrainingDiverged,
    dataset_fingerprint,
    load_run,
    lr_at,
    predict_scene,
    run_configs,
    train,
    train_config,
)

torch.set_num_threads(1)


def _mcfg():
    return model_config("smoke", num_slots=3, image_size=16, n_coarse=4, n_fine=4)


def _tcfg(**kw):
    base = TrainConfig(steps=20, batch_scenes=2, rays_per_scene=32, lr=3e-3, warmup=2,
                       log_every=1, ckpt_every=4, device="cpu")  # fmt: skip
    return base.replace(**kw)


def _read_log(run):
    return [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return write_synthetic_split(tmp_path_factory.mktemp("d") / "train", n_scenes=2,
                                 resolution=32, seed=0)  # fmt: skip


@pytest.fixture(scope="module")
def trained(split, tmp_path_factory):
    run = tmp_path_factory.mktemp("run") / "smoke"
    summary = train(split, run, _mcfg(), _tcfg(), progress=False)
    return run, summary


# ----------------------------------------------------------------- configs


def test_train_config_registry():
    for scale in ("smoke", "cpu", "paper"):
        cfg = train_config(scale, "clevr567")
        assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    paper = train_config("paper", "clevr567")
    assert (paper.lr, paper.betas, paper.warmup, paper.rays_per_scene) == (1e-4, (0.9, 0.999),
                                                                           1000, 64)  # fmt: skip
    assert paper.ray_sampling == "uniform"
    with pytest.raises(ValueError, match="unknown scale"):
        train_config("huge")
    with pytest.raises(ValueError, match="unknown preset"):
        train_config("smoke", "nope")
    with pytest.raises(ValueError, match="ray_sampling"):
        TrainConfig(ray_sampling="nope")
    m, _ = run_configs("smoke", "packed-clevr11")
    assert (m.num_slots, m.slot_mask_train) == (11, 4)
    cfg = TrainConfig(lr=1.0, warmup=4)
    assert [lr_at(cfg, s) for s in range(6)] == [0.25, 0.5, 0.75, 1.0, 1.0, 1.0]


# ----------------------------------------------------------------- training


def test_smoke_training_lowers_loss_and_writes_run(trained, split):
    run, summary = trained
    log = _read_log(run)
    assert [r["step"] for r in log] == list(range(1, 21))
    assert {"step", "wall_s", "lr", "loss", "parts", "steps_per_s"} <= set(log[0])
    assert {"mse", "connectivity"} <= set(log[0]["parts"])
    first = sum(r["loss"] for r in log[:3]) / 3
    last = sum(r["loss"] for r in log[-5:]) / 5
    assert last < 0.7 * first, (first, last)
    assert summary["steps"] == 20 and math.isfinite(summary["final_loss"])
    assert summary["dataset_fingerprint"] == dataset_fingerprint(split)
    assert summary["params"] > 0 and summary["peak_rss_mb"] > 0
    assert (run / CHECKPOINT_NAME).is_file() and (run / "config.json").is_file()
    assert not list(run.glob(".*.tmp"))  # atomic writes leave no temp files
    model, info = load_run(run)
    assert info.step == 20 and info.model == _mcfg() and info.train == _tcfg()
    assert info.dataset["fingerprint"] == dataset_fingerprint(split)
    assert not model.training
    with pytest.raises(CheckpointError, match="already holds a checkpoint"):
        train(split, run, _mcfg(), _tcfg(), progress=False)


def test_resume_equals_uninterrupted(split, tmp_path):
    straight, part = tmp_path / "straight", tmp_path / "part"
    cfg = _tcfg(steps=8, ray_sampling="object_heavy")
    train(split, straight, _mcfg(), cfg, progress=False)
    train(split, part, _mcfg(), cfg.replace(steps=4), progress=False)
    # Log lines written after the checkpoint (as after a crash) are dropped on resume.
    with open(part / "log.jsonl", "a") as f:
        f.write(json.dumps({"step": 5, "loss": 123.0}) + "\n")
    s = train(split, part, _mcfg(), cfg, resume=True, progress=False)
    assert s["start_step"] == 4
    a, _ = load_run(straight)
    b, _ = load_run(part)
    for (name, x), (_, y) in zip(a.state_dict().items(), b.state_dict().items()):
        assert torch.equal(x, y), name
    la, lb = _read_log(straight), _read_log(part)
    assert [r["step"] for r in lb] == list(range(1, 9))
    assert [r["loss"] for r in la] == [r["loss"] for r in lb]
    # A finished run resumes to a no-op with the same final loss.
    again = train(split, part, _mcfg(), cfg, resume=True, progress=False)
    assert again["final_loss"] == s["final_loss"]
    with pytest.raises(CheckpointError, match="different model config"):
        train(split, part, _mcfg().replace(num_slots=4), cfg, resume=True, progress=False)
    with pytest.raises(CheckpointError, match="different train config"):
        train(split, part, _mcfg(), cfg.replace(lr=1e-2), resume=True, progress=False)


def test_nan_loss_raises_and_keeps_last_checkpoint(split, tmp_path, monkeypatch):
    import svorf.train as st

    class Exploding(st.SVORF):
        calls = 0

        def loss(self, out, target_rgb):
            total, parts = super().loss(out, target_rgb)
            Exploding.calls += 1
            if Exploding.calls == 6:
                total = total * float("nan")
            return total, parts

    monkeypatch.setattr(st, "SVORF", Exploding)
    run = tmp_path / "nan"
    with pytest.raises(TrainingDiverged) as e:
        train(split, run, _mcfg(), _tcfg(steps=10), progress=False)
    msg = str(e.value)
    assert "\n" not in msg and "step 6" in msg and "step 4" in msg
    monkeypatch.undo()
    _, info = load_run(run)
    assert info.step == 4
    assert max(r["step"] for r in _read_log(run)) == 5


def test_corrupt_or_missing_checkpoint(trained, tmp_path):
    with pytest.raises(CheckpointError, match="missing") as e:
        load_run(tmp_path)
    assert "\n" not in str(e.value)
    good = (trained[0] / CHECKPOINT_NAME).read_bytes()
    for bad in (b"garbage", good[: len(good) // 2]):
        (tmp_path / CHECKPOINT_NAME).write_bytes(bad)
        with pytest.raises(CheckpointError, match="corrupt") as e:
            load_run(tmp_path)
        assert "\n" not in str(e.value)
    torch.save({"format": "other"}, tmp_path / CHECKPOINT_NAME)
    with pytest.raises(CheckpointError, match="not an sVORF checkpoint"):
        load_run(tmp_path)


# ----------------------------------------------------------------- prediction


def test_predict_scene(trained, split):
    model, _ = load_run(trained[0])
    ds = MultiViewDataset(split, image_size=16)
    p = predict_scene(model, ds, 1, input_view=2, chunk=100)
    v, h, w, k = 4, 16, 16, 3
    assert p["rgb"].shape == (v, h, w, 3) and p["depth_z"].shape == (v, h, w)
    assert p["slot_probs"].shape == (v, h, w, k) and p["labels"].dtype == torch.int64
    assert torch.equal(p["labels"], p["slot_probs"].argmax(-1))
    torch.testing.assert_close(p["depth_z"], p["depth_t"] * ds[1].z_scale)
    assert torch.isfinite(p["rgb"]).all() and (p["rgb"] >= 0).all() and (p["rgb"] <= 1).all()
    assert p["scene"] == 1 and p["input_view"] == 2
    # Chunking does not change the result.
    q = predict_scene(model, ds, 1, input_view=2, chunk=4096)
    torch.testing.assert_close(p["rgb"], q["rgb"], atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="input_view"):
        predict_scene(model, ds, 0, input_view=4)


# ----------------------------------------------------------------- CLI


def _err_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith("svorf: error:")
    return err


def test_cli_bad_inputs_exit_2(split, tmp_path, capsys):
    base = ["train", "--scale", "smoke", "--out", str(tmp_path / "r"), "--no-progress"]
    assert cli.main(base + ["--data", str(tmp_path / "nope"), "--preset", "synthetic"]) == 2
    assert "not a directory" in _err_line(capsys)
    assert cli.main(base + ["--data", str(tmp_path), "--preset", "synthetic"]) == 2
    assert "generate verify" in _err_line(capsys)
    assert cli.main(base + ["--data", str(split), "--preset", "clevr567"]) == 2
    assert "--preset synthetic" in _err_line(capsys)
    cpu = ["train", "--scale", "cpu", "--out", str(tmp_path / "r"), "--data", str(split)]
    assert cli.main(cpu + ["--preset", "synthetic"]) == 2
    assert "--image-size 32" in _err_line(capsys)
    assert cli.main(["train", "--scale", "huge", "--data", str(split), "--preset",
                     "synthetic", "--out", "x"]) == 2  # fmt: skip
    capsys.readouterr()
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / CHECKPOINT_NAME).write_bytes(b"garbage")
    assert cli.main(base + ["--data", str(split), "--preset", "synthetic", "--resume"]) == 2
    assert "corrupt" in _err_line(capsys)
    assert cli.main(["render", str(tmp_path / "r"), "--data", str(split), "--scene", "0"]) == 2
    assert "corrupt" in _err_line(capsys)


def test_cli_train_render_info(split, trained, tmp_path, capsys):
    run = tmp_path / "cli_run"
    rc = cli.main(["train", "--data", str(split), "--preset", "synthetic", "--scale", "smoke",
                   "--out", str(run), "--steps", "2", "--seed", "3", "--no-progress",
                   "--device", "cpu"])  # fmt: skip
    out = capsys.readouterr().out
    assert rc == 0 and "parameters" in out and (run / CHECKPOINT_NAME).is_file()
    _, info = load_run(run)
    assert info.train.seed == 3 and info.step == 2

    dst = tmp_path / "figs"
    rc = cli.main(["render", str(trained[0]), "--data", str(split), "--scene", "1",
                   "--out", str(dst), "--device", "cpu"])  # fmt: skip
    assert rc == 0, capsys.readouterr().err
    names = {p.name for p in dst.glob("*.png")}
    assert {"input.png", "grid.png", "v00_render_recon.png", "v01_render_novel.png",
            "v02_mask_pred.png", "v02_mask_gt.png", "v03_depth_pred.png"} <= names  # fmt: skip
    assert len(names) == 2 + 4 * 6
    from PIL import Image

    with Image.open(dst / "grid.png") as im:
        assert im.mode == "RGB" and im.size[0] == 6 * im.size[1] // 4
    capsys.readouterr()
    assert cli.main(["render", str(trained[0]), "--data", str(split), "--scene", "9"]) == 2
    assert "sc0009" in _err_line(capsys)

    assert cli.main(["info", "--scale", "smoke"]) == 0
    assert "parameters" in capsys.readouterr().out


def test_eval_hook_writes_eval_log(split, tmp_path):
    run = tmp_path / "ev"
    seen = []

    def fn(model, ds):
        seen.append((model.training, len(ds)))
        return {"answer": 42.0}

    cfg = _tcfg(steps=2, eval_every=1, eval_scenes=1)
    train(split, run, _mcfg(), cfg, False, fn, split, progress=False)  # positional order
    rows = [json.loads(x) for x in (run / "eval.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 2] and rows[0]["answer"] == 42.0
    assert seen == [(False, 1), (False, 1)]
    train(split, tmp_path / "ev2", _mcfg(), cfg, eval_data=split, progress=False)
    row = json.loads((tmp_path / "ev2" / "eval.jsonl").read_text().splitlines()[-1])
    assert {"psnr_input", "psnr_novel", "depth_abs_err"} <= set(row)
