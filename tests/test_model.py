"""sVORF model: config, batched fields vs references, composition, masking, ablation switches,
gradients, a short training run, editing (svorf.config/encoder/decoder/field/compose/model/edit).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time

import pytest
import torch
import torch.nn.functional as F

from svorf.compose import compose_density_weighted, density_weights
from svorf.config import ModelConfig, model_config
from svorf.decoder import MultiHeadAttention, SlotAttention, SlotTransformerDecoder
from svorf.edit import move_object, object_transforms_for, swap_background
from svorf.encoder import ImageEncoder
from svorf.field import FieldParams, HyperNetwork, SlotConditionedMLP
from svorf.model import SVORF, RenderOutput

PAPER_PARAMS = 48.73e6


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    # 2 shared cores: oversubscribed intra-op threads make tiny ops 10-50x slower.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def smoke(num_slots: int = 4, seed: int = 0, **kw) -> SVORF:
    torch.manual_seed(seed)
    return SVORF(model_config("smoke", num_slots=num_slots, **kw))


def make_rays(B: int, R: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays from a camera ~11.7 units away towards points of the scene box."""
    g = torch.Generator().manual_seed(seed)
    o = torch.tensor([0.0, -10.0, 6.0]).expand(B, R, 3).clone()
    target = (torch.rand(B, R, 3, generator=g) - 0.5) * 6.0
    return o, F.normalize(target - o, dim=-1)


def make_images(B: int, size: int = 32, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(B, 3, size, size, generator=g)


def assert_finite(out: RenderOutput) -> None:
    for name in ("rgb", "depth", "acc", "slot_probs", "connectivity", "coarse_rgb"):
        v = getattr(out, name)
        assert v is None or torch.isfinite(v).all(), name


# ----------------------------------------------------------------------------- config


def test_config_json_roundtrip_and_validation():
    for scale in ("smoke", "cpu", "paper"):
        cfg = model_config(scale, num_slots=5)
        d = json.loads(cfg.to_json())
        assert ModelConfig.from_dict(d) == cfg and isinstance(d["enc_blocks"], list)
    assert model_config("paper").image_size == 256 and model_config("cpu").image_size == 64
    assert model_config("smoke", image_size=48).image_size == 48
    with pytest.raises(ValueError, match="composition"):
        ModelConfig(composition="sum")
    with pytest.raises(ValueError, match="unknown keys"):
        ModelConfig.from_dict({"bogus": 1})
    with pytest.raises(ValueError, match="slot_mask_train"):
        ModelConfig(num_slots=5, slot_mask_train=4)
    with pytest.raises(ValueError, match="scale"):
        model_config("huge")


def test_paper_scale_parameter_count_and_shapes():
    cfg = model_config("paper")
    with torch.device("meta"):
        model = SVORF(cfg)
        n = model.count_parameters()
        feats = model.encoder(torch.empty(1, 3, 256, 256))
        slots = model.slot_module(feats)
    print(f"\nsVORF paper-scale parameters: {n / 1e6:.2f}M (paper: 48.73M)")
    assert abs(n - PAPER_PARAMS) / PAPER_PARAMS < 0.03
    assert tuple(feats.shape) == (1, 512, 128, 128)  # appendix: 128 x 128 x 512
    assert tuple(slots.shape) == (1, 8, cfg.slot_dim)
    cpu = SVORF(model_config("cpu")).count_parameters()
    assert 1e6 <= cpu <= 3e6


def test_encoder_maps_inputs_and_init():
    enc = ImageEncoder(8, (1, 1, 1), 16, "group")
    x = make_images(2, 32)
    out = enc(x)
    assert out.shape == (2, 16, 16, 16)
    conv_biases = [m.bias for m in enc.modules() if isinstance(m, torch.nn.Conv2d)]
    assert all(b is None or torch.all(b == 0) for b in conv_biases)
    # image dependence: two images give clearly different features
    rel = (out[0] - out[1]).norm() / out.norm()
    assert rel > 0.05


def test_channels_last_encoder_equals_the_default_layout():
    """On CPU the encoder runs its convolutions channels-last: same weights, the same
    features and gradients (to float rounding) as PyTorch's default layout, and a
    channels-last output map (which the decoder flattens into tokens without a copy)."""
    torch.manual_seed(0)
    fast = ImageEncoder(8, (1, 1, 1), 16, "group")
    plain = ImageEncoder(8, (1, 1, 1), 16, "group")
    plain.load_state_dict(fast.state_dict())
    plain.channels_last_on_cpu = False
    x = make_images(2, 32)
    a, b = fast(x), plain(x)
    assert a.is_contiguous(memory_format=torch.channels_last)
    assert b.is_contiguous() and not a.is_contiguous()
    torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    a.square().sum().backward()
    b.square().sum().backward()
    for (name, p), q in zip(fast.named_parameters(), plain.parameters()):
        assert p.is_contiguous(), name  # the weights keep their layout
        assert (p.grad - q.grad).norm() <= 1e-4 * q.grad.norm(), name


def test_encoder_up_kernel_one_is_a_cheaper_head_of_the_same_shape():
    x = make_images(2, 32)
    heavy = ImageEncoder(8, (1, 1, 1), 16, "group", up_kernel=3)
    light = ImageEncoder(8, (1, 1, 1), 16, "group", up_kernel=1)
    assert light(x).shape == heavy(x).shape == (2, 16, 16, 16)
    for name in ("up1", "up2", "up3"):
        assert getattr(light, name).weight.shape[-2:] == (1, 1)
        assert getattr(heavy, name).weight.numel() == 9 * getattr(light, name).weight.numel()
    with pytest.raises(ValueError, match="up_kernel"):
        ImageEncoder(8, (1, 1, 1), 16, "group", up_kernel=5)
    # the config field: off by default and then not in the config dict (earlier runs' keys stay)
    base = model_config("cpu")
    assert base.enc_up_kernel is None and "enc_up_kernel" not in base.to_dict()
    cfg = dataclasses.replace(base, enc_up_kernel=1)
    assert cfg.to_dict()["enc_up_kernel"] == 1
    assert ModelConfig.from_dict(cfg.to_dict()) == cfg
    assert SVORF(cfg).encoder.up3.weight.shape[-2:] == (1, 1)
    assert dataclasses.replace(base, enc_up_kernel=3) == base  # the paper's 3x3: same key
    with pytest.raises(ValueError, match="enc_up_kernel"):
        dataclasses.replace(base, enc_up_kernel=2)


def test_encoder_full_res_hands_the_decoder_a_map_at_the_input_resolution():
    """enc_full_res: the map (and so the decoder's tokens and attention) at H x W, not
    H/2 x W/2; the half-resolution part keeps its weights, the two new convs learn."""
    torch.manual_seed(0)
    x = make_images(2, 32)
    half = ImageEncoder(8, (1, 1, 1), 16, "group")
    full = ImageEncoder(8, (1, 1, 1), 16, "group", full_res=True)
    missing = full.load_state_dict(half.state_dict(), strict=False).missing_keys
    assert sorted(missing) == [
        "stem_full.bias", "stem_full.weight", "up4.bias", "up4.weight"
    ]  # fmt: skip
    assert half(x).shape == (2, 16, 16, 16)
    out = full(x)
    assert out.shape == (2, 16, 32, 32)
    out.square().sum().backward()
    for name in ("stem_full", "up4", "up3", "stem"):
        grads = [p.grad for p in getattr(full, name).parameters()]
        assert all(g is not None and g.abs().sum() > 0 for g in grads), name
    # the config field: off by default and then not in the config dict (earlier runs' keys stay)
    base = model_config("smoke", num_slots=4)
    assert base.enc_full_res is False and "enc_full_res" not in base.to_dict()
    assert model_config("paper").enc_full_res is False
    cfg = dataclasses.replace(base, enc_full_res=True)
    assert cfg.to_dict()["enc_full_res"] is True
    assert ModelConfig.from_dict(cfg.to_dict()) == cfg
    torch.manual_seed(0)
    model = SVORF(cfg)
    images = make_images(2, cfg.image_size)
    slots, attn = model.encode(images, return_attn=True)
    assert slots.shape == (2, 4, cfg.slot_dim)
    assert attn.shape == (2, 4, cfg.image_size, cfg.image_size)


# ----------------------------------------------------------------------------- fields


def _field_inputs(fields, B, Kx, P, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    gx = torch.randn(B, Kx, P, fields.in_x, generator=g, dtype=dtype)
    gd = torch.randn(B, Kx, P, fields.in_d, generator=g, dtype=dtype)
    return gx, gd


@pytest.mark.parametrize("hyper", [True, False])
def test_batched_fields_equal_per_slot_loop(hyper):
    cfg = model_config("smoke", num_slots=3, hypernetwork=hyper)
    torch.manual_seed(0)
    fields = (HyperNetwork if hyper else SlotConditionedMLP)(cfg).double()
    slots = torch.randn(2, 3, cfg.slot_dim, dtype=torch.float64)
    p = fields.params(slots)
    for Kx in (1, 3):
        gx, gd = _field_inputs(fields, 2, Kx, 11, seed=Kx)
        s, c = fields.eval_fields(p, gx, gd)
        s_ref, c_ref = fields.eval_reference(p, gx, gd)
        assert s.shape == (2, 3, 11) and c.shape == (2, 3, 11, 3)
        torch.testing.assert_close(s, s_ref)
        torch.testing.assert_close(c, c_ref)
        assert (s >= 0).all() and ((c > 0) & (c < 1)).all()


def test_hypernetwork_mixed_field_equals_mixed_parameters():
    """Slot Mixer: one field per point whose parameters are the a-weighted slot mix."""
    cfg = model_config("smoke", num_slots=3)
    torch.manual_seed(0)
    fields = HyperNetwork(cfg).double()
    p = fields.params(torch.randn(2, 3, cfg.slot_dim, dtype=torch.float64))
    gx, gd = _field_inputs(fields, 2, 1, 5)
    a = torch.softmax(torch.randn(2, 5, 3, dtype=torch.float64), dim=-1)
    s, c = fields.eval_mixed(p, a, gx[:, 0], gd[:, 0])
    for b in range(2):
        for i in range(5):
            w = a[b, i][None, :]

            def mix(t, w=w, b=b):
                return torch.einsum("bk,bk...->b...", w, t[b : b + 1])[:, None]

            pm = FieldParams(
                [(mix(W), mix(bb)) for W, bb in p.hidden],
                mix(p.head_w),
                mix(p.head_d),
                mix(p.head_b),
            )
            s_ref, c_ref = fields.eval_reference(
                pm, gx[b : b + 1, :, i : i + 1], gd[b : b + 1, :, i : i + 1]
            )
            torch.testing.assert_close(s[b, i], s_ref[0, 0, 0])
            torch.testing.assert_close(c[b, i], c_ref[0, 0, 0])


def test_hypernetwork_init_is_he_scaled():
    """Generated MLPs start with sensible activations (no vanishing/exploding layers)."""
    cfg = model_config("cpu")
    torch.manual_seed(0)
    fields = HyperNetwork(cfg)
    p = fields.params(torch.randn(2, 4, cfg.slot_dim))
    gx, gd = _field_inputs(fields, 2, 1, 256, dtype=torch.float32)
    s, c = fields.eval_fields(p, gx.clamp(-1, 1), gd.clamp(-1, 1))
    assert 0.05 < s.mean() < 20 and c.std() > 0.01
    # slots change the field
    assert (s[:, 0] - s[:, 1]).abs().mean() > 1e-2


# ----------------------------------------------------------------------------- model


def test_forward_shapes_and_probabilities():
    model = smoke()
    o, d = make_rays(2, 24)
    t0 = time.perf_counter()
    out = model(make_images(2), o, d, perturb=True)
    total, stats = model.loss(out, torch.rand(2, 24, 3))
    total.backward()
    print(f"\nsmoke forward+backward (2 scenes x 24 rays): {time.perf_counter() - t0:.3f}s")
    assert out.rgb.shape == (2, 24, 3) and out.coarse_rgb.shape == (2, 24, 3)
    assert out.depth.shape == (2, 24) and out.acc.shape == (2, 24)
    assert out.slot_probs.shape == (2, 24, 4) and out.connectivity.dim() == 0
    assert_finite(out)
    torch.testing.assert_close(out.slot_probs.sum(-1), torch.ones(2, 24))
    assert set(stats) == {"mse", "mse_coarse", "connectivity", "psnr", "total"}
    # depth lies within [near, far] (acc ~ 1 thanks to the infinite last interval)
    assert (out.depth > model.cfg.near - 1e-3).all() and (out.depth < model.cfg.far + 1e-3).all()
    aux_off = model.render_rays(model.encode(make_images(2)), o, d, need_aux=False)
    assert aux_off.slot_probs is None and aux_off.connectivity.item() == 0.0


def test_encode_resizes_and_slots_depend_on_image():
    model = smoke().eval()
    imgs = make_images(2, 48)
    slots = model.encode(imgs)
    ref = model.encode(F.interpolate(imgs, size=(32, 32), mode="bilinear", antialias=True))
    torch.testing.assert_close(slots, ref)
    rel = (slots[0] - slots[1]).norm() / slots.norm()
    assert rel > 1e-2
    with pytest.raises(ValueError, match="images"):
        model.encode(torch.rand(2, 32, 32))


def test_input_validation():
    model = smoke()
    slots = torch.randn(2, 4, model.cfg.slot_dim)
    o, d = make_rays(2, 8)
    with pytest.raises(ValueError, match="slots"):
        model.render_rays(slots[..., :-1], o, d)
    with pytest.raises(ValueError, match="rays_d"):
        model.render_rays(slots, o, d[:, :, :2])
    with pytest.raises(ValueError, match="slot_mask"):
        model.render_rays(slots, o, d, slot_mask=torch.ones(2, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match="no slot"):
        model.render_rays(slots, o, d, slot_mask=torch.zeros(2, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match="target_rgb"):
        model.loss(model.render_rays(slots, o, d), torch.rand(2, 7, 3))


@pytest.mark.parametrize("composition", ["slot_guided", "density_weighted", "slot_mixer"])
def test_slot_masking_zero_probability_no_nan(composition):
    model = smoke(composition=composition)
    slots = model.encode(make_images(2))
    o, d = make_rays(2, 16)
    uniform = torch.tensor([[True, False, True, True], [False, True, True, True]])
    ragged = torch.tensor([[True, False, False, True], [True, True, True, True]])
    only_bg = torch.tensor([[False, False, False, True]] * 2)
    for mask in (uniform, ragged, only_bg):
        out = model.render_rays(slots, o, d, slot_mask=mask)
        assert_finite(out)
        probs = out.slot_probs
        assert torch.all(probs[~mask[:, None, :].expand_as(probs)] == 0)
        torch.testing.assert_close(probs.sum(-1), torch.ones(2, 16))
    torch.testing.assert_close(out.slot_probs[..., -1], torch.ones(2, 16))
    # the compacted path (masked slots not evaluated) equals plain masking
    is_bg = torch.zeros(2, 4, dtype=torch.bool)
    is_bg[:, -1] = True
    fast = model.render_rays(slots, o, d, slot_mask=uniform)
    plain = model._render(slots, o, d, uniform, is_bg, False, True, None, None)
    for name in ("rgb", "depth", "slot_probs", "connectivity"):
        torch.testing.assert_close(getattr(fast, name), getattr(plain, name), atol=1e-5, rtol=1e-4)


def test_slot_mask_train_masks_objects_never_background():
    model = smoke(num_slots=6, slot_mask_train=2)
    mask = model.sample_slot_mask(64)
    assert mask.shape == (64, 6) and mask[:, -1].all()
    assert torch.all((~mask).sum(1) == 2)
    o, d = make_rays(3, 8)
    out = model.train()(make_images(3), o, d)
    assert torch.all((out.slot_probs == 0).all(dim=1).sum(-1) == 2)
    out = model.eval()(make_images(3), o, d)
    assert not (out.slot_probs == 0).all(dim=1).any()
    assert smoke(num_slots=6).sample_slot_mask(4) is None


def _query(model, slots, B=2, R=8, seed=0):
    o, d = make_rays(B, R, seed)
    K = slots.shape[1]
    is_bg = torch.zeros(B, K, dtype=torch.bool)
    is_bg[:, -1] = True
    ctx = model.query_context(slots, model.fields.params(slots), o, d, None, is_bg)
    g = torch.Generator().manual_seed(seed)
    t = torch.sort(torch.rand(B, R, 6, generator=g) * 8 + 8, dim=-1).values
    return model._query(ctx, t)


def test_composition_rules():
    base = smoke()
    slots = base.encode(make_images(2))
    q = _query(base, slots)
    # slot guided: sigma = sum m sigma_k
    torch.testing.assert_close(q.sigma, torch.einsum("brnk,bkrn->brn", q.m, q.sigma_k))
    torch.testing.assert_close(q.m.sum(-1), torch.ones_like(q.sigma))
    # density weighted: m = sigma_k / sum sigma, sigma = sum sigma_k
    dw = smoke(composition="density_weighted")
    dw.load_state_dict(base.state_dict(), strict=False)
    qd = _query(dw, slots)
    sk = qd.sigma_k.permute(0, 2, 3, 1)
    torch.testing.assert_close(qd.m, sk / sk.sum(-1, keepdim=True), atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(qd.sigma, sk.sum(-1))
    assert not torch.allclose(qd.sigma, q.sigma)
    # composition helpers: all-zero densities and masks give no NaN
    z = torch.zeros(1, 3, 4)
    m = density_weights(z, torch.tensor([True, False, True])[None, None])
    torch.testing.assert_close(m, torch.tensor([0.5, 0.0, 0.5]).expand(1, 4, 3))
    s, c, _ = compose_density_weighted(z, torch.rand(1, 3, 4, 3))
    assert torch.isfinite(s).all() and torch.isfinite(c).all()


def test_ablation_switches_change_outputs():
    torch.manual_seed(0)
    imgs = make_images(2)
    o, d = make_rays(2, 16)
    base = smoke().eval()
    ref = base(imgs, o, d)
    variants = {
        "density_weighted": {"composition": "density_weighted"},
        "slot_mixer": {"composition": "slot_mixer"},
        "no_self_attention": {"self_attention": False},
        "no_hypernetwork": {"hypernetwork": False},
        "slot_attention": {"slot_module": "slot_attention"},
        "fg_box": {"fg_box": 2.0},
        "bf16": {"bf16_autocast": True},
    }
    for name, kw in variants.items():
        model = smoke(**kw).eval()
        own = model.state_dict()
        shared = {
            k: v for k, v in base.state_dict().items() if k in own and own[k].shape == v.shape
        }
        model.load_state_dict(shared, strict=False)
        out = model(imgs, o, d)
        assert_finite(out)
        diff = (out.rgb - ref.rgb).abs().max().item()
        assert diff > 1e-4, name
        if name == "bf16":
            assert diff < 0.1, "bf16 should stay close to float32"
    assert isinstance(smoke(hypernetwork=False).fields, SlotConditionedMLP)
    assert isinstance(smoke(slot_module="slot_attention").slot_module, SlotAttention)
    # connectivity switch
    out = smoke(connectivity=False)(imgs, o, d)
    assert out.connectivity.item() == 0.0
    total, stats = smoke(connectivity=False).loss(out, torch.rand(2, 16, 3))
    torch.testing.assert_close(total, stats["mse"] + stats["mse_coarse"])
    assert ref.connectivity.item() > 0


def test_self_attention_switch_controls_slot_interaction():
    feats = torch.randn(2, 32, 8, 8)
    for sa in (True, False):
        torch.manual_seed(0)
        dec = SlotTransformerDecoder(model_config("smoke", num_slots=4, self_attention=sa))
        a = dec(feats)
        with torch.no_grad():
            dec.init.pos[0] += torch.randn(dec.init.pos.shape[1])  # slot 0's init only
        b = dec(feats)
        others_changed = (a[:, 1:] - b[:, 1:]).abs().max().item()
        assert (others_changed > 1e-4) == sa
        assert (a[:, 0] - b[:, 0]).abs().max() > 1e-4


def test_fg_box_skips_out_of_box_pairs_and_zeroes_them():
    model = smoke(fg_box=1.5)
    slots = model.encode(make_images(2))
    fields = model.fields
    p = fields.params(slots)
    x = (torch.rand(2, 1, 40, 3) - 0.5) * 6
    from svorf.field import positional_encoding

    gx = positional_encoding(x / model.cfg.box_half, model.cfg.pos_freqs_xyz)
    gd = positional_encoding(F.normalize(torch.randn(2, 1, 40, 3), dim=-1), model.cfg.pos_freqs_dir)
    inside = (x.abs() <= 1.5).all(-1)  # [B, 1, P]
    is_bg = torch.tensor([[False, False, False, True]] * 2)
    keep = (inside.expand(2, 4, 40) | is_bg[:, :, None]).transpose(1, 2)  # [B, P, K]
    assert 0 < keep.float().mean() < 0.85  # the sparse path runs
    s_fast, c_fast = model._eval_slots(p, gx, gd, keep)
    s_all, c_all = fields.eval_fields(p, gx, gd)
    k = keep.transpose(1, 2)
    torch.testing.assert_close(s_fast, s_all * k)
    torch.testing.assert_close(c_fast, c_all * k[..., None])
    out_mask = ~inside[:, 0]
    assert torch.all(s_fast[:, :3][out_mask[:, None].expand(-1, 3, -1)] == 0)
    assert torch.all(s_fast[:, 3] > 0)


def test_gradients_finite_for_all_parameters():
    o, d = make_rays(2, 12)
    target = torch.rand(2, 12, 3)
    for kw in (
        {},
        {"composition": "density_weighted"},
        {"composition": "slot_mixer"},
        {"hypernetwork": False},
        {"slot_module": "slot_attention", "self_attention": False},
        {"fg_box": 2.0, "bf16_autocast": True, "enc_norm": "batch"},
    ):
        model = smoke(**kw)
        out = model(make_images(2), o, d, perturb=True)
        total, _ = model.loss(out, target)
        total.backward()
        for name, prm in model.named_parameters():
            assert prm.grad is not None, (kw, name)
            assert torch.isfinite(prm.grad).all(), (kw, name)


def test_extreme_densities_distances_and_bf16_are_finite():
    model = smoke(near=1.0, far=1e4, clip_to_box=False, bf16_autocast=True, sigma_max=1e6)
    model.fields.density = lambda raw: raw * 0 + 1e6  # every field fully opaque
    o, d = make_rays(2, 8)
    out = model(make_images(2), o * 100, d, perturb=True)
    assert_finite(out)
    total, _ = model.loss(out, torch.rand(2, 8, 3))
    total.backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_render_chunked_matches_render_rays():
    model = smoke().eval()
    slots = model.encode(make_images(2))
    o, d = make_rays(2, 20)
    full = model.render_rays(slots, o, d)
    chunked = model.render_chunked(slots, o, d, chunk=7)
    for name in ("rgb", "depth", "acc", "slot_probs", "coarse_rgb"):
        torch.testing.assert_close(
            getattr(chunked, name), getattr(full, name), atol=1e-5, rtol=1e-5
        )
    assert not chunked.rgb.requires_grad


def test_training_loop_lowers_loss():
    torch.manual_seed(0)
    model = smoke(num_slots=4)
    imgs = make_images(2)
    o, d = make_rays(2, 64)
    # a learnable target: colour varies smoothly with the ray direction
    target = torch.sigmoid(
        4 * d @ torch.tensor([[1.0, 0.0, -1.0], [0.5, 1.0, 0.0], [0.0, -1.0, 2.0]])
    )
    opt = torch.optim.Adam(model.parameters(), lr=2e-3)
    losses = []
    t0 = time.perf_counter()
    for _ in range(40):
        out = model(imgs, o, d, perturb=True)
        total, stats = model.loss(out, target)
        opt.zero_grad()
        total.backward()
        opt.step()
        losses.append(stats["mse"].item())
    print(
        f"\nsmoke: 40 steps in {time.perf_counter() - t0:.2f}s, mse {losses[0]:.4f} -> {losses[-1]:.4f}"
    )
    assert sum(losses[-5:]) / 5 < 0.5 * losses[0]


# ----------------------------------------------------------------------------- editing


def test_moving_every_slot_equals_moving_the_camera():
    """Moving all slots by M renders what the inverse-moved camera sees."""
    model = smoke(num_slots=3, clip_to_box=False).eval()
    slots = model.encode(make_images(2))
    o, d = make_rays(2, 12)
    ang = 0.4
    rot = torch.tensor(
        [[math.cos(ang), -math.sin(ang), 0.0], [math.sin(ang), math.cos(ang), 0.0], [0.0, 0.0, 1.0]]
    )
    M = torch.eye(4)
    M[:3, :3] = rot
    M[:3, 3] = torch.tensor([0.5, -0.3, 0.2])
    moved = model.render_rays(slots, o, d, object_transforms=M.expand(2, 3, 4, 4))
    o2 = (o - M[:3, 3]) @ rot  # R^T (o - v) as row vectors
    d2 = d @ rot
    cam = model.render_rays(slots, o2, d2)
    for name in ("rgb", "depth", "slot_probs"):
        torch.testing.assert_close(getattr(moved, name), getattr(cam, name), atol=1e-4, rtol=1e-4)


def test_move_object_and_swap_background():
    model = smoke().eval()
    slots = model.encode(make_images(2))
    o, d = make_rays(2, 16)
    plain = model.render_rays(slots, o, d)
    ident = move_object(model, slots, 1, torch.eye(4), o, d)
    torch.testing.assert_close(ident.rgb, plain.rgb, atol=1e-5, rtol=1e-5)
    T = torch.eye(4)
    T[:3, 3] = torch.tensor([2.0, 0.0, 0.0])
    moved = move_object(model, slots, 1, T, o, d, chunk=5)
    assert_finite(moved)
    assert (moved.rgb - plain.rgb).abs().max() > 1e-5
    tr = object_transforms_for(slots, 1, T)
    assert torch.equal(tr[:, 1], T.expand(2, 4, 4)) and torch.equal(
        tr[:, 0], torch.eye(4).expand(2, 4, 4)
    )
    other = model.encode(make_images(2, seed=5))
    swapped = swap_background(slots, other)
    assert torch.equal(swapped[:, :-1], slots[:, :-1]) and torch.equal(swapped[:, -1], other[:, -1])
    with pytest.raises(ValueError, match="slot_mixer"):
        smoke(composition="slot_mixer").render_rays(slots, o, d, object_transforms=tr)


# ----------------------------------------------------------------------------- coordinate frame


def _rot_z(ang: float) -> torch.Tensor:
    c, s = math.cos(ang), math.sin(ang)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_azimuth_frame_puts_the_camera_at_azimuth_zero():
    from svorf.model import azimuth_frame

    c2w = torch.eye(4).repeat(3, 1, 1)
    c2w[:, :3, 3] = torch.tensor([[3.0, 4.0, 6.0], [-2.0, -0.5, 1.0], [0.0, 0.0, 9.0]])
    R = azimuth_frame(c2w)
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3).expand(3, 3, 3))
    c = torch.einsum("bij,bj->bi", R, c2w[:, :3, 3])
    torch.testing.assert_close(c[:, 1], torch.zeros(3), atol=1e-6, rtol=0)
    assert (c[:2, 0] > 0).all()
    torch.testing.assert_close(c[:, 2], c2w[:, 2, 3])  # z untouched
    torch.testing.assert_close(R[2], torch.eye(3))  # camera on the axis: identity


@pytest.mark.parametrize("frame", ["input_azimuth", "world"])
def test_input_azimuth_frame_makes_renders_rotation_invariant(frame):
    """Rotating the scene (rays and input camera) about z by 90 degrees leaves the render of
    an input_azimuth model unchanged (the networks see the same coordinates; the box priors
    are invariant under 90-degree turns), and changes a world-frame model's render."""
    model = smoke(num_slots=3, coord_frame=frame, fg_box=2.5, fg_zmin=0.1).eval()
    slots = model.encode(make_images(2))
    o, d = make_rays(2, 16)
    c2w = torch.eye(4).repeat(2, 1, 1)
    c2w[:, :3, 3] = o[:, 0]
    rot4 = torch.eye(4)
    rot4[:3, :3] = _rot_z(math.pi / 2)
    a = model.render_rays(slots, o, d, input_c2w=c2w)
    b = model.render_rays(slots, o @ rot4[:3, :3].T, d @ rot4[:3, :3].T, input_c2w=rot4 @ c2w)
    same = all(
        torch.allclose(getattr(a, n), getattr(b, n), atol=1e-4, rtol=1e-4)
        for n in ("rgb", "depth", "slot_probs")
    )
    assert same == (frame == "input_azimuth")


def test_configs_saved_without_coord_frame_load_as_world():
    d = model_config("smoke").to_dict()
    assert d["coord_frame"] == "input_azimuth"
    del d["coord_frame"]
    assert ModelConfig.from_dict(d).coord_frame == "world"
    with pytest.raises(ValueError, match="coord_frame"):
        model_config("smoke", coord_frame="camera")


# ----------------------------------------------------------------------------- slot locality


def test_slot_locality_confines_each_foreground_slot_near_its_centre():
    """With slot_locality = r every foreground slot's density is scaled by its Gaussian
    envelope around the centre it predicts, and its composition logit gets log g."""
    r = 0.5
    model = smoke(num_slots=3, slot_locality=r).eval()
    base = smoke(num_slots=3).eval()
    base.load_state_dict(model.state_dict(), strict=False)
    slots = model.encode(make_images(2))
    centres = model._centres(slots)
    assert centres.shape == (2, 3, 3) and (centres.abs() <= model.cfg.box_half).all()
    q, q0 = _query(model, slots), _query(base, slots)
    o, d = make_rays(2, 8)
    g0 = torch.Generator().manual_seed(0)
    t = torch.sort(torch.rand(2, 8, 6, generator=g0) * 8 + 8, dim=-1).values  # as _query's
    x = o[:, :, None] + t[..., None] * d[:, :, None]  # [B, R, N, 3]
    d2 = (x[:, None] - centres[:, :, None, None]).square().sum(-1)  # [B, K, R, N]
    g = torch.exp(-d2 / (2 * r * r))
    g[:, -1] = 1.0  # the background slot has no envelope
    # Densities: the base model's fields times the envelope (same weights, same samples).
    torch.testing.assert_close(q.sigma_k, q0.sigma_k * g, rtol=1e-4, atol=1e-6)
    # Composition: m = softmax(logits + log g) = m0 g / sum(m0 g).
    m0g = q0.m * g.permute(0, 2, 3, 1)
    torch.testing.assert_close(q.m, m0g / m0g.sum(-1, keepdim=True), rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match="slot_locality"):
        model_config("smoke", slot_locality=0.0)


@pytest.mark.parametrize("module", [SlotTransformerDecoder, SlotAttention])
def test_dec_value_pos_puts_token_positions_into_the_slots(module):
    """dec_value_pos: cross-attention values carry the tokens' positional encoding. With a
    spatially uniform feature map every token has the same content, so without positions in
    the values the slots cannot depend on where attention goes; with them they do."""
    cfg = model_config("smoke")
    torch.manual_seed(0)
    plain = module(cfg)
    with_pos = module(cfg.replace(dec_value_pos=True))
    with_pos.load_state_dict(plain.state_dict())  # same weights: only the values differ
    flat = torch.ones(1, cfg.feat_dim, 4, 4)
    # Content-free values: the slots equal those of a map with the same mean feature.
    torch.testing.assert_close(plain(flat), plain(flat.mean((2, 3), keepdim=True).expand_as(flat)))
    out = with_pos(flat)
    assert not torch.allclose(out, plain(flat), atol=1e-4)
    assert torch.isfinite(out).all()
    assert ModelConfig.from_dict({}).dec_value_pos is False  # old configs load unchanged


# ----------------------------------------------------------------------------- attention centres


def test_token_ground_points_match_an_independent_ray_plane_cut():
    """Each token's ground point is where the ray through the token centre (pinhole, focal
    = centre_focal x width) meets z = height: checked against look_at_opencv + a direct
    ray-plane intersection written here."""
    import numpy as np

    from svorf.model import token_ground_points
    from svorf.synthetic import look_at_opencv

    eye = np.array([9.0, -7.0, 8.0])
    c2w = torch.tensor(look_at_opencv(eye), dtype=torch.float32)[None]
    h, w, f, z0 = 4, 6, 1.1, 0.35
    got = token_ground_points(c2w, h, w, f, z0, extent=100.0)[0].numpy()
    R = look_at_opencv(eye)[:3, :3]
    for i in range(h):
        for j in range(w):
            d = R @ np.array([((j + 0.5) / w - 0.5) / f, ((i + 0.5) / h - 0.5) / f, 1.0])
            p = eye + (z0 - eye[2]) / d[2] * d
            np.testing.assert_allclose(got[i * w + j], p, rtol=1e-4, atol=1e-4)
    # Clamped to the object region.
    clamped = token_ground_points(c2w, h, w, f, z0, extent=1.0)
    assert clamped[..., :2].abs().max() <= 1.0 and (clamped[..., 2] == z0).all()


def test_anchored_centres_are_spread_anchors_plus_a_bounded_learned_offset():
    """slot_centre='anchored': c_k = a_k + e/2 tanh(Linear(s_k)), anchors on a sunflower
    disk of radius 0.6 e; with a zero offset map the centres are the anchors, and the
    offset map gets gradients from the reconstruction loss."""
    from svorf.model import centre_anchors

    a = centre_anchors(8, 3.75, 0.35)
    assert a.shape == (8, 3) and torch.equal(a[-1], torch.zeros(3))
    fg = a[:-1]
    assert bool((fg[:, 2] == 0.35).all()) and float(fg[:, :2].norm(dim=-1).max()) <= 0.6 * 3.75
    dist = torch.cdist(fg, fg) + torch.eye(7) * 1e9
    assert float(dist.min()) > 0.8  # evenly spread: no two anchors near one spot
    model = smoke(num_slots=4, slot_locality=1.0, slot_centre="anchored", fg_box=3.0).eval()
    with torch.no_grad():
        slots = model.encode(make_images(2))
        c = model._centres(slots)
    off = c - centre_anchors(4, 3.0, model.cfg.centre_height)
    assert float(off.abs().max()) <= 1.5 and float(off.abs().max()) > 0
    with torch.no_grad():
        model.slot_centre.weight.zero_()
        model.slot_centre.bias.zero_()
    torch.testing.assert_close(model._centres(slots), centre_anchors(4, 3.0, 0.35).expand(2, 4, 3))
    assert model.encode_for_render(make_images(1))[1] == {}  # no attention maps needed
    model = smoke(num_slots=4, slot_locality=1.0, slot_centre="anchored", fg_box=3.0).train()
    o, d = make_rays(2, 8)
    out = model(make_images(2), o, d, perturb=True)
    assert_finite(out)
    model.loss(out, torch.rand(2, 8, 3))[0].backward()
    g = model.slot_centre.weight.grad
    assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0


def test_attention_centres_follow_each_slots_attention():
    """slot_centre='attention': c_k = sum_t attn_kt * ground_t (then into the networks'
    frame); encode returns attention maps that sum to 1; rendering needs them."""
    import numpy as np

    from svorf.model import azimuth_frame, token_ground_points
    from svorf.synthetic import look_at_opencv

    model = smoke(num_slots=3, slot_locality=0.8, slot_centre="attention").eval()
    assert model.slot_centre is None  # nothing learned for the centres
    imgs = make_images(2)
    slots, extra = model.encode_for_render(imgs)
    attn = extra["slot_attn"]
    assert attn.shape[:2] == (2, 3) and torch.allclose(attn.sum((-1, -2)), torch.ones(2, 3))
    c2w = torch.tensor(look_at_opencv(np.array([9.0, -7.0, 8.0])), dtype=torch.float32)
    c2w = c2w[None].expand(2, 4, 4)
    frame = azimuth_frame(c2w)
    c = model._centres(slots, attn, c2w, frame)
    h, w = attn.shape[-2:]
    ground = token_ground_points(c2w, h, w, model.cfg.centre_focal, model.cfg.centre_height,
                                 model.cfg.box_half)  # fmt: skip
    for b in range(2):
        for k in range(3):
            world = (attn[b, k].reshape(-1, 1) * ground[b]).sum(0)
            torch.testing.assert_close(c[b, k], frame[b] @ world, rtol=1e-4, atol=1e-5)
    # A one-hot attention puts the centre on that token's ground point.
    onehot = torch.zeros_like(attn)
    onehot[:, :, 1, 2] = 1.0
    c1 = model._centres(slots, onehot, c2w, None)
    torch.testing.assert_close(c1[0, 0], ground[0, 1 * w + 2])
    o, d = make_rays(2, 8)
    out = model.render_rays(slots, o, d, input_c2w=c2w, slot_attn=attn)
    assert_finite(out)
    with pytest.raises(ValueError, match="slot_attn"):
        model.render_rays(slots, o, d, input_c2w=c2w)
    # Training: gradients reach the attention (the decoder's last cross-attention query).
    model.train()
    out = model(imgs, o, d, input_c2w=c2w, perturb=True)
    model.loss(out, torch.rand(2, 8, 3))[0].backward()
    g = model.slot_module.layers[-1].ca.q.weight.grad
    assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0
    with pytest.raises(ValueError, match="slot_locality"):
        model_config("smoke", slot_centre="attention")


def test_attention_weights_equal_the_fused_attention_path():
    """MultiHeadAttention(need_weights=True) (explicit softmax, for the attention centres)
    gives the same output as the fused scaled_dot_product_attention path."""
    torch.manual_seed(0)
    mha = MultiHeadAttention(16, 4, 16, 12, 12)
    q, kv = torch.randn(2, 5, 16), torch.randn(2, 7, 12)
    out, logits = mha(q, kv, kv, need_weights=True)
    torch.testing.assert_close(out, mha(q, kv, kv), rtol=1e-5, atol=1e-6)
    assert logits.shape == (2, 4, 5, 7)


def test_folded_cross_attention_equals_the_textbook_form():
    """fold_keys (the decoder's cross-attention) folds the key projection into the queries
    and applies the value projection after the weighted sum: the same outputs, logits and
    gradients as projecting every key and value (forward_reference), with non-zero biases
    and a key mask; the logits (with the query's key-bias term) also under a softmax over
    the queries, as the attention centres take them."""
    torch.manual_seed(0)
    folded = MultiHeadAttention(16, 4, 16, 12, 10, fold_keys=True)
    with torch.no_grad():
        for p in folded.parameters():
            p.add_(0.3 * torch.randn_like(p))
    plain = MultiHeadAttention(16, 4, 16, 12, 10)
    plain.load_state_dict(folded.state_dict())
    q, k, v = torch.randn(2, 5, 16), torch.randn(2, 9, 12), torch.randn(2, 9, 10)
    mask = torch.ones(2, 9, dtype=torch.bool)
    mask[0, :4] = False
    for key_mask in (None, mask):
        ins = [[t.clone().requires_grad_() for t in (q, k, v)] for _ in range(2)]
        out_f, logits_f = folded(*ins[0], key_mask=key_mask, need_weights=True)
        out_p, logits_p = plain(*ins[1], key_mask=key_mask, need_weights=True)
        torch.testing.assert_close(out_f, out_p, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(logits_f, logits_p, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(folded(q, k, v, key_mask), plain(q, k, v, key_mask))
        folded.zero_grad()
        plain.zero_grad()
        (out_f.square().sum() + logits_f.softmax(2).square().sum()).backward()
        (out_p.square().sum() + logits_p.softmax(2).square().sum()).backward()
        for a, b in zip(ins[0], ins[1]):
            torch.testing.assert_close(a.grad, b.grad, rtol=1e-4, atol=1e-5)
        # relative to each gradient's norm: the key bias's gradient is a sum of cancelling
        # terms as large as the other gradients (|g| ~ 50), so float32 rounding leaves about
        # 1e-5 absolute error there on some CPUs (AMD EPYC: 1.7e-5, 8e-6 of its norm)
        for (name, a), b in zip(folded.named_parameters(), plain.parameters()):
            assert (a.grad - b.grad).norm() <= 1e-4 * b.grad.norm(), name
    # the decoder's cross-attention folds; its self-attention (K x K) does not
    layer = SlotTransformerDecoder(model_config("smoke")).layers[0]
    assert layer.ca.fold_keys and not layer.sa.fold_keys


def test_slot_normalised_attention_maps_share_each_token_among_the_slots():
    """attn_over="slots": the last layer's logits, softmax over the slots (per head, mean
    over heads), then normalised over the tokens; "tokens": the weights the layer uses."""
    cfg = model_config("smoke", num_slots=4)
    torch.manual_seed(0)
    dec = SlotTransformerDecoder(cfg).eval()
    feats = torch.randn(2, cfg.feat_dim, 3, 5)
    slots_t, a_tok = dec(feats, return_attn=True, attn_over="tokens")
    slots_s, a_slot = dec(feats, return_attn=True, attn_over="slots")
    torch.testing.assert_close(slots_t, dec(feats))  # the slots do not change
    torch.testing.assert_close(slots_s, slots_t)
    for a in (a_tok, a_slot):
        assert a.shape == (2, 4, 3, 5)
        torch.testing.assert_close(a.sum((-1, -2)), torch.ones(2, 4))
    # Oracle: recompute the last layer's logits by hand.
    from svorf.decoder import _flatten_features

    memory, pos = _flatten_features(feats, dec.mem_norm)
    x = dec.init(feats)
    for layer in dec.layers[:-1]:
        x = layer(x, memory, pos)
    last = dec.layers[-1]
    if last.self_attention:
        h = last.norm_sa(x)
        x = x + last.sa(h, h, h)
    _, logits = last.ca(last.norm_ca(x), memory + pos, memory, need_weights=True)
    want_tok = torch.softmax(logits, -1).mean(1)
    want_slot = torch.softmax(logits, 2).mean(1) + 1e-8
    want_slot = want_slot / want_slot.sum(-1, keepdim=True)
    torch.testing.assert_close(a_tok.reshape(2, 4, -1), want_tok)
    torch.testing.assert_close(a_slot.reshape(2, 4, -1), want_slot)
    # centre_temperature T divides those logits before the softmax over slots.
    sharp = SlotTransformerDecoder(cfg.replace(centre_temperature=0.1)).eval()
    sharp.load_state_dict(dec.state_dict())
    _, a_sharp = sharp(feats, return_attn=True, attn_over="slots")
    want_sharp = torch.softmax(logits / 0.1, 2).mean(1) + 1e-8
    want_sharp = want_sharp / want_sharp.sum(-1, keepdim=True)
    torch.testing.assert_close(a_sharp.reshape(2, 4, -1), want_sharp)
    with pytest.raises(ValueError, match="centre_temperature"):
        model_config("smoke", centre_temperature=0.0)
    model = smoke(num_slots=4, slot_locality=1.0, slot_centre="attention_slots")
    _, extra = model.encode_for_render(make_images(1))
    assert extra["slot_attn"].shape[:2] == (1, 4)


@pytest.mark.parametrize("composition", ["slot_guided", "density_weighted"])
def test_bg_achromatic_greys_the_background_slot_only(composition):
    """bg_achromatic: rays rendered by the background slot alone are grey (r = g = b);
    with the foreground slots they are not, and the default config key is unchanged."""
    assert "bg_achromatic" not in ModelConfig().to_dict()
    o, d = make_rays(2, 16)
    only_bg = torch.tensor([[False, False, False, True]] * 2)
    for grey in (False, True):
        model = smoke(composition=composition, bg_achromatic=grey)
        slots = model.encode(make_images(2))
        bg = model.render_rays(slots, o, d, slot_mask=only_bg).rgb
        spread = (bg.amax(-1) - bg.amin(-1)).max().item()
        assert (spread < 1e-5) == grey, spread
        everything = model.render_rays(slots, o, d).rgb
        assert (everything.amax(-1) - everything.amin(-1)).max().item() > 1e-4
    with pytest.raises(ValueError, match="bg_achromatic"):
        ModelConfig(composition="slot_mixer", bg_achromatic=True)


def test_bg_chroma_fade_blends_the_background_towards_grey_over_training(tmp_path):
    """bg_chroma_fade=(p0, p1): full colour before p0, grey after p1, a linear blend between;
    the blend factor is a buffer that a checkpoint carries; the default key is unchanged."""
    assert "bg_chroma_fade" not in ModelConfig().to_dict()
    o, d = make_rays(2, 16)
    only_bg = torch.tensor([[False, False, False, True]] * 2)
    torch.manual_seed(0)
    model = smoke(bg_chroma_fade=(0.2, 0.6))
    assert ModelConfig.from_dict(model.cfg.to_dict()).bg_chroma_fade == (0.2, 0.6)
    slots = model.encode(make_images(2))
    plain = smoke()
    plain.load_state_dict({k: v for k, v in model.state_dict().items() if k != "bg_chroma"})

    def bg_rgb(m):
        return m.render_rays(slots, o, d, slot_mask=only_bg).rgb

    full = bg_rgb(plain)
    grey = full.mean(-1, keepdim=True)
    for progress, c in ((0.0, 1.0), (0.2, 1.0), (0.4, 0.5), (0.6, 0.0), (0.9, 0.0)):
        model.set_progress(progress)
        assert float(model.bg_chroma) == pytest.approx(c)
        torch.testing.assert_close(bg_rgb(model), grey + c * (full - grey), atol=1e-5, rtol=0)
    model.set_progress(0.9)
    torch.save(model.state_dict(), tmp_path / "m.pt")
    again = smoke(bg_chroma_fade=(0.2, 0.6))
    again.load_state_dict(torch.load(tmp_path / "m.pt"))
    assert float(again.bg_chroma) == 0.0
    plain.set_progress(0.9)  # a no-op without the field
    torch.testing.assert_close(bg_rgb(plain), full)
    for bad in ((0.6, 0.2), (0.0, 1.5), (0.1,)):
        with pytest.raises(ValueError, match="bg_chroma_fade"):
            ModelConfig(bg_chroma_fade=bad)
    with pytest.raises(ValueError, match="bg_chroma_fade"):
        ModelConfig(bg_chroma_fade=(0.2, 0.6), bg_achromatic=True)
    with pytest.raises(ValueError, match="bg_chroma_fade"):
        ModelConfig(composition="slot_mixer", bg_chroma_fade=(0.2, 0.6))


def test_slot_locality_narrow_shrinks_the_radius_over_training(tmp_path):
    """slot_locality_narrow=(r_end, p0, p1): the radius is slot_locality before p0, r_end
    after p1, linear between; a model at radius r renders as one built with slot_locality=r;
    the radius is a buffer that a checkpoint carries; the default key is unchanged."""
    assert "slot_locality_narrow" not in ModelConfig().to_dict()
    o, d = make_rays(2, 16)
    kw = {"num_slots": 4, "slot_centre": "anchored", "fg_box": 3.0}
    model = smoke(slot_locality=1.0, slot_locality_narrow=(0.5, 0.2, 0.6), **kw).eval()
    cfg = ModelConfig.from_dict(model.cfg.to_dict())
    assert cfg.slot_locality_narrow == (0.5, 0.2, 0.6)
    weights = {k: v for k, v in model.state_dict().items() if k != "locality_radius"}
    slots = model.encode(make_images(2))
    for progress, r in ((0.0, 1.0), (0.2, 1.0), (0.4, 0.75), (0.6, 0.5), (0.9, 0.5)):
        model.set_progress(progress)
        assert float(model.locality_radius) == pytest.approx(r)
        fixed = smoke(slot_locality=r, **kw).eval()
        fixed.load_state_dict(weights)
        torch.testing.assert_close(
            model.render_rays(slots, o, d).rgb, fixed.render_rays(slots, o, d).rgb
        )
    torch.save(model.state_dict(), tmp_path / "m.pt")
    again = smoke(slot_locality=1.0, slot_locality_narrow=(0.5, 0.2, 0.6), **kw)
    again.load_state_dict(torch.load(tmp_path / "m.pt"))
    assert float(again.locality_radius) == pytest.approx(0.5)
    for bad in ((0.5, 0.6, 0.2), (0.0, 0.2, 0.6), (0.5, 0.2)):
        with pytest.raises(ValueError, match="slot_locality_narrow"):
            ModelConfig(slot_locality=1.0, slot_locality_narrow=bad)
    with pytest.raises(ValueError, match="slot_locality_narrow"):
        ModelConfig(slot_locality_narrow=(0.5, 0.2, 0.6))


def test_slot_locality_xy_ignores_height(monkeypatch):
    """slot_locality_xy=True: the envelope is a vertical cylinder, so moving the centres up
    or down changes nothing while moving them sideways does; with a ball (the default)
    height matters. The default key is unchanged; the field needs slot_locality."""
    assert "slot_locality_xy" not in ModelConfig().to_dict()
    o, d = make_rays(2, 16)
    kw = {"num_slots": 4, "slot_centre": "anchored", "fg_box": 3.0, "slot_locality": 0.5}
    images = make_images(2)
    for xy in (True, False):
        model = smoke(slot_locality_xy=xy, **kw).eval()
        assert ModelConfig.from_dict(model.cfg.to_dict()).slot_locality_xy is xy
        slots = model.encode(images)
        base = model._centres(slots)

        def render(shift, model=model, slots=slots, base=base):
            monkeypatch.setattr(model, "_centres", lambda *a, **k: base + shift)
            return model.render_rays(slots, o, d).rgb

        ref = render(torch.zeros(3))
        up, side = render(torch.tensor([0.0, 0.0, 1.0])), render(torch.tensor([1.0, 0.0, 0.0]))
        assert not torch.allclose(ref, side, atol=1e-5)
        if xy:
            torch.testing.assert_close(ref, up)
        else:
            assert not torch.allclose(ref, up, atol=1e-5)
    with pytest.raises(ValueError, match="slot_locality_xy"):
        ModelConfig(slot_locality_xy=True)


def test_fg_mass_prices_what_the_object_slots_render(tmp_path):
    """fg_mass=(lambda, p0, p1): the loss gains w * mean(acc * (1 - P_bg)) with w ramped from
    0 (before p0) to lambda (from p1 on); the weight is a buffer a checkpoint carries; a
    gradient step on the price alone lowers the object slots' rendered weight; the default
    key is unchanged and bad values are refused."""
    assert "fg_mass" not in ModelConfig().to_dict()
    o, d = make_rays(2, 32)
    model = smoke(fg_mass=(0.5, 0.2, 0.6))
    assert ModelConfig.from_dict(model.cfg.to_dict()).fg_mass == (0.5, 0.2, 0.6)
    plain = smoke()
    plain.load_state_dict({k: v for k, v in model.state_dict().items() if k != "fg_mass_weight"})
    images, target = make_images(2), torch.rand(2, 32, 3)
    torch.manual_seed(0)
    out = model(images, o, d)
    mass = float((out.acc * (1.0 - out.slot_probs[..., -1])).mean().detach())
    assert 0.0 < mass < 1.0
    base, _ = plain.loss(out, target)
    for progress, w in ((0.0, 0.0), (0.2, 0.0), (0.4, 0.25), (0.6, 0.5), (0.9, 0.5)):
        model.set_progress(progress)
        assert float(model.fg_mass_weight) == pytest.approx(w)
        total, parts = model.loss(out, target)
        assert float(parts["fg_mass"]) == pytest.approx(mass, rel=1e-5)
        assert float(total.detach()) == pytest.approx(float(base.detach()) + w * mass, rel=1e-5)
    torch.save(model.state_dict(), tmp_path / "m.pt")
    again = smoke(fg_mass=(0.5, 0.2, 0.6))
    again.load_state_dict(torch.load(tmp_path / "m.pt"))
    assert float(again.fg_mass_weight) == pytest.approx(0.5)

    def fg_mass(m):
        torch.manual_seed(0)
        r = m(images, o, d)
        return (r.acc * (1.0 - r.slot_probs[..., -1])).mean()

    before = fg_mass(model)
    opt = torch.optim.SGD(model.parameters(), lr=0.5)
    opt.zero_grad()
    (model.fg_mass_weight * fg_mass(model)).backward()
    opt.step()
    assert float(fg_mass(model).detach()) < float(before.detach())
    for bad in ((-0.1, 0.2, 0.6), (0.5, 0.6, 0.2), (0.5, 0.2, 1.5), (0.5, 0.2)):
        with pytest.raises(ValueError, match="fg_mass"):
            ModelConfig(fg_mass=bad)
    no_aux = model.render_rays(model.encode(images), o, d, need_aux=False)
    with pytest.raises(ValueError, match="need_aux"):
        model.loss(no_aux, target)


def test_soft_matter_prices_only_half_transparent_object_matter():
    """soft_matter: sum_i share_i alpha_i (1 - alpha_i) per ray, mean over rays: 0 for empty
    space and for solid matter, 1/4 per sample of opacity 1/2, scaled by the object share;
    the last interval ends at the ray's far bound."""
    from svorf.losses import soft_matter

    t = torch.tensor([[[1.0, 2.0, 3.0]]])  # [B=1, R=1, N=3], far bound 4: deltas 1, 1, 1
    far = torch.tensor([[4.0]])
    one = torch.ones(1, 1, 3)
    assert float(soft_matter(torch.zeros(1, 1, 3), t, far, one)) == 0.0
    assert float(soft_matter(torch.full((1, 1, 3), 1e12), t, far, one)) == 0.0
    half = torch.full((1, 1, 3), math.log(2.0))  # alpha = 1/2 on every interval
    assert float(soft_matter(half, t, far, one)) == pytest.approx(0.75)
    share = torch.tensor([[[1.0, 0.5, 0.0]]])
    assert float(soft_matter(half, t, far, share)) == pytest.approx(0.25 * 1.5)
    # Two rays: the mean over rays.
    two = soft_matter(
        torch.cat([half, torch.zeros(1, 1, 3)], 1), t.expand(1, 2, 3), far.expand(1, 2),
        one.expand(1, 2, 3),
    )  # fmt: skip
    assert float(two) == pytest.approx(0.375)
    with pytest.raises(ValueError, match="soft_matter"):
        soft_matter(half, t, far, torch.ones(1, 1, 2))


@pytest.mark.parametrize(
    "name, term", [("fg_binary", "soft_matter"), ("ray_distortion", "ray_distortion")]
)
def test_ramped_price_adds_its_weighted_term(name, term, tmp_path):
    """fg_binary / ray_distortion = (lambda, p0, p1): the loss gains w * the term the render
    returns (the object slots' half-transparent matter / the composed ray's distortion),
    with w ramped from 0 (before p0) to lambda (from p1 on); the weight is a buffer a
    checkpoint carries; a gradient step on the price alone lowers it; the default key is
    unchanged and bad values are refused."""
    assert name not in ModelConfig().to_dict()
    o, d = make_rays(2, 32)
    model = smoke(**{name: (0.5, 0.2, 0.6)})
    assert getattr(ModelConfig.from_dict(model.cfg.to_dict()), name) == (0.5, 0.2, 0.6)
    plain = smoke()
    plain.load_state_dict({k: v for k, v in model.state_dict().items() if k != f"{name}_weight"})
    images, target = make_images(2), torch.rand(2, 32, 3)
    torch.manual_seed(0)
    out = model(images, o, d)
    value = float(getattr(out, term).detach())
    assert value > 0.0
    base, _ = plain.loss(out, target)
    for progress, w in ((0.0, 0.0), (0.2, 0.0), (0.4, 0.25), (0.6, 0.5), (0.9, 0.5)):
        model.set_progress(progress)
        assert float(getattr(model, f"{name}_weight")) == pytest.approx(w)
        total, parts = model.loss(out, target)
        assert float(parts[term]) == pytest.approx(value, rel=1e-6)
        assert float(total.detach()) == pytest.approx(float(base.detach()) + w * value, rel=1e-5)
    torch.save(model.state_dict(), tmp_path / "m.pt")
    again = smoke(**{name: (0.5, 0.2, 0.6)})
    again.load_state_dict(torch.load(tmp_path / "m.pt"))
    assert float(getattr(again, f"{name}_weight")) == pytest.approx(0.5)

    def price(m):
        torch.manual_seed(0)
        return getattr(m(images, o, d), term)

    before = price(model)
    opt = torch.optim.SGD(model.parameters(), lr=0.5)
    opt.zero_grad()
    price(model).backward()
    opt.step()
    assert float(price(model).detach()) < float(before.detach())
    for bad in ((-0.1, 0.2, 0.6), (0.5, 0.6, 0.2), (0.5, 0.2, 1.5), (0.5, 0.2)):
        with pytest.raises(ValueError, match=name):
            ModelConfig(**{name: bad})
    no_aux = model.render_rays(model.encode(images), o, d, need_aux=False)
    assert getattr(no_aux, term) is None
    with pytest.raises(ValueError, match="need_aux"):
        model.loss(no_aux, target)


def test_fg_binary_all_prices_the_background_too():
    """fg_binary_all: the same price with every sample's share 1, so it is at least the
    object-only price of the same render; off by default (key left out); needs fg_binary."""
    assert "fg_binary_all" not in ModelConfig().to_dict()
    o, d = make_rays(2, 32)
    images = make_images(2)
    part = smoke(fg_binary=(0.5, 0.0, 0.0))
    full = smoke(fg_binary=(0.5, 0.0, 0.0), fg_binary_all=True)
    assert ModelConfig.from_dict(full.cfg.to_dict()).fg_binary_all is True
    full.load_state_dict(part.state_dict())
    torch.manual_seed(0)
    a = float(part(images, o, d).soft_matter.detach())
    torch.manual_seed(0)
    b = float(full(images, o, d).soft_matter.detach())
    assert b > a > 0.0
    with pytest.raises(ValueError, match="fg_binary_all"):
        ModelConfig(fg_binary_all=True)


def test_soft_matter_over_a_fixed_length_is_a_line_integral():
    """soft_matter(length=L): alpha over L, each term weighted by delta / L. Splitting an
    interval of uniform matter in two leaves the price unchanged (per interval it grows);
    dense matter in short intervals is free over L (per interval it is not); empty space is
    free; fg_binary_length reaches the model and is refused without fg_binary or <= 0."""
    from svorf.losses import soft_matter

    far = torch.tensor([[4.0]])
    one3, one4 = torch.ones(1, 1, 3), torch.ones(1, 1, 4)
    sig3 = torch.full((1, 1, 3), math.log(2.0) / 0.5)  # alpha over L = 0.5 is 1/2
    sig4 = torch.full((1, 1, 4), math.log(2.0) / 0.5)
    t3 = torch.tensor([[[1.0, 2.0, 3.0]]])
    t4 = torch.tensor([[[1.0, 1.5, 2.0, 3.0]]])  # the first interval split in two
    a = float(soft_matter(sig3, t3, far, one3, 0.5))
    assert a == pytest.approx(0.25 * 3 * 2.0)  # 3 intervals of length 1 = 2 L each
    assert float(soft_matter(sig4, t4, far, one4, 0.5)) == pytest.approx(a)
    assert float(soft_matter(sig4, t4, far, one4)) > float(soft_matter(sig3, t3, far, one3))
    # Dense matter (alpha 0.9999 over L) crossed in short intervals of 0.05.
    t_fine = torch.tensor([[[1.0, 1.05, 1.10]]])
    dense = torch.full((1, 1, 3), 9.2 / 0.5)
    near_far = torch.tensor([[1.15]])
    assert float(soft_matter(dense, t_fine, near_far, one3, 0.5)) < 1e-3
    assert float(soft_matter(dense, t_fine, near_far, one3)) > 0.4
    assert float(soft_matter(torch.zeros(1, 1, 3), t3, far, one3, 0.5)) == 0.0
    assert "fg_binary_length" not in ModelConfig().to_dict()
    cfg = ModelConfig(fg_binary=(0.5, 0.0, 0.0), fg_binary_length=0.1)
    assert ModelConfig.from_dict(cfg.to_dict()).fg_binary_length == 0.1
    o, d = make_rays(2, 32)
    images = make_images(2)
    per_interval = smoke(fg_binary=(0.5, 0.0, 0.0))
    fixed = smoke(fg_binary=(0.5, 0.0, 0.0), fg_binary_length=0.1)
    fixed.load_state_dict(per_interval.state_dict())
    torch.manual_seed(0)
    x = float(per_interval(images, o, d).soft_matter.detach())
    torch.manual_seed(0)
    y = float(fixed(images, o, d).soft_matter.detach())
    assert y > 0.0 and y != pytest.approx(x)
    for bad in ({"fg_binary_length": 0.1}, {"fg_binary": (0.5, 0, 0), "fg_binary_length": 0}):
        with pytest.raises(ValueError, match="fg_binary_length"):
            ModelConfig(**bad)


def test_background_colour_renders_the_scene_without_the_object_region():
    """background_colour: the composed field with each point's density scaled by the
    background's mask, rendered as usual: a ray through a red object point (mask 0) in front
    of a grey floor point (mask 1) gives the floor's grey, the full render the red."""
    from svorf.losses import background_colour
    from svorf.render import volume_render

    t = torch.tensor([[[1.0, 2.0, 3.0]]])  # [B=1, R=1, N=3]
    sigma = torch.tensor([[[50.0, 50.0, 0.0]]])
    rgb = torch.tensor([[[[1.0, 0.0, 0.0], [0.5, 0.5, 0.5], [0.0, 0.0, 1.0]]]])
    m = torch.tensor([[[[1.0, 0.0], [0.0, 1.0], [0.0, 1.0]]]])  # [B, R, N, K]: slot 1 = bg
    is_bg = torch.tensor([[False, True]])
    full, _, _, _ = volume_render(sigma, rgb, t, last_delta=1.0)
    torch.testing.assert_close(full[0, 0], torch.tensor([1.0, 0.0, 0.0]), atol=1e-6, rtol=0)
    bg = background_colour(sigma, rgb, m, t, is_bg, last_delta=1.0)
    torch.testing.assert_close(bg[0, 0], torch.tensor([0.5, 0.5, 0.5]), atol=1e-6, rtol=0)
    # Every point the background's: the full render.
    both = background_colour(
        sigma, rgb, torch.ones_like(m), t, torch.ones(1, 2, dtype=torch.bool), 1.0
    )
    torch.testing.assert_close(both, full)


def test_fg_mass_halo_prices_only_rays_the_background_explains():
    """fg_mass_halo=tau: each ray's fg_mass price is weighted by exp(-|C_bg - C|^2 / tau^2)
    (C_bg = the background's own colour, rendered with need_aux; no gradient through the
    weight): a target equal to C_bg pays the plain price, a target far from it nothing; the
    key is left out when off; it needs fg_mass and bg_outside_fg."""
    assert "fg_mass_halo" not in ModelConfig().to_dict()
    kw = {"fg_zmin": 0.0, "bg_outside_fg": True, "fg_mass": (0.5, 0.0, 0.0)}
    model = smoke(fg_mass_halo=0.1, **kw)
    assert ModelConfig.from_dict(model.cfg.to_dict()).fg_mass_halo == 0.1
    plain = smoke(**kw)
    plain.load_state_dict(model.state_dict())
    model.set_progress(1.0)
    plain.set_progress(1.0)
    o, d = make_rays(2, 32)
    images = make_images(2)
    torch.manual_seed(0)
    out = model(images, o, d)
    assert out.bg_rgb is not None and out.bg_rgb.shape == (2, 32, 3)
    assert plain(images, o, d).bg_rgb is None
    mass = (out.acc * (1.0 - out.slot_probs[..., -1])).detach()
    _, same = model.loss(out, out.bg_rgb.detach().clamp(0, 1))
    torch.testing.assert_close(
        same["fg_mass"], mass.mean().detach(), atol=0.02 * float(mass.mean().detach()), rtol=0
    )
    far = (1.0 - out.bg_rgb.detach()).round()  # each channel >= 0.5 away
    _, none = model.loss(out, far)
    assert float(none["fg_mass"]) < 1e-6 * float(mass.mean())
    target = torch.rand(2, 32, 3)
    gate = torch.exp(-(out.bg_rgb.detach() - target).square().sum(-1) / 0.01)
    total, parts = model.loss(out, target)
    torch.testing.assert_close(parts["fg_mass"], (mass * gate).mean().detach())
    base, _ = smoke(**{**kw, "fg_mass": None}).loss(out, target)
    assert float(total.detach()) == pytest.approx(
        float(base.detach()) + 0.5 * float((mass * gate).mean()), rel=1e-5
    )
    from svorf.losses import halo_gate

    assert out.bg_rgb.requires_grad and not halo_gate(out.bg_rgb, target, 0.1).requires_grad
    with pytest.raises(ValueError, match="need_aux"):
        halo_gate(None, target, 0.1)
    with pytest.raises(ValueError, match="fg_mass_halo"):
        ModelConfig(fg_mass_halo=0.1, fg_zmin=0.0, bg_outside_fg=True)
    with pytest.raises(ValueError, match="fg_mass_halo"):
        ModelConfig(fg_mass_halo=0.1, fg_mass=(0.5, 0.0, 0.0))
    with pytest.raises(ValueError, match="fg_mass_halo"):
        ModelConfig(fg_mass_halo=0.0, **kw)


def test_photo_l1_moves_the_photometric_term_to_absolute_error():
    """photo_l1=(p0, p1): the photometric terms blend from MSE (before p0) to an absolute
    error scaled to MSE's value (from p1 on), so the loss's value is unchanged and its
    gradient is the absolute error's; the stats stay MSE; off by default (key left out)."""
    assert "photo_l1" not in ModelConfig().to_dict()
    o, d = make_rays(2, 32)
    images, target = make_images(2), torch.rand(2, 32, 3)
    model = smoke(photo_l1=(0.2, 0.6))
    assert ModelConfig.from_dict(model.cfg.to_dict()).photo_l1 == (0.2, 0.6)
    plain = smoke()
    plain.load_state_dict({k: v for k, v in model.state_dict().items() if k != "photo_l1_weight"})

    def loss_and_grad(m, progress=None):
        if progress is not None:
            m.set_progress(progress)
        m.zero_grad()
        torch.manual_seed(0)
        out = m(images, o, d)
        total, parts = m.loss(out, target)
        total.backward()
        g = torch.cat([p.grad.flatten() for p in m.parameters() if p.grad is not None])
        return float(total.detach()), parts, g, out

    base, base_parts, g_mse, _ = loss_and_grad(plain)
    for progress, b in ((0.0, 0.0), (0.4, 0.5), (0.9, 1.0)):
        total, parts, g, out = loss_and_grad(model, progress)
        assert float(model.photo_l1_weight) == pytest.approx(b)
        assert total == pytest.approx(base, rel=1e-5)  # the value stays MSE's
        assert float(parts["mse"]) == pytest.approx(float(base_parts["mse"]), rel=1e-6)
        if b == 0.0:
            assert torch.allclose(g, g_mse, atol=1e-7)
        if b == 1.0:
            # the gradient is the absolute error's, scaled by MSE / L1 (fine + coarse)
            assert not torch.allclose(g, g_mse, atol=1e-6)
            dr = torch.autograd.grad(
                model._photometric(out.rgb, target, F.mse_loss(out.rgb, target)),
                out.rgb,
                retain_graph=True,
            )[0]
            l1 = F.l1_loss(out.rgb, target)
            scale = float((F.mse_loss(out.rgb, target) / l1).detach())
            expect = torch.sign(out.rgb - target) * scale / out.rgb.numel()
            assert torch.allclose(dr, expect, atol=1e-9)
    with pytest.raises(ValueError, match="photo_l1 must be"):
        ModelConfig(photo_l1=(0.2,))


def test_slot_relative_fields_move_with_their_centres():
    """slot_relative=True: an object slot's field is gamma(x - c_k), so moving the scene's
    points and every centre by the same step leaves the object slots' densities and colours
    unchanged (the envelope moves too); the background slot keeps gamma(x). Without it the
    object fields change. Off by default and out of the key; needs slot_locality."""
    assert "slot_relative" not in ModelConfig().to_dict()
    step = torch.tensor([0.7, -0.4, 0.3])
    g = torch.Generator().manual_seed(1)
    t = torch.sort(torch.rand(2, 8, 6, generator=g) * 8 + 8, dim=-1).values
    o, d = make_rays(2, 8)
    is_bg = torch.zeros(2, 3, dtype=torch.bool)
    is_bg[:, -1] = True
    for rel in (True, False):
        model = smoke(num_slots=3, slot_locality=0.8, slot_relative=rel).eval()
        assert ModelConfig.from_dict(model.cfg.to_dict()).slot_relative is rel
        slots = model.encode(make_images(2))
        params, c = model.fields.params(slots), model._centres(slots)
        q = model._query(model.query_context(slots, params, o, d, None, is_bg, centres=c), t)
        ctx = model.query_context(slots, params, o + step, d, None, is_bg, centres=c + step)
        moved = model._query(ctx, t)
        same_obj = torch.allclose(q.sigma_k[:, :-1], moved.sigma_k[:, :-1], rtol=1e-4, atol=1e-6)
        assert same_obj is rel
        assert not torch.allclose(q.sigma_k[:, -1], moved.sigma_k[:, -1], atol=1e-5)
    with pytest.raises(ValueError, match="slot_relative"):
        ModelConfig(slot_relative=True)
