"""The cpu recipe's levers (benchmark/tools/recipe.py, docs/notes/cpu_recipe.md): each new
config field changes the computation it names, the paper scale has them all off, and the
time-budgeted driver stops, resumes and evaluates."""

from __future__ import annotations

import json
import math

import pytest
import torch

import svorf.train as train_mod
from benchmark.tools.recipe import (
    RECIPE_LEVERS,
    adjusted_rand_index,
    make_eval_fn,
    recipe_configs,
    save_segmentation_grid,
    segmentation_metrics_basic,
    train_eval,
)
from svorf.compose import SlotGuidedComposer, masked_softmax
from svorf.config import ModelConfig, model_config
from svorf.data import MultiViewDataset
from svorf.model import SVORF
from svorf.synthetic import write_synthetic_split
from svorf.train import TrainConfig, load_run, train, train_config


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return write_synthetic_split(tmp_path_factory.mktemp("d") / "train", n_scenes=2,
                                 resolution=32)  # fmt: skip


def test_paper_scale_has_the_levers_off():
    m = model_config("paper")
    assert m.fg_zmin is None and m.fg_box is None and m.comp_temperature == 1.0
    assert m.slot_locality is None and not m.bg_outside_fg
    t = train_config("paper")
    assert t.nvs_warmup == 0 and t.ray_sampling == "uniform"
    assert ModelConfig().comp_temperature == 1.0 and TrainConfig().nvs_warmup == 0
    # The recipe switches them on, on top of the cpu scale.
    mr, tr = recipe_configs()
    assert mr.fg_zmin == RECIPE_LEVERS["fg_zmin"] and tr.nvs_warmup == RECIPE_LEVERS["nvs_warmup"]
    assert tr.ray_sampling == "object_heavy" and mr.image_size == 64
    assert mr.bg_outside_fg and mr.fg_box == 3.75 and tr.warmup == 100
    off = {
        "fg_zmin": None,
        "fg_box": None,
        "bg_outside_fg": False,
        "nvs_warmup": 0,
        "slot_locality": None,
        "slot_centre": "learned",
        "clip_floor_z": None,
        "photo_l1": None,
        "coarse_loss_weight": 1.0,
    }
    assert mr.slot_centre == "anchored" and m.slot_centre == "learned"
    assert mr.clip_floor_z == 0.0 and m.clip_floor_z is None  # the far floor: cpu recipe only
    assert mr.photo_l1 == (0.5, 0.7) and m.photo_l1 is None  # absolute error: cpu recipe only
    assert mr.coarse_loss_weight == 0.1 and m.coarse_loss_weight == 1.0  # cpu recipe only
    assert tr.ema_decay == 0.999 and t.ema_decay == 0.0  # the weight average: cpu recipe only
    mr2, tr2 = recipe_configs(levers=off, lr=1e-3)
    assert mr2.fg_zmin is None and tr2.nvs_warmup == 0 and tr2.lr == 1e-3
    assert mr2 == model_config("cpu")  # slot_locality off takes its narrowing with it
    assert mr.slot_locality_narrow == (0.5, 0.3, 0.8) and mr2.slot_locality_narrow is None
    kept = recipe_configs(levers={**off, "slot_locality": 0.8})[0]
    assert kept.slot_locality == 0.8 and kept.slot_locality_narrow == (0.5, 0.3, 0.8)
    assert recipe_configs(warmup=5)[1].warmup == 5  # train overrides win over the levers
    # A model field the recipe does not name is a lever too: it reaches the ModelConfig,
    # not the TrainConfig (which would refuse it).
    mf, tf = recipe_configs(levers={"fg_mass": (0.001, 0.5, 0.8), "lr": 2e-4})
    assert mf.fg_mass == (0.001, 0.5, 0.8) and tf.lr == 2e-4 and mr.fg_mass is None


def test_invalid_values_are_rejected():
    with pytest.raises(ValueError, match="comp_temperature"):
        model_config("smoke", comp_temperature=0.0)
    with pytest.raises(ValueError, match="nvs_warmup"):
        TrainConfig(nvs_warmup=-1)


def _model(**kw) -> SVORF:
    torch.manual_seed(0)
    return SVORF(model_config("smoke", num_slots=4, **kw)).eval()


def test_fg_zmin_gives_the_floor_to_the_background_slot():
    base = _model()
    floor = _model(fg_zmin=0.0)
    floor.load_state_dict(base.state_dict())
    imgs = torch.rand(1, 3, 32, 32)
    # Horizontal rays entirely below z = 0 (inside the scene box) and rays above it.
    o = torch.tensor([[-4.0, -1.0, -1.0], [-4.0, 1.0, 1.0]])[None]
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])[None]
    with torch.no_grad():
        a, b = base(imgs, o, d), floor(imgs, o, d)
    # Below the floor only the background slot (last) is left ...
    assert torch.allclose(b.slot_probs[0, 0], torch.tensor([0.0, 0.0, 0.0, 1.0]), atol=1e-5)
    assert a.slot_probs[0, 0, :3].sum() > 0.01
    # ... above it the prior changes nothing.
    torch.testing.assert_close(a.rgb[0, 1], b.rgb[0, 1])
    torch.testing.assert_close(a.slot_probs[0, 1], b.slot_probs[0, 1])


def test_comp_temperature_divides_the_composition_logits():
    cfg = model_config("smoke", num_slots=4)
    torch.manual_seed(0)
    c1 = SlotGuidedComposer(cfg, 20)
    c2 = SlotGuidedComposer(cfg.replace(comp_temperature=0.25), 20)
    c2.load_state_dict(c1.state_dict())
    gx, slots = torch.randn(2, 1, 7, 20), torch.randn(2, 4, cfg.slot_dim)
    logits = c1.logits_kp(gx, slots)  # [B, K, P]
    m1, m2 = c1(gx, slots), c2(gx, slots)
    torch.testing.assert_close(m1, masked_softmax(logits, None, dim=1).transpose(1, 2))
    torch.testing.assert_close(m2, masked_softmax(logits / 0.25, None, dim=1).transpose(1, 2))
    # Sharper: the top slot gets more mass.
    assert (m2.max(-1).values >= m1.max(-1).values - 1e-6).all()
    # And the whole model's rendering changes.
    a, b = _model(), _model(comp_temperature=0.25)
    b.load_state_dict(a.state_dict())
    imgs, o = torch.rand(1, 3, 32, 32), torch.tensor([0.0, -12.0, 6.0]).expand(1, 8, 3)
    d = torch.nn.functional.normalize(-o + 0.3 * torch.randn(1, 8, 3), dim=-1)
    with torch.no_grad():
        assert not torch.allclose(a(imgs, o, d).rgb, b(imgs, o, d).rgb)


def test_the_render_probe_sets_the_composition_temperature_of_a_trained_model():
    # render_probe(model, {"comp_temperature": T}) renders as a model built with T does.
    from svorf.checkpoint import render_probe

    a, b = _model(), _model(comp_temperature=0.25)
    b.load_state_dict(a.state_dict())
    imgs, o = torch.rand(1, 3, 32, 32), torch.tensor([0.0, -12.0, 6.0]).expand(1, 8, 3)
    d = torch.nn.functional.normalize(-o + 0.3 * torch.randn(1, 8, 3), dim=-1)
    with torch.no_grad():
        before = a(imgs, o, d).rgb
        assert render_probe(a, {"comp_temperature": 0.25}) is a
        assert a.cfg.comp_temperature == 0.25 and a.composer.temperature == 0.25
        torch.testing.assert_close(a(imgs, o, d).rgb, b(imgs, o, d).rgb)
        assert not torch.allclose(before, a(imgs, o, d).rgb)


def test_the_render_probe_turns_the_sampling_box_off_as_a_model_built_without_it():
    # The box and its floor clip only decide where a ray's samples lie: a trained model can
    # render without them (--render-set clip_to_box=false clip_floor_z=null ...).
    from svorf.checkpoint import render_probe

    a, b = _model(clip_to_box=True, clip_floor_z=0.0), _model(clip_to_box=False)
    b.load_state_dict(a.state_dict())
    imgs, o = torch.rand(1, 3, 32, 32), torch.tensor([0.0, -12.0, 6.0]).expand(1, 8, 3)
    d = torch.nn.functional.normalize(-o + 0.3 * torch.randn(1, 8, 3), dim=-1)
    with torch.no_grad():
        before = a(imgs, o, d).rgb
        render_probe(a, {"clip_to_box": False, "clip_floor_z": None})
        torch.testing.assert_close(a(imgs, o, d).rgb, b(imgs, o, d).rgb)
        assert not torch.allclose(before, a(imgs, o, d).rgb)
    with pytest.raises(ValueError, match="clip_floor_z"):  # the config's own check
        render_probe(_model(clip_to_box=True, clip_floor_z=0.0), {"clip_to_box": False})


def test_nvs_warmup_uses_input_view_rays_first(split, tmp_path, monkeypatch):
    seen = []
    orig = train_mod.RaySampler.sample

    def spy(
        self, scenes, gen, salient_fraction=None, include_input=False, pixel_jitter=0.0, stride=1
    ):
        batch = orig(self, scenes, gen, salient_fraction, include_input, pixel_jitter)
        seen.append(bool((batch.target_view == batch.input_view[:, None]).all()))
        return batch

    monkeypatch.setattr(train_mod.RaySampler, "sample", spy)
    mcfg = model_config("smoke", num_slots=4)
    tcfg = train_config("smoke", steps=6, nvs_warmup=3, log_every=3, ckpt_every=6)
    train(split, tmp_path / "r", mcfg, tcfg, progress=False)
    assert seen[:3] == [True] * 3  # rays from the input view itself
    assert seen[3:] == [False] * 3  # novel views afterwards (targets never the input view)


def test_max_wall_s_stops_with_a_checkpoint_and_resumes(split, tmp_path):
    mcfg = model_config("smoke", num_slots=4)
    tcfg = train_config("smoke", steps=1000, ckpt_every=500)
    s = train(split, tmp_path / "r", mcfg, tcfg, progress=False, max_wall_s=0.0)
    assert s.steps == 1
    _, info = load_run(tmp_path / "r")
    assert info.step == 1
    s2 = train(split, tmp_path / "r", mcfg, tcfg.replace(steps=3), resume=True, progress=False)
    assert s2.start_step == 1 and s2.steps == 3


def test_ari_matches_known_values():
    gt = torch.tensor([0, 0, 1, 1, 2, 2])
    assert adjusted_rand_index(gt, gt) == pytest.approx(1.0)
    assert adjusted_rand_index(torch.tensor([5, 5, 7, 7, 9, 9]), gt) == pytest.approx(1.0)
    # index 1, expected 3 * 3 / 15 = 0.6, max 3: (1 - 0.6) / (3 - 0.6) = 1/6
    assert adjusted_rand_index(torch.tensor([0, 0, 1, 2, 1, 2]), gt) == pytest.approx(1 / 6)
    assert math.isnan(adjusted_rand_index(gt, gt, torch.zeros(6, dtype=torch.bool)))
    bm = pytest.importorskip("benchmark.metrics")
    torch.manual_seed(0)
    pred = torch.randint(0, 4, (2, 3, 8, 8))
    true = torch.randint(0, 3, (2, 3, 8, 8))
    ours, ref = segmentation_metrics_basic(pred, true, 0), bm.segmentation_metrics(pred, true, 0)
    for k in ("ari", "fg_ari", "nv_ari"):
        torch.testing.assert_close(ours[k], ref[k].double(), atol=1e-9, rtol=0)


def test_train_eval_writes_metrics_and_grid(split, tmp_path):
    mcfg = model_config("smoke", num_slots=4)
    tcfg = train_config("smoke", steps=10_000, eval_every=2, eval_scenes=2, ckpt_every=100)
    res = train_eval(split, split, tmp_path / "r", 0.0, mcfg, tcfg, grid_scenes=2)
    final = json.loads((tmp_path / "r" / "final_eval.json").read_text())
    for k in ("ari", "fg_ari", "nv_ari", "psnr_input", "psnr_novel"):
        assert k in final
    assert (tmp_path / "r" / "grid.png").stat().st_size > 0 and res["final"]["step"] == 1
    ds = MultiViewDataset(split, image_size=32)
    model, _ = load_run(tmp_path / "r")
    out = make_eval_fn(None, 1)(model, ds)
    assert 0 < out["psnr_input"] < 100
    save_segmentation_grid(model, ds, tmp_path / "g.png", 1)
    # a fine-tune probe: the second run starts from the first one's weights
    train_eval(
        split, split, tmp_path / "ft", 0.0, mcfg, tcfg, grid_scenes=1, init_from=tmp_path / "r"
    )
    init = json.loads((tmp_path / "ft" / "config.json").read_text())["init_from"]
    assert init["step"] == 1 and init["kept"] == 0 and init["loaded"] > 0


def test_bg_outside_fg_keeps_the_background_slot_out_of_the_object_region():
    base = _model(fg_zmin=0.0)
    prior = _model(fg_zmin=0.0, bg_outside_fg=True)
    prior.load_state_dict(base.state_dict())
    imgs = torch.rand(1, 3, 32, 32)
    o = torch.tensor([[-4.0, -1.0, -1.0], [-4.0, 1.0, 1.0]])[None]
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])[None]
    with torch.no_grad():
        a, b = base(imgs, o, d), prior(imgs, o, d)
    # Below the floor: background only, as with fg_zmin alone.
    torch.testing.assert_close(a.slot_probs[0, 0], b.slot_probs[0, 0])
    # Above it: the background slot has no share at all (without the prior it has one).
    assert float(b.slot_probs[0, 1, -1]) == 0.0 and float(a.slot_probs[0, 1, -1]) > 1e-3
    assert not torch.allclose(a.rgb[0, 1], b.rgb[0, 1])
    with pytest.raises(ValueError, match="bg_outside_fg"):
        model_config("smoke", bg_outside_fg=True)
    assert model_config("paper").bg_outside_fg is False


def test_bg_floor_slab_keeps_the_background_in_a_slab_under_the_object_region():
    kw = {"fg_zmin": 0.0, "fg_box": 3.0, "bg_outside_fg": True}
    base, slab = _model(**kw), _model(**kw, bg_floor_slab=0.2)
    slab.load_state_dict(base.state_dict())
    imgs = torch.rand(1, 3, 32, 32)
    # Samples lie at t in [near, far] = [6, 20]. Ray 0: horizontal in the slab (z = -0.1);
    # ray 1: vertical, wholly under the slab inside the footprint (z from -15 to -1);
    # ray 2: horizontal above the floor (z = 1).
    o = torch.tensor([[-9.0, 0.5, -0.1], [0.5, 0.5, -21.0], [-9.0, 0.5, 1.0]])[None]
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])[None]
    with torch.no_grad():
        a, b = base(imgs, o, d), slab(imgs, o, d)
    # In the slab and above the floor nothing changes.
    torch.testing.assert_close(a.rgb[0, 0], b.rgb[0, 0])
    torch.testing.assert_close(a.rgb[0, 2], b.rgb[0, 2])
    torch.testing.assert_close(a.slot_probs[0, 0], b.slot_probs[0, 0])
    # Under the slab: without the prior the background owns the ray, with it no slot does.
    assert float(a.slot_probs[0, 1, -1]) > 1e-3
    assert float(b.slot_probs[0, 1].abs().sum()) == 0.0
    with pytest.raises(ValueError, match="bg_floor_slab"):
        model_config("smoke", bg_floor_slab=0.2, fg_zmin=0.0, fg_box=3.0)
    with pytest.raises(ValueError, match="bg_floor_slab"):
        model_config("smoke", bg_floor_slab=0.0, **kw)
    assert model_config("paper").bg_floor_slab is None


def test_plot_subcommand_draws_runs_and_rejects_a_non_run(tmp_path, capsys):
    from PIL import Image

    from benchmark.tools.recipe import main

    run = tmp_path / "r"
    run.mkdir()
    (run / "log.jsonl").write_text(
        "".join(json.dumps({"wall_s": 30.0 * i, "loss": 0.02 / (i + 1)}) + "\n" for i in range(4))
    )
    (run / "eval.jsonl").write_text(
        json.dumps({"wall_s": 60.0, "fg_ari": 0.4, "fg_ari_shuffled": 0.1}) + "\n"
    )
    out = tmp_path / "curve.png"
    assert main(["plot", f"mine={run}", "--out", str(out)]) == 0
    w, h = Image.open(out).size
    assert w > 600 and h > 200
    capsys.readouterr()
    assert main(["plot", str(tmp_path / "nope"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "no log.jsonl" in err and len(err.splitlines()) == 1


def test_object_failures_classifies_lost_merged_and_own():
    from benchmark.tools.failures import object_failures, summarize_failures

    gt = torch.tensor([[0, 1, 1, 2], [0, 3, 3, 4], [0, 0, 5, 5]])
    # slot 3 = background; objects 1 and 2 share slot 0 (merged), 3 is in slot 1 (own),
    # 4 goes to the background (lost), 5 is half slot 2, half background -> own (tie: lower id)
    pred = torch.tensor([[3, 0, 0, 0], [3, 1, 1, 3], [3, 3, 2, 3]])
    rows = object_failures(pred, gt, bg_slot=3)
    assert [(r["id"], r["slot"], r["kind"]) for r in rows] == [
        (1, 0, "merged"),
        (2, 0, "merged"),
        (3, 1, "own"),
        (4, 3, "lost"),
        (5, 2, "own"),
    ]
    assert rows[4]["share"] == 0.5 and rows[0]["pixels"] == 2
    s = summarize_failures(rows)
    assert s["objects"] == 5
    assert s["lost"] == {"fraction": 0.2, "median_pixels": 1.0}
    assert s["merged"]["fraction"] == 0.4 and s["own"]["fraction"] == 0.4
    assert s["own_share"] == 0.75
    with pytest.raises(ValueError, match="pred"):
        object_failures(pred[:2], gt, 3)


def test_fg_ari_repairs_score_each_error_kind_alone():
    from sklearn.metrics import adjusted_rand_score

    from benchmark.tools.failures import fg_ari_repairs

    # slot 3 = background. Object 1: slots 0 and 1 (split); object 2: one pixel in the
    # background (a rim); objects 3 and 4 share slot 2 (merged); object 5 lost.
    gt = torch.tensor([[1, 1, 1, 1, 0], [2, 2, 2, 0, 0], [3, 3, 4, 4, 0], [5, 5, 0, 0, 0]])
    pred = torch.tensor([[0, 0, 0, 1, 3], [1, 1, 3, 3, 3], [2, 2, 2, 2, 3], [3, 3, 3, 3, 3]])
    r = fg_ari_repairs(pred, gt, bg_slot=3)
    fg = gt.reshape(-1) != 0
    g = gt.reshape(-1)[fg].numpy()

    def ari(labels):
        return adjusted_rand_score(g, torch.tensor(labels).reshape(-1)[fg].numpy())

    assert r["fg_ari"] == pytest.approx(ari(pred.tolist()))
    leak = [[0, 0, 0, 1, 3], [1, 1, 6, 3, 3], [2, 2, 2, 2, 3], [9, 9, 3, 3, 3]]  # fresh labels
    split = [[0, 0, 0, 0, 3], [1, 1, 3, 3, 3], [2, 2, 2, 2, 3], [3, 3, 3, 3, 3]]
    merge = [[0, 0, 0, 1, 3], [1, 1, 3, 3, 3], [2, 2, 7, 7, 3], [3, 3, 3, 3, 3]]
    assert r["bg_leak_repaired"] == pytest.approx(ari(leak))
    assert r["split_repaired"] == pytest.approx(ari(split))
    assert r["merge_repaired"] == pytest.approx(ari(merge))
    assert min(r["bg_leak_repaired"], r["split_repaired"], r["merge_repaired"]) > r["fg_ari"]
    assert math.isnan(fg_ari_repairs(pred, torch.zeros_like(gt), 3)["fg_ari"])


def test_ari_repairs_score_bleed_lost_and_the_one_pixel_rim():
    from sklearn.metrics import adjusted_rand_score

    from benchmark.tools.failures import ari_repairs

    # slot 3 = background; object 1 (slot 0) claims a rim pixel beside it and one far away;
    # object 2 is half lost to the background.
    gt = torch.tensor([[1, 1, 0, 0, 0, 0], [1, 1, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0],
                       [0, 0, 0, 0, 2, 2], [0, 0, 0, 0, 2, 2], [0, 0, 0, 0, 0, 0]])  # fmt: skip
    pred = torch.tensor([[0, 0, 0, 3, 3, 0], [0, 0, 3, 3, 3, 3], [3, 3, 3, 3, 3, 3],
                         [3, 3, 3, 3, 1, 1], [3, 3, 3, 3, 3, 3], [3, 3, 3, 3, 3, 3]])  # fmt: skip
    r = ari_repairs(pred, gt, bg_slot=3)

    def ari(labels):
        return adjusted_rand_score(gt.reshape(-1).numpy(), torch.as_tensor(labels).reshape(-1))

    assert r["ari"] == pytest.approx(ari(pred))
    bleed = pred.clone()
    bleed[0, 2] = bleed[0, 5] = 3
    lost = pred.clone()
    lost[4, 4:] = 6  # a fresh label: max(pred, bg) + 1 + id 2
    assert r["bleed_repaired"] == pytest.approx(ari(bleed))
    assert r["lost_repaired"] == pytest.approx(ari(lost))
    assert r["bleed_fraction"] == pytest.approx(2 / 28)
    assert r["bleed_within_1px"] == pytest.approx(0.5)  # (0, 2) touches object 1; (0, 5) not
    assert r["bleed_within_2px"] == pytest.approx(0.5)
    rim = gt.clone()
    rim[:3, :3] = torch.where(rim[:3, :3] == 0, 1, rim[:3, :3])
    rim[2:, 3:] = torch.where(rim[2:, 3:] == 0, 2, rim[2:, 3:])
    assert r["rim_ceiling"] == pytest.approx(ari(rim))
    assert min(r["bleed_repaired"], r["lost_repaired"]) > r["ari"] and r["rim_ceiling"] < 1
    assert math.isnan(ari_repairs(torch.full_like(gt, 3), gt, 3)["bleed_within_1px"])
    with pytest.raises(ValueError, match="same"):
        ari_repairs(pred[:2], gt, 3)


def test_rim_geometry_tells_an_offset_from_a_dilation():
    import doctest

    import benchmark.tools.rim as rim_mod
    from benchmark.tools.rim import rim_geometry, summarize_rim

    assert doctest.testmod(rim_mod).failed == 0
    gt = torch.zeros(10, 10, dtype=torch.long)
    gt[2:5, 2:5] = 1  # a 3x3 object
    gt[7:9, 7:9] = 2  # a 2x2 object, lost to the background below
    # an offset: object 1 predicted one pixel lower (slot 0; slot 3 is the background)
    shifted = torch.full_like(gt, 3)
    shifted[3:6, 2:5] = 0
    r = summarize_rim([rim_geometry(shifted, gt, bg_slot=3)])
    assert r["objects"] == 1  # object 2 has no foreground pixels: no shape to compare
    assert r["centroid_shift_px"] == pytest.approx({"x": 0.0, "y": 1.0})
    assert r["area_ratio_median"] == pytest.approx(1.0)
    assert r["claimed_by_side"]["below"] == pytest.approx(3 / 5)  # object 2's 2 not claimed
    assert r["claimed_by_side"]["above"] == r["claimed_by_side"]["left"] == 0.0
    # a dilation: both objects grown by one pixel on every side, no offset
    grown = torch.full_like(gt, 3)
    grown[1:6, 1:6] = 0
    grown[6:10, 6:10] = 1
    views = [rim_geometry(grown, gt, bg_slot=3), rim_geometry(grown, gt, bg_slot=3)]
    r = summarize_rim(views)
    assert r["objects"] == 4
    assert r["centroid_shift_px"]["x"] == pytest.approx(0.0, abs=0.3)
    assert r["centroid_shift_px"]["y"] == pytest.approx(0.0, abs=0.3)
    assert r["area_ratio_median"] > 2.5  # 25 / 9 and (image edge) 9 / 4
    assert all(v == pytest.approx(1.0) for v in r["claimed_by_side"].values())
    assert math.isnan(summarize_rim([])["area_ratio_median"])
    with pytest.raises(ValueError, match="same"):
        rim_geometry(gt[:2], gt, 3)


def test_ring_colour_share_reads_the_object_colour_in_the_rim():
    from benchmark.tools.rim import rim_geometry, ring_colour_share, summarize_rim

    gt = torch.zeros(20, 20, dtype=torch.long)
    gt[7:12, 7:12] = 1  # a 5x5 red object on a grey floor
    gt[1:3, 16:18] = 2  # a 2x2 object: no interior, not measured
    image = torch.full((20, 20, 3), 0.5)
    image[gt == 1] = torch.tensor([1.0, 0.0, 0.0])
    image[6, 7:12] = torch.tensor([0.75, 0.25, 0.25])  # the row above: half blended
    pred = torch.full_like(gt, 3)
    pred[6:13, 6:13] = 0  # object 1 grown by one pixel: its whole ring claimed
    pred[12, 6:13] = 3  # ... except the row below
    render = image.clone()
    render[12, 6:13] = torch.tensor([1.0, 0.0, 0.0])  # the model paints that row red
    rows = ring_colour_share(pred, gt, 3, image, render)
    assert len(rows) == 24  # the 8-connected ring of object 1 only
    blended = [r for r in rows if r[0] > 0.25]
    assert len(blended) == 5 and all(r[0] == pytest.approx(0.5) and r[2] for r in blended)
    unclaimed = [r for r in rows if not r[2]]
    assert len(unclaimed) == 7 and all(
        r[0] == 0.0 and r[1] == pytest.approx(1.0) for r in unclaimed
    )
    s = summarize_rim([rim_geometry(pred, gt, 3, image=image, render=render)])["ring_colour_share"]
    assert s["claimed"]["pixels"] == 17 and s["unclaimed"]["pixels"] == 7
    assert s["claimed"]["share_in_image_median"] == pytest.approx(0.0)
    assert s["claimed"]["image_over_half"] == 0.0  # 0.5 is not over half
    assert s["unclaimed"]["share_in_render_median"] == pytest.approx(1.0)
    # an object of the floor's colour is not measured; without a render the share is nan
    grey = image.clone()
    grey[gt == 1] = 0.52
    assert ring_colour_share(pred, gt, 3, grey) == []
    assert math.isnan(ring_colour_share(pred, gt, 3, image)[0][1])
    assert "ring_colour_share" not in summarize_rim([rim_geometry(pred, gt, 3)])


def test_split_geometry_tells_top_and_bottom_from_side_by_side():
    from benchmark.tools.splits import split_geometry, summarize_splits

    gt = torch.zeros(12, 12, dtype=torch.long)
    gt[1:7, 1:4] = 1  # a tall object: slot 0 on top, slot 1 below (a top-and-bottom split)
    gt[8:11, 1:7] = 2  # a wide object: slot 2 left, slot 1 right (side by side)
    gt[1:4, 8:11] = 3  # whole in slot 2, one background pixel: not split
    pred = torch.full_like(gt, 4)  # slot 4 = background
    pred[1:4, 1:4], pred[4:7, 1:4] = 0, 1
    pred[8:11, 1:5], pred[8:11, 5:7] = 2, 1
    pred[1:4, 8:11] = 2
    pred[1, 8] = 4
    rows = split_geometry(pred, gt, bg_slot=4)
    assert [r["split"] for r in rows] == [True, True, False]
    assert rows[0]["dy"] == pytest.approx(3.0) and rows[0]["dx"] == pytest.approx(0.0)
    assert rows[1]["dy"] == pytest.approx(0.0) and rows[1]["dx"] == pytest.approx(3.0)
    s = summarize_splits(rows, large=10)
    assert s == {"objects": 3, "split": 2, "split_large": 2, "top_bottom": 1, "second_below": 1}
    # a second slot under min_share or min_pixels is not a split
    assert not split_geometry(pred, gt, bg_slot=4, min_share=0.6)[0]["split"]
    assert not split_geometry(pred, gt, bg_slot=4, min_pixels=10)[0]["split"]
    with pytest.raises(ValueError, match="split_geometry"):
        split_geometry(pred[:2], gt, 4)


def test_depth_breakdown_splits_background_at_the_sampled_box(split):
    from benchmark.tools.failures import depth_breakdown

    ds = MultiViewDataset(split, image_size=32)
    torch.manual_seed(0)
    free = SVORF(model_config("smoke", num_slots=4, clip_to_box=False)).eval()
    d = depth_breakdown(free, ds)
    assert d["bg_outside_share"] == 0 and math.isnan(d["abs_rel_bg_outside"])
    assert d["abs_rel_bg_inside"] > 0 and d["abs_rel_objects"] > 0 and d["n_scenes"] == 2
    # a box smaller than any floor point the cameras see: all background is outside it
    tiny = SVORF(model_config("smoke", num_slots=4, clip_to_box=True, box_half=0.05)).eval()
    t = depth_breakdown(tiny, ds, n_scenes=1)
    assert t["bg_outside_share"] == 1 and math.isnan(t["abs_rel_bg_inside"])
    assert t["abs_rel_bg_outside"] > 0 and t["n_scenes"] == 1


def test_diagnose_subcommand_and_final_eval_failures(split, tmp_path, capsys):
    from benchmark.tools.recipe import main

    mcfg = model_config("smoke", num_slots=4)
    tcfg = train_config("smoke", steps=10_000, eval_every=0, ckpt_every=100)
    train_eval(split, split, tmp_path / "r", 0.0, mcfg, tcfg, grid_scenes=1)
    final = json.loads((tmp_path / "r" / "final_eval.json").read_text())
    f = final["failures"]
    assert f["objects"] > 0 and f["n_scenes"] == 2
    assert math.isclose(sum(f[k]["fraction"] for k in ("lost", "merged", "own")), 1.0)
    assert set(f["fg_ari_repairs"]) == {
        "fg_ari", "bg_leak_repaired", "split_repaired", "merge_repaired"
    }  # fmt: skip
    assert f["ari_repairs"]["ari"] == pytest.approx(final["ari"], abs=1e-6)
    assert 0 <= f["ari_repairs"]["bleed_fraction"] <= 1
    grid = tmp_path / "g" / "grid.png"
    argv = ["diagnose", str(tmp_path / "r"), "--test", str(split), "--threads", "1"]
    assert main([*argv, "--grid", str(grid), "--grid-scenes", "2", "--depth"]) == 0
    saved = json.loads((tmp_path / "r" / "failures.json").read_text())
    assert saved["depth"]["n_scenes"] == 2 and saved["depth"]["abs_rel_objects"] > 0
    assert saved["objects"] == f["objects"] and saved["step"] == final["step"]
    out = json.loads(capsys.readouterr().out)
    assert out["objects"] == f["objects"] and out["grid"] == str(grid)
    from PIL import Image

    with Image.open(grid) as im:  # two scene rows, seven tiles each
        assert im.size[0] > 3 * im.size[1] and im.size[1] >= 4 * mcfg.image_size
    assert main(["diagnose", str(tmp_path), "--test", str(split)]) == 2
    err = capsys.readouterr().err.strip()
    assert "no checkpoint" in err and len(err.splitlines()) == 1
    # A render probe: object slots barred below z = 100 leave every object to the background;
    # written beside, not over, the plain diagnosis.
    assert main([*argv, "--scenes", "1", "--render-set", "fg_zmin=100"]) == 0
    probe = json.loads((tmp_path / "r" / "failures-probe.json").read_text())
    assert probe["render_set"] == {"fg_zmin": 100} and probe["lost"]["fraction"] == 1.0
    assert json.loads((tmp_path / "r" / "failures.json").read_text())["render_set"] == {}
    # More samples per ray: a quadrature probe (no weight depends on the sample counts).
    assert main([*argv, "--scenes", "1", "--render-set", "n_fine=24"]) == 0
    probe = json.loads((tmp_path / "r" / "failures-probe.json").read_text())
    assert probe["render_set"] == {"n_fine": 24} and probe["objects"] > 0
    capsys.readouterr()
    assert main([*argv, "--render-set", "num_slots=3"]) == 2
    err = capsys.readouterr().err.strip()
    assert "num_slots cannot change at render time" in err and len(err.splitlines()) == 1
    # The optimizer's weights beside the average; a run without an average has none.
    assert main([*argv, "--scenes", "1", "--weights", "raw"]) == 0
    assert json.loads((tmp_path / "r" / "failures-raw.json").read_text())["weights"] == "raw"
    assert saved["weights"] == "raw"
    capsys.readouterr()
    assert main([*argv, "--scenes", "1", "--weights", "ema"]) == 2
    err = capsys.readouterr().err.strip()
    assert "no averaged weights" in err and len(err.splitlines()) == 1
    for name, msg in [
        ("ema0.999", "kept no average probe 'ema0.999'"),
        ("best", "weights must be"),
    ]:
        assert main([*argv, "--scenes", "1", "--weights", name]) == 2
        err = capsys.readouterr().err.strip()
        assert msg in err and len(err.splitlines()) == 1


def test_bg_pos_freqs_limits_only_the_background_slots_bandwidth():
    from svorf.field import build_fields, pe_frequency_mask, positional_encoding

    m = pe_frequency_mask(3, 1)
    assert m.tolist() == [1.0] * 3 + [1, 1, 1, 0, 0, 0, 0, 0, 0] * 2  # raw, sin, cos
    base_cfg = model_config("smoke", num_slots=4)  # pos_freqs_xyz = 3
    cfg = base_cfg.replace(bg_pos_freqs_xyz=1)
    torch.manual_seed(0)
    full = build_fields(base_cfg)
    low = build_fields(cfg)
    low.load_state_dict(full.state_dict())
    slots = torch.randn(2, 4, base_cfg.slot_dim)
    x = torch.rand(2, 1, 50, 3) * 2 - 1
    gx = positional_encoding(x, 3)
    gd = positional_encoding(torch.nn.functional.normalize(torch.randn(2, 1, 50, 3), dim=-1), 1)
    s_full, c_full = full.eval_fields(full.params(slots), gx, gd)
    s_low, c_low = low.eval_fields(low.params(slots), gx, gd)
    # foreground slots: bit-identical; background slot: changed
    assert torch.equal(s_full[:, :3], s_low[:, :3]) and torch.equal(c_full[:, :3], c_low[:, :3])
    assert not torch.allclose(s_full[:, 3], s_low[:, 3])
    # the background field no longer depends on the high-frequency inputs at all
    gx2 = gx.clone()
    gx2[..., 6:12] = torch.randn_like(gx2[..., 6:12])  # sin of frequencies 1, 2
    gx2[..., 15:] = torch.randn_like(gx2[..., 15:])  # cos of frequencies 1, 2
    s2, c2 = low.eval_fields(low.params(slots), gx2, gd)
    assert torch.equal(s2[:, 3], s_low[:, 3]) and torch.equal(c2[:, 3], c_low[:, 3])
    assert not torch.equal(s2[:, 0], s_low[:, 0])
    # validation, and run keys unchanged while off
    with pytest.raises(ValueError, match="bg_pos_freqs_xyz"):
        base_cfg.replace(bg_pos_freqs_xyz=3)
    with pytest.raises(ValueError, match="hypernetwork"):
        base_cfg.replace(bg_pos_freqs_xyz=1, hypernetwork=False)
    assert "bg_pos_freqs_xyz" not in base_cfg.to_dict()
    assert cfg.to_dict()["bg_pos_freqs_xyz"] == 1
    assert ModelConfig.from_dict(cfg.to_dict()) == cfg
    # a whole model trains a step with it (gradients reach the hypernetwork)
    model = SVORF(model_config("smoke", num_slots=4, bg_pos_freqs_xyz=1))
    o = torch.tensor([[-6.0, 0.0, 1.0]]).expand(1, 8, 3).contiguous()
    d = torch.nn.functional.normalize(torch.randn(1, 8, 3) + torch.tensor([1.0, 0, -0.1]), dim=-1)
    out = model(torch.rand(1, 3, 32, 32), o, d)
    out.rgb.sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_svorf_train_cpu_scale_is_the_benchmark_cpu_model():
    """``svorf train --scale cpu --preset P`` and ``benchmark --scale cpu`` build one model."""
    from benchmark import adapter
    from svorf.train import CPU_RECIPE_PRESETS, run_configs

    for preset in ("clevr567", "clevr567-heldout", "room-chair", "room-diverse"):
        m_svorf, t_svorf = run_configs("cpu", preset)
        m_bench, t_bench = adapter.base_configs("cpu", preset)
        assert m_svorf == m_bench and t_svorf == t_bench, preset
        assert (m_svorf.slot_locality is not None) == (preset in CPU_RECIPE_PRESETS)
    assert run_configs("cpu", "clevr567") == recipe_configs("clevr567")
    plain, _ = run_configs("cpu", "clevr567", recipe=False)
    assert plain.slot_locality is None and plain.fg_box is None


def test_cosine_lr_decay_follows_steps_or_the_wall_budget():
    from svorf.train import TrainConfig, lr_at

    cfg = TrainConfig(steps=1000, lr=1e-3, warmup=10, lr_decay="cosine", lr_final_ratio=0.1)
    assert lr_at(cfg, 4) == pytest.approx(5e-4)  # warm-up unchanged
    assert lr_at(cfg, 500) == pytest.approx(1e-3 * (0.1 + 0.9 * 0.5))
    assert lr_at(cfg, 10, progress=1.0) == pytest.approx(1e-4)
    assert lr_at(cfg, 10, progress=0.0) == pytest.approx(1e-3)
    flat = cfg.replace(lr_decay="none")
    assert lr_at(flat, 999) == lr_at(flat, 10, progress=1.0) == 1e-3
    with pytest.raises(ValueError, match="lr_decay"):
        TrainConfig(lr_decay="step")


def test_late_cosine_keeps_the_rate_until_its_start():
    from svorf.train import TrainConfig, lr_at

    cfg = TrainConfig(
        steps=1000, lr=1e-3, warmup=10, lr_decay="cosine", lr_final_ratio=0.1, lr_decay_from=0.8
    )
    assert lr_at(cfg, 500) == lr_at(cfg, 800) == pytest.approx(1e-3)
    assert lr_at(cfg, 900) == pytest.approx(1e-3 * (0.1 + 0.9 * 0.5))
    assert lr_at(cfg, 10, progress=0.9) == pytest.approx(lr_at(cfg, 900))
    assert lr_at(cfg, 999, progress=1.0) == pytest.approx(1e-4)
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg
    assert "lr_decay_from" not in cfg.replace(lr_decay_from=0.0).to_dict()
    with pytest.raises(ValueError, match="lr_decay_from.*cosine"):
        TrainConfig(lr_decay_from=0.8)
    with pytest.raises(ValueError, match=r"lr_decay_from must be a progress in \[0, 1\)"):
        TrainConfig(lr_decay="cosine", lr_decay_from=1.0)
