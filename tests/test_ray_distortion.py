"""ModelConfig.ray_distortion: Mip-NeRF 360's distortion loss on the composed ray's weights."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from svorf.config import ModelConfig, model_config
from svorf.losses import distortion_loss_reference, ray_distortion
from svorf.model import SVORF
from svorf.render import render_weights


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _model(**kw) -> SVORF:
    torch.manual_seed(0)
    return SVORF(model_config("smoke", num_slots=4, **kw))


def _rays(B: int, R: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    o = torch.tensor([0.0, -10.0, 6.0]).expand(B, R, 3).clone()
    target = (torch.rand(B, R, 3, generator=g) - 0.5) * 6.0
    return o, F.normalize(target - o, dim=-1)


def test_ray_distortion_is_the_distortion_of_the_composed_weights():
    """Equal to the O(N^2) definition on weights whose last interval ends at the ray's far
    bound (normalised by far - near); a ray split between two surfaces pays more than one
    whose weight lies on one surface; bad shapes are refused."""
    g = torch.Generator().manual_seed(1)
    t = torch.sort(6.0 + 14.0 * torch.rand(2, 5, 16, generator=g), dim=-1).values
    sigma = 3.0 * torch.rand(2, 5, 16, generator=g)
    far_r = torch.full((2, 5), 20.0)
    edges = torch.cat([t, far_r[..., None]], dim=-1)
    w = render_weights(sigma, edges[..., 1:] - edges[..., :-1])
    want = distortion_loss_reference(w.double(), ((edges - 6.0) / 14.0).double()).mean()
    got = ray_distortion(sigma, t, far_r, 6.0, 20.0)
    assert float(got) == pytest.approx(float(want), rel=1e-5)

    t1 = torch.linspace(6.0, 19.0, 14)[None, None]
    one, split = torch.zeros(1, 1, 14), torch.zeros(1, 1, 14)
    one[..., 9] = 1e3  # all weight on one surface
    split[..., 3], split[..., 9] = 0.7, 1e3  # a thin halo in front of it
    far1 = torch.full((1, 1), 20.0)
    assert float(ray_distortion(split, t1, far1, 6.0, 20.0)) > float(
        ray_distortion(one, t1, far1, 6.0, 20.0)
    )
    with pytest.raises(ValueError, match="ray_distortion"):
        ray_distortion(sigma, t[..., :-1], far_r, 6.0, 20.0)


def test_ray_distortion_prices_the_composed_spread(tmp_path):
    """ray_distortion=(lambda, p0, p1): the loss gains w * the fine pass's composed
    distortion, w ramped from 0 (before p0) to lambda (from p1 on); the weight is a buffer a
    checkpoint carries; a gradient step on the price alone lowers it; the default key is
    unchanged and bad values are refused."""
    assert "ray_distortion" not in ModelConfig().to_dict()
    o, d = _rays(2, 32)
    model = _model(ray_distortion=(0.5, 0.2, 0.6))
    assert ModelConfig.from_dict(model.cfg.to_dict()).ray_distortion == (0.5, 0.2, 0.6)
    plain = _model()
    state = {k: v for k, v in model.state_dict().items() if k != "ray_distortion_weight"}
    plain.load_state_dict(state)
    images = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    target = torch.rand(2, 32, 3)
    torch.manual_seed(0)
    out = model(images, o, d)
    spread = float(out.ray_distortion.detach())
    assert spread > 0.0
    base, _ = plain.loss(out, target)
    for progress, w in ((0.0, 0.0), (0.2, 0.0), (0.4, 0.25), (0.6, 0.5), (0.9, 0.5)):
        model.set_progress(progress)
        assert float(model.ray_distortion_weight) == pytest.approx(w)
        total, parts = model.loss(out, target)
        assert float(parts["ray_distortion"]) == pytest.approx(spread, rel=1e-6)
        assert float(total.detach()) == pytest.approx(float(base.detach()) + w * spread, rel=1e-5)
    torch.save(model.state_dict(), tmp_path / "m.pt")
    again = _model(ray_distortion=(0.5, 0.2, 0.6))
    again.load_state_dict(torch.load(tmp_path / "m.pt"))
    assert float(again.ray_distortion_weight) == pytest.approx(0.5)

    def price(m):
        torch.manual_seed(0)
        return m(images, o, d).ray_distortion

    before = price(model)
    opt = torch.optim.SGD(model.parameters(), lr=0.5)
    opt.zero_grad()
    price(model).backward()
    opt.step()
    assert float(price(model).detach()) < float(before.detach())
    for bad in ((-0.1, 0.2, 0.6), (0.5, 0.6, 0.2), (0.5, 0.2, 1.5), (0.5, 0.2)):
        with pytest.raises(ValueError, match="ray_distortion"):
            ModelConfig(ray_distortion=bad)
    no_aux = model.render_rays(model.encode(images), o, d, need_aux=False)
    assert no_aux.ray_distortion is None
    with pytest.raises(ValueError, match="need_aux"):
        model.loss(no_aux, target)
