"""Scene editing in 3D (paper 4.4): move an object, swap the background.

Where it sits: on top of ``SVORF.render_rays``; the benchmark's qualitative figures and
users' notebooks call these.

- Moving object k by an affine map M (4x4, world frame): the moved scene at point x shows
  object k's original field at M^-1 x, so slot k's sample points are mapped by M^-1 before
  its field and its composition logit are evaluated (``object_transforms`` of render_rays).
- Changing the background: the background slot (the last) is replaced by another scene's.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .model import SVORF, RenderOutput


def object_transforms_for(slots: Tensor, k: int, transform: Tensor) -> Tensor:
    """Per-slot transforms that move only slot ``k``.

    Args:
        slots: [B, K, D] (for B, K, device).
        k: slot index in [0, K) (K-1 is the background).
        transform: [4, 4] or [B, 4, 4] affine map (world frame) applied to object k.
    Returns:
        [B, K, 4, 4] float32: identity except ``transform`` at slot k.
    """
    B, K, _ = slots.shape
    if not -K <= k < K:
        raise ValueError(f"object_transforms_for: k must be in [0, {K}), got {k}")
    transform = torch.as_tensor(transform, dtype=torch.float32, device=slots.device)
    if transform.shape not in ((4, 4), (B, 4, 4)):
        raise ValueError(
            f"object_transforms_for: transform must be [4, 4] or [B={B}, 4, 4], "
            f"got {tuple(transform.shape)}"
        )
    out = torch.eye(4, device=slots.device).repeat(B, K, 1, 1)
    out[:, k] = transform.expand(B, 4, 4)
    return out


def move_object(
    model: SVORF,
    slots: Tensor,
    k: int,
    transform: Tensor,
    rays_o: Tensor,
    rays_d: Tensor,
    *,
    chunk: int | None = None,
    **render_kw,
) -> RenderOutput:
    """Render the scene with object ``k`` moved by the affine ``transform``.

    Args:
        model: a trained :class:`SVORF` (composition "slot_guided" or "density_weighted").
        slots: [B, K, D] from ``model.encode``.
        k: slot to move.
        transform: [4, 4] or [B, 4, 4] affine map, world frame (e.g. a translation).
        rays_o, rays_d: [B, R, 3] rays to render (world frame, unit directions).
        chunk: if given, render with :meth:`SVORF.render_chunked` (no gradients).
        **render_kw: passed on (slot_mask, need_aux, ...).
    Returns:
        :class:`RenderOutput` of the edited scene.
    """
    tr = object_transforms_for(slots, k, transform)
    if chunk is not None:
        return model.render_chunked(slots, rays_o, rays_d, chunk, object_transforms=tr, **render_kw)
    return model.render_rays(slots, rays_o, rays_d, object_transforms=tr, **render_kw)


def swap_background(slots_a: Tensor, slots_b: Tensor) -> Tensor:
    """slots_a with its background slot (the last) replaced by slots_b's.

    Args:
        slots_a: [B, K, D]; slots_b: [B, K', D] or [1, K', D] (broadcast over B).
    Returns:
        new slots [B, K, D] (slots_a is not modified).
    """
    if slots_a.dim() != 3 or slots_b.dim() != 3 or slots_a.shape[-1] != slots_b.shape[-1]:
        raise ValueError(
            "swap_background: expected slots_a [B, K, D] and slots_b [B or 1, K', D]; got "
            f"{tuple(slots_a.shape)} and {tuple(slots_b.shape)}"
        )
    if slots_b.shape[0] not in (1, slots_a.shape[0]):
        raise ValueError(
            f"swap_background: slots_b batch {slots_b.shape[0]} must be 1 or {slots_a.shape[0]}"
        )
    bg = slots_b[:, -1:].expand(slots_a.shape[0], 1, -1).to(slots_a)
    return torch.cat([slots_a[:, :-1], bg], dim=1)
