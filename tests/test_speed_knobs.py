"""Speed knobs of ModelConfig: each changes results only within its stated
tolerance, or not at all where it should be exact (svorf.field.eval_pairs, the folded
composer, svorf.model slot selection, bf16 autocast, fg_box, benchmark.tools.speedbench).

Stated tolerances (checked here; measured values at cpu scale in the speedbench report):
- folded composer (always on, not a knob) vs the paper-form reference: float32 precision
  (both run the attention softmax in float32; float64 parameters agree to 1e-5).
- sparse pair evaluation (fg_box, masked slots, any selection): exact, i.e. equal to the dense
  evaluation times the selection up to float summation order (its float32 output within 1e-6
  of the float64 per-slot reference; gradients equal); with fg_box, model outputs equal the
  dense-and-zero path within 1e-5.
- fg_box that contains the whole sampled box: bit-identical to fg_box=None.
- bf16_autocast vs float32, same weights, cpu-scale model at init: rgb max |diff| <= 1e-2,
  depth mean |diff| <= 1e-2 world units, slot_probs max |diff| <= 1e-2 (measured ~2e-3);
  transmittance, sampling and distortion cumsums all run in float32.
- enc_bf16 (the encoder's CNN in bf16 too) with bf16_autocast vs float32, same weights, cpu
  scale at init: rgb max <= 1e-2, depth mean <= 1e-2, slot_probs max <= 2e-2; with
  bf16_autocast off it is bit-identical to float32.
- slot_topk / slot_keep_mass, per sample point: |rgb - rgb_full| <= 1 - M and
  |sigma - sigma_full| <= (1 - M) max_k sigma_k, M = mass of the evaluated slots
  (slot_keep_mass=0.99 gives 1 - M <= 0.01 everywhere); one-hot masks: exact (1e-5).
- slot_keep_mass=0.99 on a model with sharp masks (composition logits x8): rendered rgb max
  |diff| <= 1e-2, depth mean <= 1e-2, slot_probs max <= 1e-2 (measured ~2e-3).
- the cpu defaults together (bf16 + slot_keep_mass=0.99), flat or sharp masks: rgb max
  <= 1e-2, depth mean <= 1e-2, slot_probs max <= 3e-2 (measured 4e-3 / 1e-3 / 1.3e-2). Fixed
  slot_topk at initialisation (m nearly uniform, top-2 of 8 keep ~47% of the mass) is NOT
  within these: rgb max ~0.1 at cpu scale, which is why it is off by default.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from benchmark.tools import speedbench
from svorf.config import ModelConfig, model_config
from svorf.field import HyperNetwork, SlotConditionedMLP, positional_encoding, sparse_tile_rows
from svorf.model import SVORF, RenderOutput

KNOBS_OFF = speedbench.KNOBS_OFF


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    # 2 shared cores: oversubscribed intra-op threads make tiny ops 10-50x slower.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def make_rays(B: int, R: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    o = torch.tensor([0.0, -10.0, 6.0]).expand(B, R, 3).clone()
    target = (torch.rand(B, R, 3, generator=g) - 0.5) * 6.0
    return o, F.normalize(target - o, dim=-1)


def make_images(B: int, size: int = 32, seed: int = 0) -> torch.Tensor:
    return torch.rand(B, 3, size, size, generator=torch.Generator().manual_seed(seed))


def model_pair(scale="smoke", sharpen=1.0, num_slots=4, base=None, **knobs):
    """(model with the knobs, the same weights with every knob off), eval mode."""
    out = []
    for kw in ({**KNOBS_OFF, **knobs}, KNOBS_OFF):
        torch.manual_seed(0)
        m = SVORF(model_config(scale, num_slots=num_slots, **{**(base or {}), **kw}))
        if sharpen != 1.0:
            with torch.no_grad():
                m.composer.a_s.weight.mul_(sharpen)
                m.composer.a_s.bias.mul_(sharpen)
        out.append(m.eval())
    return out[0], out[1]


def assert_finite(out: RenderOutput) -> None:
    for name in ("rgb", "depth", "acc", "slot_probs", "connectivity", "coarse_rgb"):
        v = getattr(out, name)
        assert v is None or torch.isfinite(v).all(), name


def query_pair(model, ref, B=2, R=16, N=8, seed=0, transforms=None):
    """_query of both models at the same samples (so per-point values can be compared)."""
    slots = ref.encode(make_images(B, model.cfg.image_size, seed))
    o, d = make_rays(B, R, seed)
    K = slots.shape[1]
    is_bg = torch.zeros(B, K, dtype=torch.bool)
    is_bg[:, -1] = True
    t = torch.sort(
        torch.rand(B, R, N, generator=torch.Generator().manual_seed(seed)) * 8 + 8
    ).values
    inv = None if transforms is None else torch.linalg.inv(transforms)
    qs = []
    for m in (model, ref):
        ctx = m.query_context(slots, m.fields.params(slots), o, d, None, is_bg, inv)
        qs.append(m._query(ctx, t))
    return qs


# ----------------------------------------------------------------------------- sparse pairs


@pytest.mark.parametrize("hyper", [True, False])
def test_eval_pairs_equals_dense_times_selection(hyper):
    cfg = model_config("smoke", num_slots=3, hypernetwork=hyper)
    torch.manual_seed(0)
    fields = (HyperNetwork if hyper else SlotConditionedMLP)(cfg).double()
    g = torch.Generator().manual_seed(1)
    B, K, P = 2, 3, 37
    for Kx in (1, K):
        gx = torch.randn(B, Kx, P, fields.in_x, generator=g, dtype=torch.float64)
        gd = torch.randn(B, Kx, P, fields.in_d, generator=g, dtype=torch.float64)
        sel_random = torch.rand(B, K, P, generator=g) < 0.4
        sel_random[0, 1] = False  # an empty (scene, slot) group
        sel_random[1, 2] = True  # a full one
        for sel in (
            sel_random,
            torch.zeros(B, K, P, dtype=torch.bool),
            torch.ones(B, K, P, dtype=torch.bool),
        ):
            slots = torch.randn(B, K, cfg.slot_dim, dtype=torch.float64, requires_grad=True)
            p = fields.params(slots)
            s, c = fields.eval_pairs(p, gx, gd, sel)
            s_ref, c_ref = fields.eval_reference(p, gx, gd)
            assert s.dtype == torch.float32 and s.shape == (B, K, P) and c.shape == (B, K, P, 3)
            torch.testing.assert_close(s.double(), s_ref * sel, atol=1e-6, rtol=1e-6)
            torch.testing.assert_close(c.double(), c_ref * sel[..., None], atol=1e-6, rtol=1e-6)
            assert torch.all(s[~sel] == 0) and torch.all(c[~sel] == 0)
            # gradients reach exactly the selected pairs' parameters
            if sel.any():
                (s.sum() + c.sum()).backward()
                g_sparse = slots.grad.clone()
                slots.grad = None
                s2, c2 = fields.eval_fields(fields.params(slots), gx, gd)
                ((s2 * sel).sum() + (c2 * sel[..., None]).sum()).backward()
                torch.testing.assert_close(g_sparse, slots.grad, atol=1e-5, rtol=1e-4)
    with pytest.raises(ValueError, match="eval_pairs"):
        fields.eval_pairs(p, gx[:, :, :5], gd, sel_random)


def test_sparse_tile_rows_is_a_bounded_power_of_two():
    for n, g in [(1, 1), (10, 32), (32768, 32), (10**7, 4), (0, 0)]:
        s = sparse_tile_rows(n, g)
        assert 32 <= s <= 256 and s & (s - 1) == 0
    assert sparse_tile_rows(8192, 32) == 64 and sparse_tile_rows(32768, 32) == 256


def test_sparse_and_dense_paths_of_eval_slots_agree():
    """Above _DENSE_ABOVE kept pairs the dense evaluation is used: same result either way."""
    model, _ = model_pair()
    slots = model.encode(make_images(2))
    p = model.fields.params(slots)
    x = (torch.rand(2, 1, 30, 3) - 0.5) * 6
    gx = positional_encoding(x / model.cfg.box_half, model.cfg.pos_freqs_xyz)
    gd = positional_encoding(F.normalize(torch.randn(2, 1, 30, 3), dim=-1), model.cfg.pos_freqs_dir)
    for frac in (0.3, 0.95):
        keep = torch.rand(2, 30, 4, generator=torch.Generator().manual_seed(2)) < frac
        s, c = model._eval_slots(p, gx, gd, keep)
        sel = keep.transpose(1, 2)
        s_sparse, c_sparse = model.fields.eval_pairs(p, gx, gd, sel)
        torch.testing.assert_close(s, s_sparse, atol=1e-6, rtol=1e-5)
        torch.testing.assert_close(c, c_sparse, atol=1e-6, rtol=1e-5)


def test_count_pairs_counts_the_kept_pairs():
    """SVORF.count_pairs: every (point, slot) pair without a selection, the kept ones with."""
    model, _ = model_pair()
    slots = model.encode(make_images(2))
    p = model.fields.params(slots)
    x = (torch.rand(2, 1, 30, 3) - 0.5) * 6
    gx = positional_encoding(x / model.cfg.box_half, model.cfg.pos_freqs_xyz)
    gd = positional_encoding(F.normalize(torch.randn(2, 1, 30, 3), dim=-1), model.cfg.pos_freqs_dir)
    assert model.pair_count is None  # off until asked for
    counts = model.count_pairs()
    assert model.count_pairs() is counts and counts.fraction == 0.0
    keep = torch.zeros(2, 30, 4, dtype=torch.bool)
    keep[:, :, :1] = True
    model._eval_slots(p, gx, gd, keep)
    assert (counts.kept, counts.total) == (60.0, 240.0) and counts.fraction == 0.25
    model._eval_slots(p, gx, gd, None)
    assert (counts.kept, counts.total) == (300.0, 480.0)
    counts.reset()
    assert (counts.kept, counts.total, counts.fraction) == (0.0, 0.0, 0.0)


# ----------------------------------------------------------------------------- composer


def test_folded_composer_equals_paper_form():
    """D^c + D^a folded into per-scene matrices == q/k/v attention + a_z/a_s (float64)."""
    from svorf.compose import SlotGuidedComposer
    from svorf.field import encoding_dim

    cfg = model_config("cpu", num_slots=6)
    cx = encoding_dim(cfg.pos_freqs_xyz)
    torch.manual_seed(0)
    comp = SlotGuidedComposer(cfg, cx).double()
    with torch.no_grad():
        for prm in comp.parameters():  # non-zero biases too
            prm.normal_(0.0, 0.3)
    g = torch.Generator().manual_seed(0)
    slots = torch.randn(2, 6, cfg.slot_dim, dtype=torch.float64, generator=g, requires_grad=True)
    valid = torch.rand(2, 30, 6, generator=g) < 0.6
    valid[..., -1] = True
    for gx, vmask in [
        (torch.randn(2, 30, cx, dtype=torch.float64, generator=g), None),
        (torch.randn(2, 30, cx, dtype=torch.float64, generator=g), valid),
        (torch.randn(2, 6, 30, cx, dtype=torch.float64, generator=g), valid[:, :1]),
    ]:
        got = comp.logits(gx, slots, vmask)
        ref = comp.logits_reference(gx, slots, vmask)
        assert got.shape == ref.shape == (2, 30, 6)
        # the attention softmax runs in float32 in both: agreement to float32 precision
        torch.testing.assert_close(got, ref, atol=1e-5, rtol=1e-5)
        (ga,) = torch.autograd.grad(got.square().sum(), slots)
        (gr,) = torch.autograd.grad(ref.square().sum(), slots)
        torch.testing.assert_close(ga, gr, atol=1e-4, rtol=1e-4)
        m = comp(gx, slots, vmask)
        torch.testing.assert_close(m.sum(-1), torch.ones(2, 30, dtype=torch.float32))
        if vmask is not None:
            assert torch.all(m[~vmask.expand_as(m)] == 0)


# ----------------------------------------------------------------------------- fg_box


def test_fg_box_around_the_whole_box_is_bit_identical():
    # clip_to_box keeps every sample in +-4.5, so fg_box=5 removes nothing.
    model, ref = model_pair(fg_box=5.0)
    imgs = make_images(2)
    o, d = make_rays(2, 16)
    a, b = model(imgs, o, d), ref(imgs, o, d)
    for name in ("rgb", "depth", "acc", "slot_probs", "connectivity", "coarse_rgb"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


@pytest.mark.parametrize("composition", ["slot_guided", "density_weighted"])
def test_fg_box_sparse_model_matches_dense_masked(composition, monkeypatch):
    """The model with fg_box computes only in-box foreground pairs, same result as zeroing."""
    import svorf.pairs as sp

    model, _ = model_pair(fg_box=1.5, base={"composition": composition})
    imgs = make_images(2)
    o, d = make_rays(2, 24)
    sparse = model(imgs, o, d)
    monkeypatch.setattr(sp, "_DENSE_ABOVE", -1.0)  # force dense evaluation + zeroing
    dense = model(imgs, o, d)
    for name in ("rgb", "depth", "slot_probs", "connectivity"):
        torch.testing.assert_close(
            getattr(sparse, name), getattr(dense, name), atol=1e-5, rtol=1e-4
        )


# ----------------------------------------------------------------------------- bf16


def test_hypernetwork_output_layer_keeps_no_bf16_weight_copy_and_is_bit_identical():
    """Under bf16 autocast the hypernetwork's output layer (a [n_params, D] weight for only
    B*K rows) keeps its float32 weight for backward instead of a bf16 copy (2.7 MB per step
    at cpu scale); values and gradients equal nn.Linear under autocast bit for bit."""
    from svorf.field import _linear_autocast_recast

    torch.manual_seed(0)
    cfg = model_config("cpu", bf16_autocast=True)
    model = SVORF(cfg)
    head = model.fields.head
    slots = torch.randn(2, cfg.num_slots, cfg.slot_dim, requires_grad=True)
    gy = torch.randn(2, cfg.num_slots, head.weight.shape[0])
    runs = []
    for fn in (head, lambda x: _linear_autocast_recast(x, head)):
        saved: list[tuple[tuple[int, ...], torch.dtype]] = []

        def pack(t, saved=saved):
            saved.append((tuple(t.shape), t.dtype))
            return t

        with (
            torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t),
            model._autocast(slots.device),
        ):
            y = fn(model.fields.norm(slots))
        (y.float() * gy).sum().backward()
        runs.append((saved, [y.detach(), slots.grad, head.weight.grad, head.bias.grad]))
        slots.grad = None
        model.zero_grad(set_to_none=True)
    bf16_w = {
        (tuple(head.weight.shape), torch.bfloat16),
        (tuple(head.weight.T.shape), torch.bfloat16),
    }
    assert bf16_w & set(runs[0][0])  # nn.Linear under autocast keeps the bf16 copy
    assert not bf16_w & set(runs[1][0])
    for a, b in zip(runs[0][1], runs[1][1], strict=True):
        assert a.dtype == b.dtype and torch.equal(a, b)
    # the model uses it; float32 models go through the plain nn.Linear
    assert model.slot_params(slots).head_b.dtype == torch.bfloat16
    fp32 = SVORF(model_config("cpu", bf16_autocast=False))
    assert fp32.slot_params(slots).head_b.dtype == torch.float32


def test_bf16_within_tolerance_at_cpu_scale_and_float32_cumsums(monkeypatch):
    model, ref = model_pair("cpu", num_slots=8, bf16_autocast=True)
    imgs = make_images(2, 64)
    o, d = make_rays(2, 64)
    dtypes = []
    real_cumsum = torch.cumsum

    def spy(x, *a, **kw):
        dtypes.append(x.dtype)
        return real_cumsum(x, *a, **kw)

    monkeypatch.setattr(torch, "cumsum", spy)
    with torch.no_grad():
        a = model(imgs, o, d)
    monkeypatch.undo()
    b = ref(imgs, o, d)
    assert dtypes and all(dt in (torch.float32, torch.int64) for dt in dtypes), dtypes
    assert_finite(a)
    assert a.rgb.dtype == a.depth.dtype == a.slot_probs.dtype == torch.float32
    rgb_err = (a.rgb - b.rgb).abs().max().item()
    assert 0 < rgb_err <= 1e-2
    assert (a.depth - b.depth).abs().mean().item() <= 1e-2
    assert (a.slot_probs - b.slot_probs).abs().max().item() <= 1e-2


def test_enc_bf16_within_tolerance_and_only_where_bf16_is_on():
    """enc_bf16: the encoder's CNN runs in bf16 where bf16_autocast is on and hands the slot
    decoder a float32 map; within the bf16 tolerances of the whole model; bit-identical to
    float32 where bf16_autocast is off; left out of the config dict while off."""
    model, ref = model_pair("cpu", num_slots=8, bf16_autocast=True, enc_bf16=True)
    dtypes = []
    model.encoder.up3.register_forward_hook(lambda m, i, o: dtypes.append(o.dtype))
    imgs = make_images(2, 64)
    o, d = make_rays(2, 64)
    with torch.no_grad():
        feats = []
        hook = model.slot_module.register_forward_pre_hook(lambda m, a: feats.append(a[0]))
        a = model(imgs, o, d)
        hook.remove()
        b = ref(imgs, o, d)
    assert dtypes == [torch.bfloat16] and feats[0].dtype == torch.float32
    assert_finite(a)
    assert 0 < (a.rgb - b.rgb).abs().max().item() <= 1e-2
    assert (a.depth - b.depth).abs().mean().item() <= 1e-2
    assert (a.slot_probs - b.slot_probs).abs().max().item() <= 2e-2
    # gradients reach the float32 encoder weights, finite
    a = model.train()(imgs, o, d)
    a.rgb.square().mean().backward()
    g = model.encoder.stem[0].weight.grad
    assert (
        g is not None and g.dtype == torch.float32 and torch.isfinite(g).all() and g.abs().sum() > 0
    )
    # bf16_autocast off: enc_bf16 changes nothing, bit for bit
    off, ref = model_pair("cpu", num_slots=8, enc_bf16=True)
    with torch.no_grad():
        assert torch.equal(off(imgs, o, d).rgb, ref(imgs, o, d).rgb)
    assert "enc_bf16" not in ref.cfg.to_dict() and off.cfg.to_dict()["enc_bf16"] is True


# ----------------------------------------------------------------------------- slot selection


@pytest.mark.parametrize("knob", [{"slot_topk": 2}, {"slot_keep_mass": 0.9}])
def test_slot_selection_per_point_bound(knob):
    """|rgb - rgb_full| <= 1 - M, |sigma - sigma_full| <= (1 - M) max sigma_k at every point."""
    model, ref = model_pair(num_slots=6, **knob)
    q, qf = query_pair(model, ref)
    ms = torch.sort(qf.m, dim=-1, descending=True).values
    if "slot_topk" in knob:
        M = ms[..., :2].sum(-1)
    else:  # smallest prefix reaching the target mass
        before = torch.cumsum(ms, -1) - ms
        M = (ms * (before < 0.9)).sum(-1)
        assert (M >= 0.9 - 1e-6).all()
    assert (M < 0.999).any()  # the bound is not trivially met
    drop = (1 - M).clamp_min(0)
    sig_max = qf.sigma_k.amax(dim=1)  # [B, R, N]
    assert torch.all((q.rgb - qf.rgb).abs() <= drop[..., None] + 1e-5)
    assert torch.all((q.sigma - qf.sigma).abs() <= drop * sig_max + 1e-4)
    torch.testing.assert_close(q.m, qf.m)  # slot masks (and so slot_probs' m) untouched
    # fewer per-slot densities are non-zero: the dropped pairs were not evaluated
    assert (q.sigma_k == 0).sum() > 0 and (qf.sigma_k == 0).sum() == 0


@pytest.mark.parametrize("knob", [{"slot_topk": 1}, {"slot_keep_mass": 0.99}])
def test_slot_selection_exact_for_one_hot_masks(knob):
    """When one slot owns each point (m one-hot), evaluating only it changes nothing."""
    model, ref = model_pair(sharpen=1e4, **knob)
    imgs = make_images(2)
    o, d = make_rays(2, 16)
    a, b = model(imgs, o, d), ref(imgs, o, d)
    for name in ("rgb", "depth", "acc", "slot_probs", "coarse_rgb"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), atol=1e-5, rtol=1e-5)


def test_keep_mass_within_tolerance_on_sharp_masks():
    model, ref = model_pair("cpu", num_slots=8, sharpen=8.0, slot_keep_mass=0.99)
    imgs = make_images(2, 64)
    o, d = make_rays(2, 64)
    a, b = model(imgs, o, d), ref(imgs, o, d)
    assert_finite(a)
    assert (a.rgb - b.rgb).abs().max().item() <= 1e-2
    assert (a.depth - b.depth).abs().mean().item() <= 1e-2
    assert (a.slot_probs - b.slot_probs).abs().max().item() <= 1e-2
    torch.testing.assert_close(a.slot_probs.sum(-1), torch.ones(2, 64))


@pytest.mark.parametrize("sharpen", [1.0, 8.0])
def test_cpu_default_knobs_within_tolerance(sharpen):
    """model_config("cpu") (bf16 + slot_keep_mass=0.99) vs the same weights with every knob
    off, at initialisation (flat m) and with sharp masks."""
    cpu = model_config("cpu")
    knobs = {k: getattr(cpu, k) for k in KNOBS_OFF}
    model, ref = model_pair("cpu", num_slots=8, sharpen=sharpen, **knobs)
    imgs = make_images(2, 64)
    o, d = make_rays(2, 64)
    a, b = model(imgs, o, d), ref(imgs, o, d)
    assert_finite(a)
    assert (a.rgb - b.rgb).abs().max().item() <= 1e-2
    assert (a.depth - b.depth).abs().mean().item() <= 1e-2
    assert (a.slot_probs - b.slot_probs).abs().max().item() <= 3e-2


def test_topk_keeps_masks_transforms_and_gradients_sound():
    # clip_to_box off: moving the camera must not move the sampling interval.
    model, _ = model_pair(num_slots=5, base={"clip_to_box": False}, slot_topk=2, fg_box=2.5)
    slots = model.encode(make_images(2))
    o, d = make_rays(2, 16)
    ragged = torch.tensor([[True, False, True, True, True], [True, True, False, False, True]])
    out = model.render_rays(slots, o, d, slot_mask=ragged)
    assert_finite(out)
    assert torch.all(out.slot_probs[~ragged[:, None, :].expand_as(out.slot_probs)] == 0)
    torch.testing.assert_close(out.slot_probs.sum(-1), torch.ones(2, 16))
    # object transforms (per-slot points, Kx = K): moving every slot = moving the camera
    M = torch.eye(4)
    M[:3, 3] = torch.tensor([0.4, -0.2, 0.1])
    moved = model.render_rays(slots, o, d, object_transforms=M.expand(2, 5, 4, 4))
    cam = model.render_rays(slots, o - M[:3, 3], d)
    for name in ("rgb", "depth", "slot_probs"):
        torch.testing.assert_close(getattr(moved, name), getattr(cam, name), atol=1e-4, rtol=1e-4)
    # training: finite gradients everywhere
    model.train()
    out = model(make_images(2), o, d, perturb=True)
    total, _ = model.loss(out, torch.rand(2, 16, 3))
    total.backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert len(grads) > 0.9 * len(list(model.parameters()))
    assert all(torch.isfinite(g).all() for g in grads)


def test_training_with_knobs_lowers_loss():
    torch.manual_seed(0)
    model = SVORF(
        model_config("smoke", bf16_autocast=True, slot_keep_mass=0.99, slot_topk=2, fg_box=3.0)
    )
    imgs = make_images(2)
    o, d = make_rays(2, 64)
    target = torch.sigmoid(
        4 * d @ torch.tensor([[1.0, 0.0, -1.0], [0.5, 1.0, 0.0], [0.0, -1.0, 2.0]])
    )
    opt = torch.optim.Adam(model.parameters(), lr=2e-3)
    losses = []
    for _ in range(40):
        out = model(imgs, o, d, perturb=True)
        total, stats = model.loss(out, target)
        opt.zero_grad()
        total.backward()
        opt.step()
        losses.append(stats["mse"].item())
    assert all(map(math.isfinite, losses))
    assert sum(losses[-5:]) / 5 < 0.5 * losses[0]


def test_all_knobs_extreme_inputs_are_finite():
    model = SVORF(
        model_config(
            "smoke",
            num_slots=4,
            near=1.0,
            far=1e4,
            clip_to_box=False,
            sigma_max=1e6,
            bf16_autocast=True,
            slot_topk=2,
            slot_keep_mass=0.9,
            fg_box=2.0,
        )
    )
    model.fields.density = lambda raw: raw * 0 + 1e6  # every field fully opaque
    o, d = make_rays(2, 8)
    out = model(make_images(2), o * 100, d, perturb=True)
    assert_finite(out)
    total, _ = model.loss(out, torch.rand(2, 8, 3))
    total.backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


# ----------------------------------------------------------------------------- config


@pytest.mark.parametrize("native", [False, True])
def test_bf16_auto_follows_the_hardware(monkeypatch, native):
    """ "auto" = bf16 only where the CPU has it (torch emulates bf16 on AVX2: 3-5x slower);
    True / False force it either way."""
    import svorf.config as config_mod

    monkeypatch.setattr(config_mod, "_cpu_has_native_bf16", lambda: native)
    assert config_mod.bf16_native("cpu") is native
    seen = {}
    for setting in ("auto", True, False):
        m = SVORF(model_config("smoke", bf16_autocast=setting))
        with m._autocast(torch.device("cpu")):
            seen[setting] = torch.is_autocast_enabled("cpu")
    assert seen == {"auto": native, True: True, False: False}
    with pytest.raises(ValueError, match="bf16_autocast must be true, false or 'auto'"):
        model_config("smoke", bf16_autocast="yes")


def test_bf16_native_reads_the_cpu_flags():
    import svorf.config as config_mod

    config_mod._cpu_has_native_bf16.cache_clear()
    try:
        with open("/proc/cpuinfo") as f:
            flags = f.read()
    except OSError:
        flags = None
    got = config_mod._cpu_has_native_bf16()
    if flags is None:
        assert got is False
    else:
        assert got == ("avx512_bf16" in flags.split() or "amx_bf16" in flags.split())


def test_knob_config_defaults_and_validation():
    paper = model_config("paper")
    assert all(getattr(paper, k) == v for k, v in KNOBS_OFF.items())  # paper = the method
    cpu = model_config("cpu")
    assert cpu.bf16_autocast == "auto" and cpu.slot_keep_mass == 0.99
    assert cpu.slot_topk == 0 and cpu.fg_box is None  # beyond tolerance / a modelling choice
    assert model_config("cpu", bf16_autocast=False).bf16_autocast is False  # overrides win
    # selection knobs are inert (not an error) for compositions that cannot use them
    for comp in ("density_weighted", "slot_mixer"):
        cfg = model_config("cpu", composition=comp)
        m = SVORF(cfg.replace(slot_topk=2, image_size=32))
        out = m(make_images(1), *make_rays(1, 4))
        assert_finite(out)
    with pytest.raises(ValueError, match="slot_topk"):
        model_config("smoke", slot_topk=-1)
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="slot_keep_mass"):
            model_config("smoke", slot_keep_mass=bad)


# ----------------------------------------------------------------------------- speedbench


def test_speedbench_report_table_and_json(tmp_path):
    variants = [
        speedbench.Variant(
            "original", {}, reference=True, paper_form_composer=True, reference_encode=True
        ),
        speedbench.Variant("baseline", {}),
        speedbench.Variant("topk=2", {"slot_topk": 2}),
        speedbench.Variant("sharp-m baseline", {}, 8.0, reference=True),
        speedbench.Variant("sharp-m keep", {"slot_keep_mass": 0.99}, 8.0),
    ]
    rep = speedbench.run(
        "smoke",
        scenes=1,
        rays=8,
        repeats=1,
        warmup=0,
        threads=1,
        rss=False,
        variants=variants,
        block=2,
        log=lambda s: None,
    )
    assert rep["block"] == 2
    names = [r["name"] for r in rep["variants"]]
    assert names == [v.name for v in variants]
    orig, base = rep["variants"][:2]
    assert orig["ratio"] == 1.0 and orig["rgb_max_err"] == 0.0 and orig["kept_pairs"] == 1.0
    assert base["ratio_vs_baseline"] == 1.0 and base["rgb_max_err"] < 1e-5  # exact refactor
    # the original's encode: default conv layout, textbook cross-attention
    orig_model = speedbench.build_model("smoke", variants[0], None)
    assert not orig_model.encoder.channels_last_on_cpu
    assert not any(getattr(m, "fold_keys", False) for m in orig_model.slot_module.modules())
    base_model = speedbench.build_model("smoke", variants[1], None)
    assert base_model.encoder.channels_last_on_cpu and base_model.slot_module.layers[0].ca.fold_keys
    assert rep["variants"][2]["kept_pairs"] < 1.0
    assert "steps/s" in speedbench.format_table(rep)
    out = tmp_path / "bench.json"
    rc = speedbench.main(
        [
            "--scale",
            "smoke",
            "--scenes",
            "1",
            "--rays",
            "4",
            "--repeats",
            "1",
            "--warmup",
            "0",
            "--threads",
            "1",
            "--only",
            "bf16",
        ]
        + ["--json", str(out)]
    )
    assert rc == 0
    data = json.loads(out.read_text())
    assert [r["name"] for r in data["variants"]] == ["original", "bf16"]
    assert data["variants"][1]["peak_rss_mb"] > 50
    with pytest.raises(SystemExit):
        speedbench.main(["--only", "nonsense", "--no-rss"])
    # --recipe: every variant is the recipe's model (slot locality, foreground box, ...).
    out2 = tmp_path / "recipe.json"
    small = ["--scale", "smoke", "--scenes", "1", "--rays", "4", "--repeats", "1"]
    rc = speedbench.main(
        small
        + ["--warmup", "0", "--threads", "1", "--no-rss", "--recipe", "--only", "keep_mass=0.99"]
        + ["--json", str(out2)]
    )
    assert rc == 0
    rec = json.loads(out2.read_text())
    from benchmark.tools.recipe import recipe_model_levers

    assert rec["base_overrides"]["slot_locality"] == recipe_model_levers()["slot_locality"]
    assert all(r["overrides"]["slot_locality"] for r in rec["variants"])
    assert rec["variants"][0]["rgb_max_err"] == 0.0


def test_compare_train_steps_times_every_model_against_the_first():
    from benchmark.tools.speedbench import compare_train_steps, make_batch
    from svorf.train import run_configs

    mcfg, _ = run_configs("smoke", "synthetic")
    torch.manual_seed(0)
    models = {"a": SVORF(mcfg).train(), "b": SVORF(mcfg.replace(mlp_width=24)).train()}
    out = compare_train_steps(models, make_batch(mcfg, 1, 16), repeats=2, warmup=1)
    assert out["repeats"] == 2 and out["warmup"] == 1
    assert (out["batch_scenes"], out["rays_per_scene"]) == (1, 16)
    assert list(out["median_s"]) == ["a", "b"] and all(t > 0 for t in out["median_s"].values())
    assert out["ratio"]["a"] == 1.0
    assert out["ratio"]["b"] == out["median_s"]["b"] / out["median_s"]["a"]
    # Each timed call was a training step: the last one left its gradients.
    grads = [p.grad for p in models["b"].parameters() if p.grad is not None]
    assert grads and any(g.abs().sum() > 0 for g in grads)


def test_speedbench_times_a_trained_runs_weights(tmp_path):
    """--weights RUN: every variant starts from the run's weights; a run of another model
    is refused in one line naming the first differing parameter."""
    from svorf.checkpoint import write_checkpoint
    from svorf.train_config import TrainConfig

    def save(run: Path, cfg: ModelConfig) -> SVORF:
        torch.manual_seed(3)
        model = SVORF(cfg)
        run.mkdir()
        write_checkpoint(
            run / "checkpoint.pt",
            step=1,
            model=model,
            optimizer=torch.optim.Adam(model.parameters()),
            gen=torch.Generator(),
            device=torch.device("cpu"),
            model_cfg=cfg,
            train_cfg=TrainConfig(),
            dataset={},
            wall_s=0.0,
            loss=0.0,
        )
        return model

    cfg = model_config("smoke", **speedbench.KNOBS_OFF)
    trained = save(tmp_path / "run", cfg)
    like = speedbench.build_model("smoke", speedbench.Variant("init", {}), None).state_dict()
    state = speedbench._run_weights(tmp_path / "run", like)
    for k, v in trained.state_dict().items():
        torch.testing.assert_close(state[k], v)
    rep = speedbench.run(
        "smoke",
        scenes=1,
        rays=4,
        repeats=1,
        threads=1,
        rss=False,
        variants=[speedbench.Variant("baseline", {}, reference=True)],
        weights=tmp_path / "run",
        log=lambda s: None,
    )
    assert rep["weights"] == str(tmp_path / "run")
    save(tmp_path / "other", cfg.replace(slot_locality=1.0, slot_centre="anchored"))
    with pytest.raises(ValueError, match="does not match") as e:
        speedbench._run_weights(tmp_path / "other", like)
    assert "\n" not in str(e.value)
