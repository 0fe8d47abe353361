"""svorf.train and svorf.cli: smoke training, exact resume, NaN guard, checkpoints, CLI."""

from __future__ import annotations

import hashlib
import json
import math
import pickle
import shutil

import pytest
import torch

from svorf.cli import main
from svorf.config import model_config
from svorf.data import MultiViewDataset
from svorf.model import SVORF
from svorf.optim import TailAverage
from svorf.synthetic import write_synthetic_split
from svorf.train import (
    CheckpointError,
    TrainConfig,
    TrainingDiverged,
    default_eval,
    load_run,
    predict_scene,
    run_configs,
    train,
    train_config,
)

# A tiny model at 16x16 (the 32x32 split is area-downsampled): fast on 2 shared cores.
MCFG = model_config("smoke", num_slots=4, image_size=16)


def tcfg(**kw) -> TrainConfig:
    base = {
        "steps": 6,
        "batch_scenes": 2,
        "rays_per_scene": 32,
        "lr": 1e-3,
        "warmup": 2,
        "seed": 0,
        "log_every": 1,
        "ckpt_every": 3,
        "device": "cpu",
    }
    return TrainConfig(**{**base, **kw})


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    # The CI/dev boxes have 2 cores shared with other jobs: a second OpenMP thread that
    # waits on a busy core makes tiny steps ~15x slower.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return write_synthetic_split(
        tmp_path_factory.mktemp("synth") / "train", n_scenes=2, resolution=32, seed=1
    )


def _log(run):
    return [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines()]


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_smoke_training_lowers_loss_and_writes_a_run(split, tmp_path):
    calls = []

    def eval_fn(model, ds):
        assert not model.training
        calls.append(len(ds))
        return {"n": float(len(ds))}

    run = tmp_path / "run"
    cfg = tcfg(steps=30, ckpt_every=15, eval_every=10, eval_scenes=1)
    summary = train(split, run, MCFG, cfg, eval_data=split, eval_fn=eval_fn, progress=False)
    assert summary.steps == 30 and summary.params == SVORF(MCFG).count_parameters()
    assert summary.peak_rss_mb > 0 and summary.s_per_step > 0
    assert summary.bf16_autocast_active is False  # the smoke config keeps float32
    on_disk = json.loads((run / "summary.json").read_text())
    assert on_disk == json.loads(json.dumps(summary.to_dict()))
    assert "world_size" not in on_disk  # a single process
    log = _log(run)
    assert [r["step"] for r in log] == list(range(1, 31))
    assert {"loss", "lr", "wall_s", "parts", "steps_per_s"} <= set(log[0])
    assert log[0]["lr"] == pytest.approx(5e-4) and log[-1]["lr"] == pytest.approx(1e-3)
    first = sum(r["loss"] for r in log[:5]) / 5
    last = sum(r["loss"] for r in log[-5:]) / 5
    assert last < 0.8 * first, (first, last)
    evals = [json.loads(x) for x in (run / "eval.jsonl").read_text().splitlines()]
    assert [e["step"] for e in evals] == [10, 20, 30] and calls == [1, 1, 1]
    assert (run / "checkpoint.pt").is_file() and (run / "summary.json").is_file()
    assert json.loads((run / "config.json").read_text())["model"] == MCFG.to_dict()

    model, info = load_run(run)
    assert info.step == 30 and info.model == MCFG and info.train == cfg
    ds = MultiViewDataset(split, image_size=16)
    assert info.dataset["fingerprint"] == ds.fingerprint
    pred = predict_scene(model, ds, 1, input_view=2, chunk=100)
    assert pred.rgb.shape == (4, 16, 16, 3) and pred.slot_probs.shape == (4, 16, 16, 4)
    assert pred.labels.shape == (4, 16, 16) and pred.labels.dtype == torch.int64
    torch.testing.assert_close(pred.depth_z, pred.depth_t * ds[1].z_scale)
    assert pred.input_view == 2 and pred.scene == 1
    metrics = default_eval(model, ds, max_scenes=1)
    assert set(metrics) == {"psnr_input", "psnr_novel", "depth_abs_err", "n_scenes"}
    assert not any(math.isnan(v) for v in metrics.values())


def test_gradients_do_not_outlive_their_step(split, tmp_path, monkeypatch):
    # The forward, where activations peak, and the evaluation between steps run without
    # the previous step's gradients (one parameter-sized copy less at the memory peak).
    held = []
    forward = SVORF.forward

    def spy(self, *a, **k):
        if self.training:
            held.append(sum(p.grad is not None for p in self.parameters()))
        return forward(self, *a, **k)

    def eval_fn(model, ds):
        held.append(sum(p.grad is not None for p in model.parameters()))
        return {}

    monkeypatch.setattr(SVORF, "forward", spy)
    cfg = tcfg(ema_decay=0.9, eval_every=2, eval_scenes=1)
    train(split, tmp_path / "run", MCFG, cfg, eval_data=split, eval_fn=eval_fn, progress=False)
    assert len(held) == 6 + 3 and held == [0] * 9


@pytest.mark.parametrize("ray_sampling", ["uniform", "error_driven"])
def test_resume_matches_an_uninterrupted_run(split, tmp_path, ray_sampling):
    # The uninterrupted run also evaluates: evaluation must not disturb the RNG streams.
    # "error_driven" also carries its error map across the interruption.
    rs = {"ray_sampling": ray_sampling}
    full = tmp_path / "full"
    train(split, full, MCFG, tcfg(eval_every=2, eval_scenes=1, **rs), eval_data=split,
          progress=False)  # fmt: skip
    part = tmp_path / "part"
    train(split, part, MCFG, tcfg(steps=3, **rs), progress=False)
    # A crash after the checkpoint may leave log lines past it: resume drops them.
    with open(part / "log.jsonl", "a") as f:
        f.write(json.dumps({"step": 4, "loss": 1.0}) + "\n")
    train(split, part, MCFG, tcfg(steps=6, **rs), resume=True, progress=False)
    a = torch.load(full / "checkpoint.pt", weights_only=True)
    b = torch.load(part / "checkpoint.pt", weights_only=True)
    assert a["step"] == b["step"] == 6
    if ray_sampling == "error_driven":
        err = a["error_map"]["err"]
        assert torch.equal(err, b["error_map"]["err"])
        assert 0 < int((err < 1.0).sum()) < err.numel()  # fed by training, not everywhere
    else:
        assert "error_map" not in a
    for k, v in a["model"].items():
        assert torch.equal(v, b["model"][k]), k
    la, lb = _log(full), _log(part)
    assert [r["step"] for r in lb] == list(range(1, 7))
    assert [r["loss"] for r in la] == [r["loss"] for r in lb]


def test_weight_average_is_checkpointed_resumed_and_evaluated(split, tmp_path):
    ema = {"ema_decay": 0.9}
    full, part, plain = tmp_path / "full", tmp_path / "part", tmp_path / "plain"
    train(split, full, MCFG, tcfg(**ema), progress=False)
    train(split, part, MCFG, tcfg(steps=3, **ema), progress=False)
    train(split, part, MCFG, tcfg(**ema), resume=True, progress=False)
    a = torch.load(full / "checkpoint.pt", weights_only=True)
    b = torch.load(part / "checkpoint.pt", weights_only=True)
    for k, v in a["model_ema"].items():
        assert torch.equal(v, b["model_ema"][k]), k
    moved = [k for k, v in a["model"].items() if not torch.equal(v, a["model_ema"][k])]
    assert moved  # the average is not the weights
    avg, info = load_run(full)
    raw, info_raw = load_run(full, weights="raw")
    assert (info.weights, info_raw.weights) == ("ema", "raw")
    for k in moved:
        assert torch.equal(avg.state_dict()[k], a["model_ema"][k])
        assert torch.equal(raw.state_dict()[k], a["model"][k])
    # Without ema_decay: no average, the same config key as before the field existed.
    train(split, plain, MCFG, tcfg(), progress=False)
    assert "model_ema" not in torch.load(plain / "checkpoint.pt", weights_only=True)
    assert load_run(plain)[1].weights == "raw"
    with pytest.raises(CheckpointError, match="no averaged weights"):
        load_run(plain, weights="ema")
    assert "ema_decay" not in tcfg().to_dict() and tcfg(**ema).to_dict()["ema_decay"] == 0.9
    with pytest.raises(ValueError, match="ema_decay must be in"):
        tcfg(ema_decay=1.0)


def test_average_probes_leave_training_alone_and_are_scored_by_name(split, tmp_path):
    """``average_probes``: the run's weights and its ``ema_decay`` average are those of a
    run without them; each probe is what its own average would be, survives a resume, and
    ``load_run`` scores it by name."""
    ema = {"ema_decay": 0.9}
    probes = {"average_probes": ("ema0.2", "tail0.7")}
    base, full, part = tmp_path / "base", tmp_path / "full", tmp_path / "part"
    train(split, base, MCFG, tcfg(**ema), progress=False)
    train(split, full, MCFG, tcfg(**ema, **probes), progress=False)
    train(split, part, MCFG, tcfg(steps=3, **ema, **probes), progress=False)
    train(split, part, MCFG, tcfg(**ema, **probes), resume=True, progress=False)
    a0 = torch.load(base / "checkpoint.pt", weights_only=True)
    a = torch.load(full / "checkpoint.pt", weights_only=True)
    b = torch.load(part / "checkpoint.pt", weights_only=True)
    for k, v in a0["model"].items():
        assert torch.equal(v, a["model"][k]), k
        assert torch.equal(a0["model_ema"][k], a["model_ema"][k]), k
    pa, pb = a["model_average_probes"], b["model_average_probes"]
    assert sorted(pa) == ["ema0.2", "tail0.7"] and pa["tail0.7"]["count"] == pb["tail0.7"]["count"]
    for name in pa:
        for k, v in pa[name]["model"].items():
            assert torch.equal(v, pb[name]["model"][k]), (name, k)
    # Of 6 steps only the last starts at progress >= 0.7 (5/6); the first leg of the resumed
    # run (3 steps, progress < 0.7 throughout) averages none.
    assert pa["tail0.7"]["count"] == 1
    moved = [k for k, v in a["model"].items() if not torch.equal(v, pa["ema0.2"]["model"][k])]
    assert moved and any(
        not torch.equal(pa["ema0.2"]["model"][k], a["model_ema"][k]) for k in moved
    )
    model, info = load_run(full, weights="tail0.7")
    assert info.weights == "tail0.7"
    for k, v in pa["tail0.7"]["model"].items():
        assert torch.equal(model.state_dict()[k], v), k
    with pytest.raises(CheckpointError, match="kept no average probe 'ema0.99'.*ema0.2, tail0.7"):
        load_run(full, weights="ema0.99")
    with pytest.raises(ValueError, match="weights must be one of"):
        load_run(full, weights="mean")
    assert "average_probes" not in tcfg().to_dict()
    with pytest.raises(ValueError, match="average_probes.*'ema1.5'"):
        tcfg(average_probes=("ema1.5",))


def test_tail_average_is_the_mean_of_the_weights_from_its_start():
    p = torch.nn.Parameter(torch.zeros(3))
    avg = TailAverage([("w", p)], start=0.5)
    for step, (progress, value) in enumerate([(0.0, 9.0), (0.5, 1.0), (0.75, 2.0), (0.9, 6.0)], 1):
        p.data.fill_(value)
        avg.update(step, progress)
    assert avg.count == 3 and torch.allclose(avg.averages[0], torch.full((3,), 3.0))


def test_resume_refuses_a_different_run(split, tmp_path):
    run = tmp_path / "run"
    train(split, run, MCFG, tcfg(steps=1), progress=False)
    with pytest.raises(CheckpointError, match="already holds a checkpoint"):
        train(split, run, MCFG, tcfg(steps=2), progress=False)
    with pytest.raises(CheckpointError, match="different model config.*num_slots"):
        train(split, run, MCFG.replace(num_slots=5), tcfg(steps=2), resume=True, progress=False)
    with pytest.raises(CheckpointError, match="different train config.*lr"):
        train(split, run, MCFG, tcfg(steps=2, lr=0.5), resume=True, progress=False)


def test_resume_refuses_another_budget_when_schedules_follow_the_progress(split, tmp_path):
    # The budget is the progress's denominator: a finished 60-minute run resumed under 120
    # minutes would replay its schedules from their middle.
    sched = MCFG.replace(photo_l1=(0.5, 0.7))
    run = tmp_path / "run"
    train(split, run, sched, tcfg(steps=1), progress=False, max_wall_s=3600.0)
    assert torch.load(run / "checkpoint.pt", weights_only=True)["max_wall_s"] == 3600.0
    with pytest.raises(CheckpointError, match=r"3600 s budget.*7200 s budget.*\(photo_l1\)"):
        train(split, run, sched, tcfg(steps=2), resume=True, progress=False, max_wall_s=7200.0)
    with pytest.raises(CheckpointError, match=r"3600 s budget.*no time budget"):
        train(split, run, sched, tcfg(steps=2), resume=True, progress=False)
    train(split, run, sched, tcfg(steps=2), resume=True, progress=False, max_wall_s=3600.0)
    assert [r["step"] for r in _log(run)][-1] == 2
    # Without such schedules a run may be resumed under another budget (or none).
    plain = tmp_path / "plain"
    train(split, plain, MCFG, tcfg(steps=1), progress=False, max_wall_s=3600.0)
    train(split, plain, MCFG, tcfg(steps=2), resume=True, progress=False)
    assert [r["step"] for r in _log(plain)][-1] == 2


class _Reads:
    """A config stand-in that records which fields are read."""

    def __init__(self, cfg) -> None:
        self._cfg, self.names = cfg, set()

    def __getattr__(self, name):
        self.names.add(name)
        return getattr(self._cfg, name)


def test_the_resume_guard_knows_every_schedule_that_follows_the_progress():
    # The guard's lists are the fields the progress-driven code reads, no more, no fewer.
    from svorf.config import PROGRESS_FIELDS as MODEL_FIELDS
    from svorf.train_config import PROGRESS_FIELDS as TRAIN_FIELDS

    model = SVORF(MCFG)
    model.cfg = reads = _Reads(model.cfg)
    for p in (0.0, 0.5, 1.0):
        model.set_progress(p)
    assert reads.names - {"slot_locality"} == set(MODEL_FIELDS)
    reads = _Reads(tcfg())
    for p in (0.0, 0.5, 1.0):
        TrainConfig.salient_share(reads, p)
        TrainConfig.input_view_targeted(reads, p)
        TrainConfig.ray_stride(reads, p)
    assert reads.names == set(TRAIN_FIELDS)


def test_resume_a_checkpoint_saved_before_a_config_field_existed(split, tmp_path):
    """A model-config field added after the checkpoint was written takes its default (the
    behaviour the run was trained with): resuming is not a config mismatch."""
    run = tmp_path / "old"
    train(split, run, MCFG, tcfg(steps=2), progress=False)
    ckpt = torch.load(run / "checkpoint.pt", weights_only=True)
    for key in ("slot_centre", "centre_temperature", "dec_value_pos"):
        ckpt["model_config"].pop(key)
    # ... and the data's fingerprint as written then (raw bytes, before numbers were
    # rounded): the same data, so it resumes; another fingerprint is other data.
    from scenefmt import dataset_fingerprint, legacy_fingerprint

    assert legacy_fingerprint(split) != dataset_fingerprint(split)
    torch.save({**ckpt, "dataset": {**ckpt["dataset"], "fingerprint": "0" * 64}},
               run / "checkpoint.pt")  # fmt: skip
    with pytest.raises(CheckpointError, match="differs from the run's training data"):
        train(split, run, MCFG, tcfg(steps=3), resume=True, progress=False)
    ckpt["dataset"]["fingerprint"] = legacy_fingerprint(split)
    torch.save(ckpt, run / "checkpoint.pt")
    train(split, run, MCFG, tcfg(steps=3), resume=True, progress=False)
    assert [r["step"] for r in _log(run)][-1] == 3
    with pytest.raises(CheckpointError, match="slot_centre"):  # a real difference still is
        train(split, run, MCFG.replace(slot_locality=1.0, slot_centre="attention"),
              tcfg(steps=4), resume=True, progress=False)  # fmt: skip


def test_nan_loss_raises_and_keeps_the_last_checkpoint(split, tmp_path, monkeypatch):
    run = tmp_path / "run"
    train(split, run, MCFG, tcfg(steps=2, ckpt_every=2), progress=False)
    before = _sha(run / "checkpoint.pt")
    real_loss = SVORF.loss

    def nan_loss(self, out, target):
        total, parts = real_loss(self, out, target)
        return total * float("nan"), parts

    monkeypatch.setattr(SVORF, "loss", nan_loss)
    with pytest.raises(TrainingDiverged, match=r"at step 3 .*step 2\)") as e:
        train(split, run, MCFG, tcfg(steps=4, ckpt_every=1), resume=True, progress=False)
    assert e.value.step == 3
    assert pickle.loads(pickle.dumps(e.value)).step == 3
    assert _sha(run / "checkpoint.pt") == before
    assert load_run(run)[1].step == 2


def test_corrupt_or_missing_checkpoint_is_a_one_line_error(split, tmp_path):
    with pytest.raises(CheckpointError, match="missing") as e:
        load_run(tmp_path / "nothing")
    assert "\n" not in str(e.value)
    run = tmp_path / "run"
    train(split, run, MCFG, tcfg(steps=1), progress=False)
    data = (run / "checkpoint.pt").read_bytes()
    (run / "checkpoint.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="corrupt") as e:
        load_run(run)
    assert "\n" not in str(e.value)
    with pytest.raises(CheckpointError, match="corrupt"):
        train(split, run, MCFG, tcfg(steps=2), resume=True, progress=False)
    torch.save({"format": "something else"}, run / "checkpoint.pt")
    with pytest.raises(CheckpointError, match="not an sVORF checkpoint"):
        load_run(run)


def test_target_size_draws_rays_from_the_finer_grid(split, tmp_path):
    """TrainConfig.target_size: the rays come from the 32x32 images while the encoder sees
    16x16; the run renders and evaluates at image_size, and the config key of a run
    without it is unchanged (the field is omitted when None)."""
    assert "target_size" not in tcfg().to_dict()
    cfg = tcfg(steps=3, target_size=32)
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    run = tmp_path / "fine"
    train(split, run, MCFG, cfg, progress=False)
    model, info = load_run(run)
    assert info.train.target_size == 32
    assert info.dataset["image_hw"] == [16, 16] and info.dataset["target_hw"] == [32, 32]
    ds = MultiViewDataset(split, image_size=info.dataset["image_hw"])
    assert predict_scene(model, ds, 0, chunk=256).rgb.shape == (4, 16, 16, 3)
    assert [r["step"] for r in _log(run)] == [1, 2, 3]
    with pytest.raises(ValueError, match="target_size"):
        train(split, tmp_path / "low", MCFG, tcfg(steps=1, target_size=8), progress=False)
    with pytest.raises(ValueError, match="target_size"):
        TrainConfig(target_size=4)


def test_salient_fade_ends_the_run_on_uniform_rays(split, tmp_path, monkeypatch):
    """TrainConfig.salient_fade: the salient share passed to the sampler is the strategy's
    0.5 until p0, 0 from p1 on; the field round-trips, is left out of the key while off,
    and refuses a bad schedule or a strategy without a salient share."""
    from svorf.data import RaySampler

    assert "salient_fade" not in tcfg(ray_sampling="object_heavy").to_dict()
    cfg = tcfg(steps=4, ray_sampling="object_heavy", salient_fade=[0.25, 0.75])
    assert cfg.salient_fade == (0.25, 0.75)
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    seen = []
    real = RaySampler.sample

    def spy(
        self, scenes, generator, salient_fraction=None, include_input=False, jitter=0.0, stride=1
    ):
        seen.append(salient_fraction)
        return real(self, scenes, generator, salient_fraction, include_input, jitter, stride)

    monkeypatch.setattr(RaySampler, "sample", spy)
    train(split, tmp_path / "fade", MCFG, cfg, progress=False)
    assert seen == pytest.approx([0.5, 0.5, 0.25, 0.0])  # progress 0, 1/4, 1/2, 3/4
    with pytest.raises(ValueError, match="salient_fade must be"):
        TrainConfig(ray_sampling="object_heavy", salient_fade=(0.7, 0.5))
    with pytest.raises(ValueError, match="salient_fade fades"):
        TrainConfig(ray_sampling="uniform", salient_fade=(0.5, 0.7))


def test_input_view_from_adds_the_input_view_to_the_targets_late(split, tmp_path, monkeypatch):
    """TrainConfig.input_view_from: the sampler is told to include the input view from that
    progress on; the field round-trips, is left out of the key while off, and refuses a
    value outside [0, 1]."""
    from svorf.data import RaySampler

    assert "input_view_from" not in tcfg().to_dict()
    cfg = tcfg(steps=4, input_view_from=0.5)
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    seen = []
    real = RaySampler.sample

    def spy(
        self, scenes, generator, salient_fraction=None, include_input=False, jitter=0.0, stride=1
    ):
        seen.append(include_input)
        return real(self, scenes, generator, salient_fraction, include_input, jitter, stride)

    monkeypatch.setattr(RaySampler, "sample", spy)
    train(split, tmp_path / "iv", MCFG, cfg, progress=False)
    assert seen == [False, False, True, True]  # progress 0, 1/4, 1/2, 3/4
    with pytest.raises(ValueError, match="input_view_from must be"):
        TrainConfig(input_view_from=1.5)


def test_pixel_jitter_reaches_the_sampler_and_is_keyed_only_when_on(split, tmp_path, monkeypatch):
    """TrainConfig.pixel_jitter: passed to every batch; left out of the key while 0 (earlier
    runs keep their keys), round-trips, and refuses a side outside [0, 1]."""
    from svorf.data import RaySampler

    assert "pixel_jitter" not in tcfg().to_dict()
    cfg = tcfg(steps=2, pixel_jitter=1)
    assert cfg.pixel_jitter == 1.0 and cfg.to_dict()["pixel_jitter"] == 1.0
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    seen = []
    real = RaySampler.sample

    def spy(
        self, scenes, generator, salient_fraction=None, include_input=False, jitter=0.0, stride=1
    ):
        seen.append(jitter)
        return real(self, scenes, generator, salient_fraction, include_input, jitter, stride)

    monkeypatch.setattr(RaySampler, "sample", spy)
    train(split, tmp_path / "pj", MCFG, cfg, progress=False)
    assert seen == [1.0, 1.0]
    with pytest.raises(ValueError, match="pixel_jitter must be in"):
        TrainConfig(pixel_jitter=1.5)


def test_gray_scenes_shows_picked_scenes_in_luma_and_is_keyed_only_when_on(split, tmp_path):
    """TrainConfig.gray_scenes: a picked scene's input view and target rays become Rec.601
    luma in all three channels, the others stay as drawn; left out of the key while 0,
    round-trips, refuses a chance outside [0, 1], and trains."""
    from scenefmt import LUMA_REC601
    from svorf.data import RaySampler, gray_some_scenes

    assert "gray_scenes" not in tcfg().to_dict()
    cfg = tcfg(steps=2, gray_scenes=0.5)
    assert cfg.to_dict()["gray_scenes"] == 0.5
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    with pytest.raises(ValueError, match="gray_scenes must be a probability"):
        TrainConfig(gray_scenes=1.5)
    ds = MultiViewDataset(split, image_size=MCFG.image_size)
    smp = RaySampler(ds, rays_per_scene=32, nvs=True)
    batch = smp.sample(torch.arange(2), torch.Generator().manual_seed(0))
    w = torch.tensor(LUMA_REC601)
    all_gray = gray_some_scenes(batch, 1.0, torch.Generator().manual_seed(0))
    luma = torch.einsum("bchw,c->bhw", batch.images, w)
    for c in range(3):
        assert torch.allclose(all_gray.images[:, c], luma)
        assert torch.allclose(all_gray.target_rgb[..., c], batch.target_rgb @ w)
    assert torch.equal(all_gray.rays_d, batch.rays_d)
    assert gray_some_scenes(batch, 0.0, torch.Generator()) is batch
    assert not torch.equal(all_gray.images, batch.images)  # the colour split is not gray
    train(split, tmp_path / "gray", MCFG, cfg, progress=False)


def test_coarse_to_fine_strides_the_early_batches_and_is_keyed_only_when_on(
    split, tmp_path, monkeypatch
):
    """TrainConfig.coarse_to_fine: blocks of its stride before ``until``, pixels after;
    left out of the key while None (earlier runs keep their keys), round-trips through
    JSON, and refuses what it cannot honour."""
    from svorf.data import RaySampler

    assert "coarse_to_fine" not in tcfg().to_dict()
    cfg = tcfg(steps=4, coarse_to_fine=[2, 0.5])
    assert cfg.coarse_to_fine == (2, 0.5) and cfg.to_dict()["coarse_to_fine"] == [2, 0.5]
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    assert [cfg.ray_stride(p) for p in (0.0, 0.49, 0.5, 1.0)] == [2, 2, 1, 1]
    assert tcfg().ray_stride(0.0) == 1
    seen = []
    real = RaySampler.sample

    def spy(
        self, scenes, generator, salient_fraction=None, include_input=False, jitter=0.0, stride=1
    ):
        seen.append(stride)
        return real(self, scenes, generator, salient_fraction, include_input, jitter, stride)

    monkeypatch.setattr(RaySampler, "sample", spy)
    train(split, tmp_path / "c2f", MCFG, cfg, progress=False)
    assert seen == [2, 2, 1, 1]  # progress 0, 1/4, 1/2, 3/4
    for bad in ((1, 0.5), (2, 1.5), (2,), (2, 0.5, 1)):
        with pytest.raises(ValueError, match="coarse_to_fine must be"):
            TrainConfig(coarse_to_fine=bad)
    with pytest.raises(ValueError, match="does not combine"):
        TrainConfig(coarse_to_fine=(2, 0.5), pixel_jitter=0.5)


def test_cli_train_refuses_data_coarser_than_target_size(split, tmp_path, capsys, monkeypatch):
    """svorf train whose configs ask for 64x64 targets on a 32x32 split: one line that
    names target_size and the resolution to render, before any model is built."""
    import svorf.train as train_mod

    plain = train_mod.run_configs

    def finer(*a, **k):
        m, t = plain(*a, **k)
        return m, t.replace(target_size=64)

    monkeypatch.setattr(train_mod, "run_configs", finer)
    argv = ["train", "--scale", "smoke", "--preset", "synthetic", "--data", str(split),
            "--out", str(tmp_path / "run"), "--no-progress"]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("svorf: error:") and len(err.splitlines()) == 1, err
    assert "target_size" in err and "--resolution 64" in err
    assert not (tmp_path / "run").exists()


def test_configs_registry_and_json_round_trip():
    for scale in ("smoke", "cpu", "paper"):
        cfg = train_config(scale, "clevr567")
        assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    paper = train_config("paper")
    assert (paper.lr, paper.betas, paper.warmup, paper.rays_per_scene) == (
        1e-4,
        (0.9, 0.999),
        1000,
        64,
    )
    m, _ = run_configs("smoke", "packed-clevr11")
    assert (m.num_slots, m.slot_mask_train) == (11, 4)
    assert run_configs("smoke", "room-chair")[0].num_slots == 5
    # the cpu recipe gives Room-Chair a spare slot; the paper scale keeps the paper's K
    assert run_configs("cpu", "room-chair")[0].num_slots == 6
    assert run_configs("paper", "room-chair")[0].num_slots == 5
    assert run_configs("cpu", "room-chair", recipe=False)[0].num_slots == 5
    assert run_configs("cpu", "clevr567")[0].num_slots == 8
    with pytest.raises(ValueError, match="unknown scale"):
        train_config("huge")
    with pytest.raises(ValueError, match="unknown preset"):
        train_config("smoke", "nope")
    with pytest.raises(ValueError, match="unknown keys"):
        TrainConfig.from_dict({"stepz": 3})
    with pytest.raises(ValueError, match="ray_sampling"):
        TrainConfig(ray_sampling="nope")


def test_cli_bad_inputs_exit_2(split, tmp_path, capsys):
    out = str(tmp_path / "run")
    base = ["train", "--scale", "smoke", "--out", out, "--no-progress"]
    cases = [
        base + ["--data", str(split), "--preset", "nope"],  # unknown preset
        base + ["--data", str(split), "--preset", "clevr567"],  # preset/data mismatch
        base + ["--data", str(tmp_path / "missing"), "--preset", "synthetic"],  # no data
        ["train", "--scale", "cpu", "--out", out, "--data", str(split), "--preset", "synthetic"],
        ["render", str(tmp_path / "norun"), "--data", str(split), "--scene", "0"],
        ["info", "--scale", "huge"],
    ]
    for argv in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert err.startswith("svorf: error:") and len(err.splitlines()) == 1, err
    bad = tmp_path / "badrun"
    bad.mkdir()
    (bad / "checkpoint.pt").write_bytes(b"not a checkpoint")
    assert main(["render", str(bad), "--data", str(split), "--scene", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("svorf: error:") and "corrupt" in err and len(err.splitlines()) == 1


def test_cli_train_render_info(split, tmp_path, capsys):
    run = tmp_path / "run"
    argv = [
        "train",
        "--data",
        str(split),
        "--preset",
        "synthetic",
        "--scale",
        "smoke",
        "--out",
        str(run),
        "--steps",
        "2",
        "--image-size",
        "16",
        "--seed",
        "3",
        "--device",
        "cpu",
        "--no-progress",
    ]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "parameters" in out and (run / "checkpoint.pt").is_file()
    assert load_run(run)[1].train.seed == 3
    assert "resuming" not in out
    assert main(argv + ["--resume", "--steps", "3"]) == 0
    assert load_run(run)[1].step == 3
    assert "3 steps, config key" in (out := capsys.readouterr().out)
    assert out.splitlines()[0].endswith(", resuming at step 2")
    dest = tmp_path / "render"
    assert main(["render", str(run), "--data", str(split), "--scene", "1", "--out", str(dest)]) == 0
    pngs = sorted(p.name for p in dest.glob("*.png"))
    assert "grid.png" in pngs and "input.png" in pngs and "v01_render_novel.png" in pngs
    assert "v00_mask_pred.png" in pngs and "v03_depth_gt.png" in pngs and len(pngs) == 26
    assert main(["render", str(run), "--data", str(split), "--scene", "7"]) == 2
    capsys.readouterr()
    assert main(["info", "--scale", "smoke", "--preset", "synthetic"]) == 0
    n = SVORF(model_config("smoke", num_slots=4)).count_parameters()
    assert f"{n:,} parameters" in capsys.readouterr().out
    shutil.rmtree(run)


def test_enc_lr_scale_steps_the_slot_inference_at_a_multiple_and_resumes(split, tmp_path):
    from svorf.optim import param_groups

    fast = {"enc_lr_scale": 2.5}
    full, part, plain = tmp_path / "full", tmp_path / "part", tmp_path / "plain"
    train(split, full, MCFG, tcfg(**fast), progress=False)
    train(split, part, MCFG, tcfg(steps=3, **fast), progress=False)
    train(split, part, MCFG, tcfg(**fast), resume=True, progress=False)
    a = torch.load(full / "checkpoint.pt", weights_only=True)
    b = torch.load(part / "checkpoint.pt", weights_only=True)
    for k, v in a["model"].items():
        assert torch.equal(v, b["model"][k]), k
    rest, inference = a["optimizer"]["param_groups"]
    assert inference["lr"] == pytest.approx(2.5 * rest["lr"]) and rest["lr"] > 0
    model = SVORF(MCFG)
    groups = param_groups(model, 2.5)
    enc = {id(p) for m in (model.encoder, model.slot_module) for p in m.parameters()}
    assert {id(p) for p in groups[1]["params"]} == enc
    assert len(groups[0]["params"]) + len(groups[1]["params"]) == len(list(model.parameters()))
    # At 1: one group, and the config key of the runs before the field existed.
    assert len(param_groups(model)) == 1
    assert "enc_lr_scale" not in tcfg().to_dict() and tcfg(**fast).to_dict()["enc_lr_scale"] == 2.5
    assert TrainConfig.from_dict(tcfg(**fast).to_dict()) == tcfg(**fast)
    train(split, plain, MCFG, tcfg(steps=1), progress=False)
    assert (
        len(torch.load(plain / "checkpoint.pt", weights_only=True)["optimizer"]["param_groups"])
        == 1
    )
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="enc_lr_scale"):
            tcfg(enc_lr_scale=bad)


def test_slot_distill_pulls_the_slots_to_their_refinement_and_resumes(split, tmp_path):
    from svorf.refine import refine_batch

    distill = {"slot_distill": (1.0, 2, 1e-2), "nvs_warmup": 2}
    full, part, plain = tmp_path / "full", tmp_path / "part", tmp_path / "plain"
    train(split, full, MCFG, tcfg(**distill), progress=False)
    train(split, part, MCFG, tcfg(steps=3, **distill), progress=False)
    train(split, part, MCFG, tcfg(**distill), resume=True, progress=False)
    train(split, plain, MCFG, tcfg(nvs_warmup=2), progress=False)
    a = torch.load(full / "checkpoint.pt", weights_only=True)["model"]
    b = torch.load(part / "checkpoint.pt", weights_only=True)["model"]
    c = torch.load(plain / "checkpoint.pt", weights_only=True)["model"]
    for k, v in a.items():
        assert torch.equal(v, b[k]), k
    assert not all(torch.equal(v, c[k]) for k, v in a.items())
    log = _log(full)
    # From the end of nvs_warmup on, the step logs the distance and the refinement's gain.
    assert all("slot_distill" not in r["parts"] for r in log if r["step"] <= 2)
    late = [r["parts"] for r in log if r["step"] > 2]
    assert late and all(p["slot_distill"] >= 0 and p["refine_gain"] > 0 for p in late)
    assert tcfg(**distill).to_dict()["slot_distill"] == [1.0, 2, 0.01]
    assert "slot_distill" not in tcfg().to_dict()
    assert TrainConfig.from_dict(tcfg(**distill).to_dict()) == tcfg(**distill)
    for bad in ((0.0, 2, 1e-2), (1.0, 0, 1e-2), (1.0, 2, 0.0), (1.0, 2), (1.0, 2.5, 1e-2), "x"):
        with pytest.raises(ValueError, match="slot_distill"):
            tcfg(slot_distill=bad)
    # The refinement lowers the rays' error and leaves the parameters without gradients.
    torch.manual_seed(0)
    model = SVORF(MCFG)
    img = torch.rand(2, 3, 32, 32)
    o = torch.tensor([0.0, -12.0, 6.0]).expand(2, 48, 3)
    d = torch.nn.functional.normalize(-o + 0.3 * torch.randn(2, 48, 3), dim=-1)
    rgb = torch.rand(2, 48, 3)
    slots = model.encode(img)
    refined, mse = refine_batch(model, slots, o, d, rgb, steps=8, lr=3e-2)
    assert refined.shape == slots.shape and not refined.requires_grad
    assert float(mse[1]) < float(mse[0])
    assert all(p.grad is None and p.requires_grad for p in model.parameters())


def test_refine_train_renders_from_refined_slots_and_resumes(split, tmp_path):
    iterative = {"refine_train": (2, 2e-2, 16), "nvs_warmup": 2}
    full, part, plain = tmp_path / "full", tmp_path / "part", tmp_path / "plain"
    train(split, full, MCFG, tcfg(**iterative), progress=False)
    train(split, part, MCFG, tcfg(steps=3, **iterative), progress=False)
    train(split, part, MCFG, tcfg(**iterative), resume=True, progress=False)
    train(split, plain, MCFG, tcfg(nvs_warmup=2), progress=False)
    a = torch.load(full / "checkpoint.pt", weights_only=True)["model"]
    b = torch.load(part / "checkpoint.pt", weights_only=True)["model"]
    c = torch.load(plain / "checkpoint.pt", weights_only=True)["model"]
    for k, v in a.items():
        assert torch.equal(v, b[k]), k
    assert not all(torch.equal(v, c[k]) for k, v in a.items())
    # The encoder still learns through the refinement (the identity's gradient).
    enc = [k for k in a if k.startswith("encoder.")]
    assert enc and not all(torch.equal(a[k], c[k]) for k in enc)
    log = _log(full)
    assert all("refine_gain" not in r["parts"] for r in log if r["step"] <= 2)
    late = [r["parts"] for r in log if r["step"] > 2]
    assert late and all(p["refine_gain"] > 0 for p in late)
    assert tcfg(**iterative).to_dict()["refine_train"] == [2, 0.02, 16]
    assert "refine_train" not in tcfg().to_dict()
    assert TrainConfig.from_dict(tcfg(**iterative).to_dict()) == tcfg(**iterative)
    for bad in ((0, 2e-2, 16), (2, 0.0, 16), (2, 2e-2, 0), (2, 2e-2), (2.5, 2e-2, 16), "x"):
        with pytest.raises(ValueError, match="refine_train"):
            tcfg(refine_train=bad)
    with pytest.raises(ValueError, match="one of them"):
        tcfg(refine_train=(2, 2e-2, 16), slot_distill=(1.0, 2, 1e-2))


def test_recipe_of_names_the_recipes_model_and_not_its_variants():
    from svorf.train_config import recipe_of

    for preset in ("clevr567", "clevr567-heldout", "packed-clevr11", "room-chair"):
        m, t = run_configs("cpu", preset)
        # --steps, --seed and benchmark --train-minutes change only these
        assert recipe_of(m, t.replace(steps=1_000_000, seed=3)).name == "cpu recipe"
    m, t = run_configs("cpu", "clevr567")
    assert recipe_of(m.replace(image_size=128), t) is None  # another cost per step
    assert recipe_of(m.replace(hypernetwork=False), t) is None  # an ablation
    assert recipe_of(m, t.replace(rays_per_scene=256)) is None
    assert recipe_of(*run_configs("cpu", "room-diverse")) is None  # no recipe there
    assert recipe_of(*run_configs("cpu", "clevr567", recipe=False)) is None
    assert recipe_of(*run_configs("smoke", "clevr567")) is None


def test_rate_check_note_projects_the_budget_and_names_the_step_budget(capsys):
    from svorf.run_records import RateCheck

    check = RateCheck("cpu recipe", (427.0, 440.0), 3600.0, float32_here=True, after_s=150.0)
    # The 60-minute command on an AVX2-only CPU: 218 steps per minute, 13,068 steps.
    note = check.note(218.0, 13_068)
    assert "218 steps per minute here" in note and "about 13,068 steps" in note
    assert "427-440 steps per minute" in note and "float32" in note
    assert "--steps 26000" in note and "about 119 minutes here" in note
    assert check.note(0.8 * 427.0, 20_000) is None  # near the recipe's speed
    assert "float32" not in RateCheck("r", (427.0, 440.0), 7200.0).note(100.0, 12_000)
    assert RateCheck.probe_seconds(3600.0) == 180.0
    assert RateCheck.probe_seconds(600.0) == 60.0 and RateCheck.probe_seconds(1e5) == 300.0
    # Speaks once it is due, of the speed in the window's second half: a call that resumed
    # at 1,000 s of training, 1,372 steps done at 150 s, 272 of them since 75 s.
    assert not check.speak(1_100, 1_075.0, 1_000.0, 10**6)  # 75 s: the window starts
    assert not check.speak(1_371, 1_149.0, 1_000.0, 10**6)  # 149 s: not yet
    assert capsys.readouterr().err == ""
    assert check.speak(1_372, 1_150.0, 1_000.0, 10**6)
    err = capsys.readouterr().err  # 217.6 steps per minute for 2,450 s more: 8,885 steps
    assert err.startswith("svorf train: 218 steps per minute here") and "about 10,257" in err
    # Where the step limit will end the run before the budget, the speed costs no steps.
    short = RateCheck("cpu recipe", (427.0, 440.0), 3600.0, after_s=150.0)
    assert not short.speak(1_100, 1_075.0, 1_000.0, 10_257)
    assert short.speak(1_372, 1_150.0, 1_000.0, 10_257) and capsys.readouterr().err == ""


def test_a_slow_time_budgeted_recipe_run_says_so_once_early(split, tmp_path, monkeypatch, capsys):
    import svorf.train_config as tc
    from svorf.registry import Recipe
    from svorf.run_records import RateCheck

    # The smoke model stands in for a recipe's, measured at an impossible speed.
    fast = Recipe("test recipe", {}, {}, ("synthetic",), steps_per_minute=(1e9, 1e9))
    monkeypatch.setattr(tc, "recipe_of", lambda m, t: fast)
    monkeypatch.setattr(RateCheck, "probe_seconds", staticmethod(lambda s: 0.0))
    # A 1.5-second budget ends the run long before its 1,000 steps.
    budget = tcfg(steps=1000, ckpt_every=1000)
    train(split, tmp_path / "budget", MCFG, budget, progress=False, max_wall_s=1.5)
    err = capsys.readouterr().err
    assert err.count("steps per minute here") == 1, err
    assert "test recipe's results were measured at 1000000000-1000000000" in err
    # No budget, no check: a step budget makes the same steps on any machine.
    train(split, tmp_path / "steps", MCFG, tcfg(steps=4), progress=False)
    assert "steps per minute here" not in capsys.readouterr().err
