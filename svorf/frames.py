"""Scene frames and anchor points of the model's priors: the input camera's azimuth frame
(``ModelConfig.coord_frame``), the fixed slot anchors of ``slot_centre="anchored"`` and the
ground points under the input view's tokens (``slot_centre="attention"``). Used by
:mod:`svorf.model`; pure tensor geometry, no learned parameters."""

from __future__ import annotations

import math

import torch
from torch import Tensor


def azimuth_frame(cam_to_world: Tensor) -> Tensor:
    """Rotation [B, 3, 3] from the world frame to the camera's azimuth frame.

    The azimuth frame is the world frame (z up) rotated about z so that the camera centre
    ``cam_to_world[:, :3, 3]`` lies in the x-z half-plane x >= 0 (azimuth 0): x_frame =
    R @ x_world. A camera on the z axis (azimuth undefined) gives the identity.
    """
    c = cam_to_world[..., :3, 3].float()
    phi = torch.atan2(c[..., 1], c[..., 0])  # atan2(0, 0) = 0
    cos, sin = torch.cos(phi), torch.sin(phi)
    zero, one = torch.zeros_like(phi), torch.ones_like(phi)
    rows = [
        torch.stack([cos, sin, zero], -1),
        torch.stack([-sin, cos, zero], -1),
        torch.stack([zero, zero, one], -1),
    ]
    return torch.stack(rows, -2)


def centre_anchors(k: int, extent: float, height: float) -> Tensor:
    """Fixed anchors [K, 3] of ``slot_centre="anchored"``: the K-1 foreground slots on a
    sunflower (Fibonacci) disk of radius 0.6 ``extent`` at z = ``height`` (slot i at radius
    0.6 e sqrt((i + 0.5) / (K - 1)), angle i x the golden angle: evenly spread, no two
    on one spot); the last (background) slot at the origin (its centre is never used)."""
    n = max(k - 1, 1)
    i = torch.arange(k - 1, dtype=torch.float64)
    r = 0.6 * extent * torch.sqrt((i + 0.5) / n)
    theta = i * math.pi * (3.0 - math.sqrt(5.0))
    fg = torch.stack([r * torch.cos(theta), r * torch.sin(theta), torch.full_like(r, height)], -1)
    return torch.cat([fg, torch.zeros(1, 3, dtype=torch.float64)]).float()


def token_ground_points(
    cam_to_world: Tensor, h: int, w: int, focal: float, height: float, extent: float
) -> Tensor:
    """World points [B, h*w, 3] where the rays through the centres of an h x w token grid of
    the input view meet the plane z = ``height`` (row-major over (y, x), as the tokens).

    Pinhole camera, OpenCV axes, principal point at the image centre, focal length
    ``focal`` x image width. x and y are clamped to [-extent, extent]; a ray that does not
    descend to the plane is taken to meet it at the far edge of that square.

    Args:
        cam_to_world: [B, 4, 4].
    """
    dev = cam_to_world.device
    u = (torch.arange(w, device=dev, dtype=torch.float32) + 0.5) / w - 0.5
    v = (torch.arange(h, device=dev, dtype=torch.float32) + 0.5) / h - 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    d_cam = torch.stack([uu / focal, vv / focal, torch.ones_like(uu)], -1).reshape(-1, 3)
    rot, o = cam_to_world[:, :3, :3].float(), cam_to_world[:, :3, 3].float()
    d = torch.einsum("bij,tj->bti", rot, d_cam)  # [B, T, 3]
    dz = d[..., 2]
    t = (height - o[:, None, 2]) / dz.clamp(max=-1e-6)  # rays going up: far away
    t = torch.where(dz < -1e-6, t, torch.full_like(t, 1e4))
    p = o[:, None] + t[..., None] * d
    xy = p[..., :2].clamp(-extent, extent)
    return torch.cat([xy, torch.full_like(xy[..., :1], height)], -1)
