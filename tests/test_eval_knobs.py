"""Evaluation-only speed knobs of the model ("early termination of opaque rays at
evaluation", fine samples only where the coarse weights are non-negligible):
``ModelConfig.eval_early_stop`` and ``ModelConfig.eval_fine_min_weight``; and the reading
of masks from the largest-weight sample, ``ModelConfig.eval_mask_rule``.

Off is the exact path; on stays within a stated tolerance of it on a small random model
(whose init densities make rays opaque within the box, so early termination does skip
samples); slot_probs stay a distribution; nothing is NaN; training never sees the knobs.
Their time-vs-error curve on trained weights is ``benchmark run tradeoff`` (render curve).
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

import svorf.march as march_mod
from svorf.config import ModelConfig, model_config
from svorf.model import SVORF

#: Stated tolerances on the smoke model below (colour units / world units / probability).
#: eval_early_stop=t bounds the skipped colour by about t per pass (ModelConfig docstring).
TOL_STOP = {"rgb": 0.02, "depth": 0.05, "probs": 0.02}
TOL_MINW = {"rgb": 0.05, "depth": 0.3, "probs": 0.05}


def _setup(num_slots: int = 4, rays: int = 96, seed: int = 0):
    torch.manual_seed(seed)
    cfg = model_config("smoke", num_slots=num_slots)
    model = SVORF(cfg).eval()
    imgs = torch.rand(2, 3, 32, 32)
    o = torch.tensor([0.0, -12.0, 6.0]).expand(2, rays, 3)
    d = F.normalize(-o + 0.3 * torch.randn(2, rays, 3), dim=-1)
    with torch.no_grad():
        slots = model.encode(imgs)
    return cfg, model, slots, o, d


def _with(model: SVORF, **knobs) -> SVORF:
    m = SVORF(model.cfg.replace(**knobs)).eval()
    m.load_state_dict(model.state_dict())
    return m


def _errors(a, b) -> dict[str, float]:
    return {
        "rgb": float((a.rgb - b.rgb).abs().max()),
        "depth": float((a.depth - b.depth).abs().mean()),
        "probs": float((a.slot_probs - b.slot_probs).abs().max()),
    }


def _check_distribution(out, slot_mask=None) -> None:
    for x in (out.rgb, out.depth, out.acc, out.slot_probs, out.coarse_rgb):
        assert torch.isfinite(x).all()
    s = out.slot_probs.sum(-1)
    assert (out.slot_probs >= 0).all()
    assert torch.allclose(s, torch.ones_like(s), atol=1e-5)
    assert (out.acc <= 1 + 1e-5).all()
    if slot_mask is not None:
        assert (out.slot_probs[~slot_mask[:, None].expand_as(out.slot_probs)] == 0).all()


def test_defaults_off_and_not_saved():
    cfg = model_config("smoke")
    assert cfg.eval_early_stop is None and cfg.eval_fine_min_weight is None
    d = cfg.to_dict()  # off: not written, so run keys of earlier runs stay valid
    assert "eval_early_stop" not in d and "eval_fine_min_weight" not in d
    on = cfg.replace(eval_early_stop=0.01, eval_fine_min_weight=0.05)
    assert ModelConfig.from_dict(on.to_dict()) == on
    assert ModelConfig.from_dict(d) == cfg


@pytest.mark.parametrize("name", ["eval_early_stop", "eval_fine_min_weight"])
@pytest.mark.parametrize("bad", [0.0, 1.0, -0.1, 2.0])
def test_bad_values_name_the_field(name, bad):
    with pytest.raises(ValueError, match=name):
        model_config("smoke", **{name: bad})


def test_off_is_bit_identical():
    _, model, slots, o, d = _setup()
    base = model.render_chunked(slots, o, d)
    again = _with(model, eval_early_stop=None, eval_fine_min_weight=None).render_chunked(
        slots, o, d
    )
    for n in ("rgb", "depth", "acc", "slot_probs", "coarse_rgb"):
        assert torch.equal(getattr(base, n), getattr(again, n)), n


def test_training_path_ignores_the_knobs():
    """With gradients or perturbed samples the knobs are off: the training forward is
    bit-identical to the model without them."""
    _, model, slots, o, d = _setup()
    on = _with(model, eval_early_stop=0.5, eval_fine_min_weight=0.5)
    for perturb in (False, True):
        torch.manual_seed(1)
        a = model.render_rays(slots, o, d, perturb=perturb)
        torch.manual_seed(1)
        b = on.render_rays(slots, o, d, perturb=perturb)
        assert torch.equal(a.rgb, b.rgb) and torch.equal(a.slot_probs, b.slot_probs)
    with torch.no_grad():  # evaluation, but perturbed samples: still off
        torch.manual_seed(2)
        a = model.render_rays(slots, o, d, perturb=True)
        torch.manual_seed(2)
        b = on.render_rays(slots, o, d, perturb=True)
    assert torch.equal(a.rgb, b.rgb)


def _count_evaluated(monkeypatch) -> list[float]:
    seen: list[float] = []
    orig = march_mod.RayMarcher.query_subset

    def spy(self, ctx, t, keep):
        seen.append(float(keep.float().mean()))
        return orig(self, ctx, t, keep)

    monkeypatch.setattr(march_mod.RayMarcher, "query_subset", spy)
    return seen


@pytest.mark.parametrize("stop", [1e-3, 1e-2])
def test_early_stop_skips_samples_within_tolerance(stop, monkeypatch):
    _, model, slots, o, d = _setup()
    base = model.render_chunked(slots, o, d)
    seen = _count_evaluated(monkeypatch)
    out = _with(model, eval_early_stop=stop).render_chunked(slots, o, d)
    assert min(seen) < 1.0  # some samples were not evaluated
    err = _errors(out, base)
    assert all(err[k] <= TOL_STOP[k] for k in err), err
    _check_distribution(out)


def test_early_stop_error_grows_with_the_threshold():
    _, model, slots, o, d = _setup()
    base = model.render_chunked(slots, o, d)
    errs = [
        _errors(_with(model, eval_early_stop=s).render_chunked(slots, o, d), base)["rgb"]
        for s in (1e-3, 0.1, 0.5)
    ]
    assert errs[0] <= errs[1] <= errs[2] and errs[2] > 0


def test_fine_min_weight_within_tolerance(monkeypatch):
    _, model, slots, o, d = _setup()
    base = model.render_chunked(slots, o, d)
    seen = _count_evaluated(monkeypatch)
    out = _with(model, eval_fine_min_weight=0.2).render_chunked(slots, o, d)
    assert min(seen) < 1.0
    err = _errors(out, base)
    assert all(err[k] <= TOL_MINW[k] for k in err), err
    _check_distribution(out)


def test_fine_min_weight_dropping_every_fine_sample_is_the_coarse_render():
    """A dropped fine sample is a zero-length duplicate of its bin's coarse sample: with
    every one dropped, the fine render equals the coarse render."""
    _, model, slots, o, d = _setup()
    out = _with(model, eval_fine_min_weight=0.999).render_chunked(slots, o, d)
    assert torch.allclose(out.rgb, out.coarse_rgb, atol=1e-6)
    with torch.no_grad():
        coarse_only = _with(model, n_fine=0).render_rays(slots, o, d)
    assert torch.allclose(out.depth, coarse_only.depth, atol=1e-4)
    assert torch.allclose(out.slot_probs, coarse_only.slot_probs, atol=1e-5)


def test_both_knobs_with_a_slot_mask_and_chunks():
    _, model, slots, o, d = _setup(num_slots=5)
    mask = torch.tensor([[True, False, True, True, True], [True, True, False, True, True]])
    base = model.render_chunked(slots, o, d, chunk=40, slot_mask=mask)
    out = _with(model, eval_early_stop=1e-2, eval_fine_min_weight=0.05).render_chunked(
        slots, o, d, chunk=40, slot_mask=mask
    )
    _check_distribution(out, mask)
    err = _errors(out, base)
    assert all(err[k] <= TOL_MINW[k] for k in err), err


def test_opaque_at_the_first_sample_no_nan():
    """Densities at the bound (sigma_max) everywhere: every ray stops after the first
    segment; nothing is NaN and the colour equals the exact render's."""
    _, model, slots, o, d = _setup()
    with torch.no_grad():
        for p in model.fields.parameters():
            p.mul_(30.0)
    base = model.render_chunked(slots, o, d)
    out = _with(model, eval_early_stop=1e-3, eval_fine_min_weight=0.1).render_chunked(slots, o, d)
    _check_distribution(out)
    assert torch.isfinite(base.rgb).all()
    assert float((out.rgb - base.rgb).abs().max()) <= TOL_MINW["rgb"]


def test_packed_query_equals_the_dense_one_at_kept_samples():
    """RayMarcher.query_subset packs the kept samples of each scene into pseudo-rays: their values
    equal the dense query's; the others are 0."""
    cfg, model, slots, o, d = _setup(rays=16)
    B, R, N = 2, 16, 6
    t = torch.linspace(7.0, 17.0, N).expand(B, R, N).contiguous()
    keep = torch.rand(B, R, N, generator=torch.Generator().manual_seed(3)) < 0.4
    keep[1] = False  # a scene with nothing kept: padding only
    keep[1, 0, 0] = True
    with torch.no_grad():
        is_bg = torch.zeros(B, cfg.num_slots, dtype=torch.bool)
        is_bg[:, -1] = True
        ctx = model.query_context(slots, model.fields.params(slots), o, d, None, is_bg)
        dense = model._query(ctx, t)
        part = march_mod.RayMarcher.from_config(model._query, cfg, True).query_subset(ctx, t, keep)
    for name in ("sigma", "rgb", "m"):
        a, b = getattr(part, name), getattr(dense, name)
        k = keep if name == "sigma" else keep[..., None]
        assert torch.allclose(a, torch.where(k, b, torch.zeros_like(b)), atol=1e-5), name
    sk = torch.where(keep[:, None], dense.sigma_k, torch.zeros_like(dense.sigma_k))
    assert torch.allclose(part.sigma_k, sk, atol=1e-5)


def test_knobs_with_object_transforms():
    """The edit path (moved objects) goes through the same packed queries."""
    _, model, slots, o, d = _setup(num_slots=4, rays=32)
    tf = torch.eye(4).expand(2, 4, 4, 4).clone()
    tf[:, 0, 0, 3] = 0.5  # move slot 0 along x
    base = model.render_chunked(slots, o, d, object_transforms=tf)
    out = _with(model, eval_early_stop=1e-3, eval_fine_min_weight=0.05).render_chunked(
        slots, o, d, object_transforms=tf
    )
    _check_distribution(out)
    err = _errors(out, base)
    assert all(err[k] <= TOL_MINW[k] for k in err), err


def test_peak_mask_rule_hand_example():
    """A half-transparent rind of object matter in front of the floor: the composite masks
    give the pixel to the object (0.55 of the weight), the peak rule to the floor (its
    one sample outweighs each of the rind's)."""
    obj, bg = torch.tensor([1.0, 0.0]), torch.tensor([0.0, 1.0])
    w = torch.tensor([[[0.2, 0.2, 0.15, 0.4, 0.0]]])
    m = torch.stack([obj, obj, obj, bg, bg])[None, None]  # [1, 1, 5, 2]
    acc = w.sum(-1)
    comp = march_mod.ray_slot_probs(w, m, acc)
    assert torch.allclose(comp, torch.tensor([[[0.55 / 0.95, 0.4 / 0.95]]]), atol=1e-5)
    assert torch.equal(march_mod.ray_slot_probs(w, m, acc, "composite"), comp)
    peak = march_mod.ray_slot_probs(w, m, acc, "peak")
    assert torch.allclose(peak, bg[None, None], atol=1e-5)
    empty = torch.zeros_like(w)  # no weight: the mean mask in both forms
    for rule in (None, "peak"):
        p = march_mod.ray_slot_probs(empty, m, empty.sum(-1), rule)
        assert torch.allclose(p, m.mean(dim=2), atol=1e-6)


def test_peak_background_rule_hand_example():
    """The peak sample decides background against object, the weighted masks which object:
    a rind in front of the floor goes to the floor; a ray whose peak sample is an object's
    keeps the paper's split between the objects."""
    a, b, bg = torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]), torch.eye(3)[2]
    is_bg = torch.tensor([[False, False, True]])
    w = torch.tensor([[[0.2, 0.2, 0.15, 0.4, 0.0], [0.3, 0.25, 0.2, 0.1, 0.0]]])
    m = torch.stack([torch.stack([a, a, a, bg, bg]), torch.stack([a, b, b, bg, bg])])[None]
    acc = w.sum(-1)
    out = march_mod.ray_slot_probs(w, m, acc, "peak_background", is_bg)
    assert torch.allclose(out[0, 0], bg, atol=1e-5)  # the floor's sample is the peak
    comp = march_mod.ray_slot_probs(w, m, acc)
    assert torch.equal(out[0, 1], comp[0, 1])  # object a's sample is the peak: as the paper
    assert out[0, 1].argmax() == 1  # ... so object b, with more of the weight, keeps it
    with pytest.raises(ValueError, match="needs is_bg"):
        march_mod.ray_slot_probs(w, m, acc, "peak_background")


@pytest.mark.parametrize("rule", ["peak", "peak_background"])
def test_peak_mask_rules_change_only_the_masks_and_only_at_evaluation(rule):
    _, model, slots, o, d = _setup()
    base = model.render_chunked(slots, o, d)
    on = _with(model, eval_mask_rule=rule)
    out = on.render_chunked(slots, o, d)
    for n in ("rgb", "depth", "acc", "coarse_rgb"):
        assert torch.equal(getattr(base, n), getattr(out, n)), n
    _check_distribution(out)
    if rule == "peak":
        assert not torch.allclose(out.slot_probs, base.slot_probs)
    else:  # each pixel read as the paper reads it or as the peak rule does
        peak = _with(model, eval_mask_rule="peak").render_chunked(slots, o, d).slot_probs
        same = (out.slot_probs == base.slot_probs).all(-1)
        assert torch.equal(out.slot_probs[~same], peak[~same])
    torch.manual_seed(1)
    a = model.render_rays(slots, o, d, perturb=True)  # training: the paper's masks
    torch.manual_seed(1)
    b = on.render_rays(slots, o, d, perturb=True)
    assert torch.equal(a.slot_probs, b.slot_probs)
    cfg = model.cfg
    assert "eval_mask_rule" not in cfg.to_dict()
    assert ModelConfig.from_dict(on.cfg.to_dict()) == on.cfg
    with pytest.raises(ValueError, match="eval_mask_rule"):
        model_config("smoke", eval_mask_rule="surface")
