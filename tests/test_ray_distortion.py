"""svorf.losses.ray_distortion: Mip-NeRF 360's distortion loss on the composed ray's weights.

The loss term of ``ModelConfig.ray_distortion`` (its ramp, buffer and checks:
tests/test_model.py, ``test_ramped_price_adds_its_weighted_term``)."""

from __future__ import annotations

import pytest
import torch

from svorf.losses import distortion_loss_reference, ray_distortion
from svorf.render import render_weights


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


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
