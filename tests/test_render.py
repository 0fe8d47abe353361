"""Ray sampling, volume rendering and the connectivity loss against slow references and
closed forms (svorf.render, svorf.losses)."""

from __future__ import annotations

import math

import pytest
import torch

from svorf.losses import connectivity_loss, distortion_loss, distortion_loss_reference
from svorf.render import (
    clip_rays_to_box,
    ray_box_intersect,
    render_weights,
    sample_pdf,
    sample_stratified,
    volume_render,
)


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    # 2 shared cores: oversubscribed intra-op threads make tiny ops 10-50x slower.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def render_reference(sigma, rgb, t, last_delta):
    """Float64 loop: T_i = prod_{j<i} exp(-sigma_j delta_j), w_i = T_i (1 - exp(-sigma_i delta_i))."""
    sigma, rgb, t = sigma.double(), rgb.double(), t.double()
    *batch, N = t.shape
    flat_s, flat_c, flat_t = sigma.reshape(-1, N), rgb.reshape(-1, N, 3), t.reshape(-1, N)
    out_c, out_d, out_w, out_a = [], [], [], []
    for s, c, tt in zip(flat_s, flat_c, flat_t):
        trans, col, dep, acc, ws = 1.0, torch.zeros(3, dtype=torch.float64), 0.0, 0.0, []
        for i in range(N):
            delta = (tt[i + 1] - tt[i]).item() if i + 1 < N else last_delta
            alpha = 1.0 - math.exp(-s[i].item() * delta)
            w = trans * alpha
            ws.append(w)
            col += w * c[i]
            dep += w * tt[i].item()
            acc += w
            trans *= 1.0 - alpha
        out_c.append(col)
        out_d.append(dep)
        out_w.append(torch.tensor(ws, dtype=torch.float64))
        out_a.append(acc)
    return (
        torch.stack(out_c).reshape(*batch, 3),
        torch.tensor(out_d, dtype=torch.float64).reshape(batch),
        torch.stack(out_w).reshape(*batch, N),
        torch.tensor(out_a, dtype=torch.float64).reshape(batch),
    )


@pytest.mark.parametrize("last_delta", [1e10, 0.7])
def test_volume_render_matches_float64_loop(last_delta):
    g = torch.Generator().manual_seed(0)
    sigma = torch.rand(3, 5, 16, generator=g) * 3.0
    rgb = torch.rand(3, 5, 16, 3, generator=g)
    t = torch.sort(torch.rand(3, 5, 16, generator=g) * 10 + 2, dim=-1).values
    got = volume_render(sigma, rgb, t, last_delta=last_delta)
    ref = render_reference(sigma, rgb, t, last_delta)
    for a, b in zip(got, ref):
        assert a.dtype == torch.float32
        torch.testing.assert_close(a.double(), b, atol=1e-5, rtol=1e-5)


def test_volume_render_per_ray_last_delta_and_bad_shapes():
    t = torch.linspace(0, 1, 8).expand(2, 8)
    far = torch.tensor([1.5, 3.0])
    _, _, w, _ = volume_render(torch.ones(2, 8), torch.rand(2, 8, 3), t, last_delta=far - t[:, -1])
    ref_w = render_reference(torch.ones(1, 8), torch.rand(1, 8, 3), t[:1], 0.5)[2]
    torch.testing.assert_close(w[:1].double(), ref_w, atol=1e-6, rtol=1e-6)
    with pytest.raises(ValueError, match="volume_render"):
        volume_render(torch.ones(2, 8), torch.rand(2, 7, 3), t)


def test_constant_density_slab_closed_form():
    """Slab [a, b] of density s: acc = 1 - exp(-s L), E[t w] has a closed form."""
    a, b, s = 3.0, 5.0, 0.8
    step = 0.005
    t = torch.arange(0, 10, step, dtype=torch.float64).float()[None]
    sigma = ((t >= a - 1e-4) & (t < b - 1e-4)).float() * s
    rgb = torch.ones(1, t.shape[1], 3)
    _, depth, _, acc = volume_render(sigma, rgb, t, last_delta=step)
    L = b - a
    e = math.exp(-s * L)
    assert acc.item() == pytest.approx(1 - e, abs=1e-4)
    # int_a^b t s exp(-s (t - a)) dt
    expected_depth = a * (1 - e) + (1 - e) / s - L * e
    assert depth.item() == pytest.approx(expected_depth, abs=2 * step)


def test_opaque_sphere_depth_is_entry_distance():
    g = torch.Generator().manual_seed(1)
    centre, radius = torch.tensor([0.3, -0.2, 0.0]), 2.0
    R, N, near, far = 64, 256, 2.0, 18.0
    o = torch.tensor([0.0, 0.0, -10.0]).expand(R, 3)
    target = centre + (torch.rand(R, 3, generator=g) - 0.5) * 2.0  # aim inside the sphere
    d = torch.nn.functional.normalize(target - o, dim=-1)
    t = sample_stratified(near, far, R, N, perturb=True, generator=g)
    x = o[:, None] + t[..., None] * d[:, None]
    inside = (x - centre).norm(dim=-1) < radius
    sigma = inside.float() * 1e6
    _, depth, _, acc = volume_render(sigma, torch.rand(R, N, 3, generator=g), t)
    # analytic entry: |o + t d - c|^2 = r^2
    oc = o - centre
    bq = (oc * d).sum(-1)
    disc = bq**2 - (oc.square().sum(-1) - radius**2)
    assert (disc > 0).all()
    t_entry = -bq - disc.sqrt()
    spacing = (far - near) / N
    assert torch.all((depth - t_entry).abs() <= 2 * spacing)
    torch.testing.assert_close(acc, torch.ones(R))


def test_extreme_inputs_are_finite():
    t = torch.sort(torch.rand(4, 32) * 1e4, dim=-1).values.requires_grad_(False)
    sigma = torch.full((4, 32), 1e6, requires_grad=True)
    rgb = torch.rand(4, 32, 3, requires_grad=True)
    for dtype in (torch.float32, torch.bfloat16):
        sig_mixed = sigma * torch.tensor([1.0, 0.0] * 16)  # zeros between huge densities
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=dtype == torch.bfloat16):
            out = volume_render(sig_mixed.to(dtype), rgb.to(dtype), t.to(dtype))
        assert all(torch.isfinite(o).all() for o in out)
        assert out[0].dtype == torch.float32
        sum(o.sum() for o in out).backward()
        assert torch.isfinite(sigma.grad).all() and torch.isfinite(rgb.grad).all()
        sigma.grad = rgb.grad = None
    w = render_weights(torch.tensor([[float("inf"), 1.0]]), torch.tensor([[1e10, 1e10]]))
    assert torch.isfinite(w).all() and w[0, 0] == 1.0


def test_sample_stratified_bounds_and_order():
    near = torch.tensor([[2.0, 5.0], [6.0, 7.0]])
    far = near + torch.tensor([[1.0, 2.0], [3.0, 0.5]])
    for perturb in (False, True):
        t = sample_stratified(near, far, 2, 16, perturb)
        assert t.shape == (2, 2, 16)
        assert torch.all(t >= near[..., None]) and torch.all(t <= far[..., None])
        assert torch.all(t[..., 1:] >= t[..., :-1])
    t = sample_stratified(6.0, 20.0, 5, 4, perturb=False)
    torch.testing.assert_close(t[0], torch.tensor([7.75, 11.25, 14.75, 18.25]))


def test_sample_pdf_sorted_in_range_and_concentrated():
    g = torch.Generator().manual_seed(0)
    bins = torch.linspace(6.0, 20.0, 33).expand(3, 33).contiguous()
    weights = torch.full((3, 32), 1e-3)
    weights[:, 10] = 5.0
    weights = weights.requires_grad_(True)
    for det in (True, False):
        s = sample_pdf(bins, weights, 64, det=det, generator=g)
        assert s.shape == (3, 64) and not s.requires_grad
        assert torch.all(s[:, 1:] >= s[:, :-1])
        assert torch.all((s >= 6.0) & (s <= 20.0))
        in_peak = ((s >= bins[:, 10:11]) & (s <= bins[:, 11:12])).float().mean()
        assert in_peak > 0.9
    # all-zero weights: uniform, still valid
    s = sample_pdf(bins, torch.zeros(3, 32), 16, det=True)
    assert torch.all((s >= 6.0) & (s <= 20.0)) and torch.isfinite(s).all()
    assert weights.grad is None


def test_ray_box_clipping():
    o = torch.tensor([[0.0, -12.0, 3.0], [0.0, -12.0, 3.0], [10.0, 10.0, 10.0], [0.0, 0.0, -9.0]])
    d = torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    d[1] = torch.nn.functional.normalize(torch.tensor([0.0, 1.0, -0.1]), dim=0)
    near, far = clip_rays_to_box(o, d, 6.0, 20.0, 4.5)
    assert near[0].item() == pytest.approx(7.5) and far[0].item() == pytest.approx(16.5)
    # the miss keeps [near, far]; the axis-parallel ray is guarded (no inf / nan)
    assert near[2].item() == 6.0 and far[2].item() == 20.0
    assert near[3].item() == pytest.approx(6.0) and far[3].item() == pytest.approx(13.5)
    t = sample_stratified(near, far, 4, 32, perturb=True)
    x = o[:, None] + t[..., None] * d[:, None]
    assert (x[[0, 1, 3]].abs() <= 4.5 + 1e-4).all()
    _, _, hit = ray_box_intersect(o, d, 4.5)
    assert hit.tolist() == [True, True, False, True]


def test_ray_box_clipping_to_a_z_slab():
    """box_z: the samples of a CLEVR camera's ray lie between the floor and the ceiling."""
    e = math.radians(40.0)
    o = torch.tensor([[12.4 * math.cos(e), 0.0, 12.4 * math.sin(e)], [0.0, 0.0, -9.0]])
    d = torch.stack([-o[0] / o[0].norm(), torch.tensor([0.0, 0.0, 1.0])])
    near, far = clip_rays_to_box(o, d, 6.0, 20.0, 4.5, (-0.25, 2.0))
    # the ray towards the origin enters at z = 2 and leaves at z = -0.25 (slant 1 / sin 40)
    z_near, z_far = (o[0, 2] + near[0] * d[0, 2]).item(), (o[0, 2] + far[0] * d[0, 2]).item()
    assert z_near == pytest.approx(2.0, abs=1e-5) and z_far == pytest.approx(-0.25, abs=1e-5)
    assert far[0].item() - near[0].item() == pytest.approx(2.25 / math.sin(e), rel=1e-5)
    # the vertical ray from below crosses the slab: [8.75, 11]
    assert near[1].item() == pytest.approx(8.75) and far[1].item() == pytest.approx(11.0)
    # without z_range: the cube, as before
    cube = clip_rays_to_box(o, d, 6.0, 20.0, 4.5)
    assert cube[1][1].item() == pytest.approx(13.5)
    # a ray towards the horizon passes over the slab: it keeps the cube's interval
    h = torch.tensor([[-12.0, 0.0, 3.0]]), torch.tensor([[1.0, 0.0, 0.0]])
    assert clip_rays_to_box(*h, 6.0, 20.0, 4.5, (-0.25, 2.0)) == clip_rays_to_box(
        *h, 6.0, 20.0, 4.5
    )


def test_clip_floor_z_extends_rays_that_see_the_floor_beyond_the_box():
    """clip_floor_z: a ray leaving the box through a side wall goes on to the ground plane."""
    o = torch.tensor([9.5, 0.0, 8.0])
    targets = torch.tensor([
        [-8.0, 0.0, 0.0],  # floor beyond the far wall (x = -4.5): extended to it
        [0.0, 0.0, 0.0],   # floor at the centre: the box's interval already reaches it
        [-60.0, 0.0, 0.0],  # floor beyond far: extended to far only
    ])  # fmt: skip
    d = torch.nn.functional.normalize(targets - o, dim=-1)
    d = torch.cat([d, torch.tensor([[0.0, 0.6, 0.8]])])  # upward: never reaches the floor
    oo = o.expand(4, 3)
    near0, far0 = clip_rays_to_box(oo, d, 6.0, 20.0, 4.5)
    near, far = clip_rays_to_box(oo, d, 6.0, 20.0, 4.5, floor_z=0.0)
    assert torch.equal(near, near0)
    assert far[0].item() == pytest.approx((targets[0] - o).norm().item(), rel=1e-5)
    assert far0[0].item() < far[0].item()  # it used to end on the box wall
    assert far[1].item() == far0[1].item() and far[3].item() == far0[3].item()
    assert far[2].item() == pytest.approx(20.0)
    from svorf.config import ModelConfig

    with pytest.raises(ValueError, match="clip_to_box"):
        ModelConfig(clip_floor_z=0.0)
    assert "clip_floor_z" not in ModelConfig().to_dict()  # off: run keys stay as they were
    assert ModelConfig(clip_to_box=True, clip_floor_z=0.0).to_dict()["clip_floor_z"] == 0.0
    from svorf.config import model_config
    from svorf.model import SVORF

    torch.manual_seed(0)
    cfg = model_config("smoke", num_slots=3, clip_to_box=True, clip_floor_z=0.0)
    out = SVORF(cfg).eval()(torch.rand(1, 3, cfg.image_size, cfg.image_size), oo[None], d[None])
    assert torch.isfinite(out.rgb).all() and torch.isfinite(out.depth).all()
    assert out.depth[0, 0].item() <= far[0].item() + 1e-3  # may reach the floor beyond the wall


def test_clip_floor_front_samples_the_floor_seen_before_the_box():
    """clip_floor_front: a ray that meets the ground plane in front of the box (and would
    enter the box under the floor) is sampled from near to the plane."""
    o = torch.tensor([9.5, 0.0, 8.0])
    targets = torch.tensor([
        [6.0, 0.0, 0.0],   # floor in front of the near wall (x = 4.5)
        [0.0, 0.0, 0.0],   # floor at the centre: inside the box, unchanged
        [-8.0, 0.0, 0.0],  # floor beyond the far wall: clip_floor_z's extension, unchanged
    ])  # fmt: skip
    d = torch.nn.functional.normalize(targets - o, dim=-1)
    oo = o.expand(3, 3)
    near0, far0 = clip_rays_to_box(oo, d, 6.0, 20.0, 4.5, floor_z=0.0)
    near, far = clip_rays_to_box(oo, d, 6.0, 20.0, 4.5, floor_z=0.0, floor_front=True)
    hit = (targets[0] - o).norm().item()
    assert near0[0].item() > hit + 1.0  # without it: samples in the box, under the floor
    assert near[0].item() == pytest.approx(6.0) and far[0].item() == pytest.approx(hit, rel=1e-5)
    assert torch.equal(near[1:], near0[1:]) and torch.equal(far[1:], far0[1:])
    with pytest.raises(ValueError, match="floor_front needs floor_z"):
        clip_rays_to_box(oo, d, 6.0, 20.0, 4.5, floor_front=True)
    from svorf.config import ModelConfig

    with pytest.raises(ValueError, match="clip_floor_front=True needs clip_floor_z"):
        ModelConfig(clip_to_box=True, clip_floor_front=True)
    assert "clip_floor_front" not in ModelConfig(clip_to_box=True, clip_floor_z=0.0).to_dict()
    cfg = ModelConfig(clip_to_box=True, clip_floor_z=0.0, clip_floor_front=True)
    assert cfg.to_dict()["clip_floor_front"] is True
    assert ModelConfig.from_json(cfg.to_json()) == cfg


def test_box_z_needs_clip_to_box_and_an_ordered_range():
    from svorf.config import ModelConfig

    assert ModelConfig(clip_to_box=True, box_z=[-0.25, 2.0]).box_z == (-0.25, 2.0)
    cfg = ModelConfig(clip_to_box=True, box_z=(-0.25, 2.0))
    assert ModelConfig.from_json(cfg.to_json()) == cfg
    assert "box_z" not in ModelConfig().to_dict()  # off: earlier config keys unchanged
    for clip, box_z in [
        (False, (-0.25, 2.0)),
        (True, (2.0, -0.25)),
        (True, (-5.0, 2.0)),
        (True, (1.0,)),
    ]:
        with pytest.raises(ValueError, match="box_z"):
            ModelConfig(clip_to_box=clip, box_z=box_z)


def test_distortion_linear_equals_quadratic():
    g = torch.Generator().manual_seed(0)
    w = torch.rand(4, 7, 24, generator=g, dtype=torch.float64)
    w = w / w.sum(-1, keepdim=True) * torch.rand(4, 7, 1, generator=g, dtype=torch.float64)
    edges = torch.sort(torch.rand(4, 7, 25, generator=g, dtype=torch.float64), dim=-1).values
    torch.testing.assert_close(
        distortion_loss(w, edges).double(),
        distortion_loss_reference(w, edges),
        atol=1e-6,
        rtol=1e-5,
    )
    # a single delta at one interval costs only its own width / 3
    w1 = torch.zeros(1, 4)
    w1[0, 2] = 1.0
    e1 = torch.tensor([[0.0, 0.1, 0.2, 0.5, 1.0]])
    assert distortion_loss(w1, e1).item() == pytest.approx(0.1)


def test_connectivity_uses_each_slot_alone_and_masks():
    g = torch.Generator().manual_seed(0)
    B, K, R, N = 2, 3, 5, 12
    near, far = 6.0, 20.0
    t = torch.sort(torch.rand(B, R, N, generator=g) * 14 + 6, dim=-1).values
    far_r = torch.full((B, R), far)
    sigma_k = torch.rand(B, K, R, N, generator=g) * 2
    loss = connectivity_loss(sigma_k, t, far_r, near, far)
    # reference: slot by slot, weights from the slot's density alone, far-bounded last delta
    vals = []
    for b in range(B):
        for k in range(K):
            _, _, w, _ = render_reference(sigma_k[b, k], torch.zeros(R, N, 3), t[b], 0.0)
            w = w.clone()
            for r in range(R):  # last interval = far - t_N
                _, _, wr, _ = render_reference(
                    sigma_k[b, k, r : r + 1],
                    torch.zeros(1, N, 3),
                    t[b, r : r + 1],
                    far - t[b, r, -1].item(),
                )
                w[r] = wr[0]
            edges = (torch.cat([t[b], far_r[b, :, None]], -1).double() - near) / (far - near)
            vals.append(distortion_loss_reference(w, edges).mean())
    assert loss.item() == pytest.approx(torch.stack(vals).mean().item(), rel=1e-4)
    mask = torch.tensor([[True, False, True], [True, True, True]])
    masked = connectivity_loss(sigma_k, t, far_r, near, far, mask)
    keep = [0, 2, 3, 4, 5]
    assert masked.item() == pytest.approx(torch.stack(vals)[keep].mean().item(), rel=1e-4)
