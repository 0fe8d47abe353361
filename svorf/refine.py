"""Test-time slot refinement: a few gradient steps on the slots of one scene, every network
frozen, to reproduce the pixels of the view they were encoded from.

Where this sits: on top of ``svorf.model``; :func:`svorf.predict.predict_scene` calls
:func:`refine_slots` when asked for ``refine_steps`` (``benchmark run ... --refine-slots N``
and the diagnostic ``python -m benchmark.tools.refine`` reach it from there). The encoder
infers slots in one forward pass (amortised inference); refining them on the input view's
own pixels is iterative inference in the spirit of IODINE (Greff et al., 2019). It reads
nothing but the input view (no other view, no mask, no depth), so it stays unsupervised,
and it is off unless asked for: the paper's evaluation is the encoder's slots alone.

Example:
    >>> import torch
    >>> from svorf.config import model_config
    >>> from svorf.model import SVORF
    >>> model = SVORF(model_config("smoke", num_slots=3)).eval()
    >>> img = torch.rand(1, 3, 32, 32)
    >>> slots = model.encode(img)
    >>> o = torch.tensor([0.0, -12.0, 6.0]).expand(64, 3)
    >>> d = torch.nn.functional.normalize(-o + 0.3 * torch.randn(64, 3), dim=-1)
    >>> refined, losses = refine_slots(model, slots, o, d, torch.rand(64, 3), steps=3, rays=32)
    >>> refined.shape == slots.shape, len(losses)
    (True, 3)
"""

from __future__ import annotations

import torch
from torch import Tensor

from svorf.model import SVORF

__all__ = ["REFINE_LR", "REFINE_RAYS", "refine_batch", "refine_slots"]

#: Adam learning rate of the slots (slot vectors are O(1) per component). Chosen on training
#: scenes of a cpu-scale model (docs/notes/cpu_recipe.md, "The refinement's own learning
#: rate"): at 50 steps 2e-2 gave about twice the ARI gain of 3e-3, the rate before
#: 2026-12-05 (reports of ``--refine-slots`` from before then refined at 3e-3).
REFINE_LR = 2e-2
#: Random pixels of the fitted view(s) per refinement step.
REFINE_RAYS = 1024


def _check_centres(model: SVORF, who: str) -> None:
    if model.cfg.slot_centre.startswith("attention") and model.cfg.slot_locality is not None:
        raise ValueError(
            f"{who}: slot_centre={model.cfg.slot_centre!r} takes its centres from the "
            "encoder's attention, not the slots; refinement needs 'anchored' or 'learned'"
        )


def refine_batch(
    model: SVORF,
    slots: Tensor,
    rays_o: Tensor,
    rays_d: Tensor,
    target_rgb: Tensor,
    *,
    steps: int,
    lr: float = REFINE_LR,
    input_c2w: Tensor | None = None,
    slot_mask: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Refine a batch of scenes' slots on the given rays: the target of
    ``TrainConfig.slot_distill`` and the slots ``TrainConfig.refine_train`` renders from.

    Adam on the slot vectors alone, ``steps`` steps, every step on all ``R`` rays of each
    scene, deterministic samples, photometric MSE. The model's parameters get no gradient
    (only the slots' gradient is computed, so the parameters' ``requires_grad`` and any
    graph already built through them are left alone) and its mode is unchanged.

    Args:
        model: as for :func:`refine_slots`.
        slots: [B, K, D]; detached before use.
        rays_o, rays_d, target_rgb: [B, R, 3].
        steps, lr: Adam steps (>= 1) and learning rate.
        input_c2w: [B, 4, 4] each scene's input camera.
        slot_mask: [B, K] as for :meth:`SVORF.render_rays`.

    Returns:
        ``(refined slots [B, K, D] detached, float32; [2] the MSE of the first and the
        last step, each before its update)``.
    """
    if steps < 1 or not lr > 0:
        raise ValueError(f"refine_batch: steps must be >= 1 and lr > 0, got {steps}, {lr}")
    _check_centres(model, "refine_batch")
    target = target_rgb.to(device=slots.device, dtype=torch.float32)
    s = slots.detach().float().clone().requires_grad_(True)
    opt = torch.optim.Adam([s], lr=lr)
    losses = []
    with torch.enable_grad():
        for _ in range(steps):
            out = model.render_rays(
                s, rays_o, rays_d, need_aux=False, input_c2w=input_c2w, slot_mask=slot_mask
            )
            loss = ((out.rgb.float() - target) ** 2).mean()
            losses.append(loss.detach())
            (s.grad,) = torch.autograd.grad(loss, [s])
            opt.step()
    return s.detach(), torch.stack([losses[0], losses[-1]])


def refine_slots(
    model: SVORF,
    slots: Tensor,
    rays_o: Tensor,
    rays_d: Tensor,
    target_rgb: Tensor,
    *,
    steps: int,
    lr: float = REFINE_LR,
    rays: int = REFINE_RAYS,
    input_c2w: Tensor | None = None,
    seed: int = 0,
) -> tuple[Tensor, list[float]]:
    """Optimise one scene's slots to reproduce ``target_rgb`` (the networks stay as they are).

    Adam on the slot vectors alone, ``steps`` steps of ``rays`` pixels drawn (with a
    generator seeded by ``seed``, so a refinement is reproducible) from the given pixels,
    photometric MSE of the rendered colour, deterministic samples along each ray (as the
    evaluation renders them). The model's parameters get no gradient and its train/eval mode
    is restored.

    Args:
        model: a trained model with per-slot centres from the slots (``slot_centre``
            "anchored" or "learned", or no slot locality).
        slots: [1, K, D] the encoder's slots of one scene.
        rays_o, rays_d, target_rgb: [N, 3] the pixels fitted (world-frame rays, colours in
            [0, 1]); for the benchmark's refinement, every pixel of the input view.
        steps: Adam steps (>= 1).
        lr, rays: learning rate and pixels per step.
        input_c2w: [1, 4, 4] the input camera (as for :meth:`SVORF.render_rays`).
        seed: the pixel draws' seed.

    Returns:
        ``(refined slots [1, K, D] detached, the MSE of each step)``.
    """
    if steps < 1 or rays < 1 or not lr > 0:
        raise ValueError(
            f"refine_slots: steps and rays must be >= 1 and lr > 0, got {steps}, {rays}, {lr}"
        )
    if slots.dim() != 3 or slots.shape[0] != 1:
        raise ValueError(f"refine_slots: slots must be [1, K, D], got {tuple(slots.shape)}")
    _check_centres(model, "refine_slots")
    n = rays_o.shape[0]
    if rays_d.shape != rays_o.shape or target_rgb.shape != rays_o.shape or rays_o.shape[-1] != 3:
        raise ValueError(
            f"refine_slots: rays_o {tuple(rays_o.shape)}, rays_d {tuple(rays_d.shape)} and "
            f"target_rgb {tuple(target_rgb.shape)} must all be [N, 3]"
        )
    device = slots.device
    o, d, rgb = (x.to(device=device, dtype=torch.float32) for x in (rays_o, rays_d, target_rgb))
    gen = torch.Generator().manual_seed(int(seed))
    was = model.training
    grad_on = [p.requires_grad for p in model.parameters()]
    model.eval()
    try:
        for p in model.parameters():
            p.requires_grad_(False)
        with torch.enable_grad():
            s = torch.nn.Parameter(slots.detach().float().clone())
            opt = torch.optim.Adam([s], lr=lr)
            losses = []
            for _ in range(steps):
                idx = torch.randint(0, n, (min(rays, n),), generator=gen).to(device)
                out = model.render_rays(
                    s, o[idx][None], d[idx][None], need_aux=False, input_c2w=input_c2w
                )
                loss = ((out.rgb[0].float() - rgb[idx]) ** 2).mean()
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                losses.append(float(loss.detach()))
    finally:
        for p, r in zip(model.parameters(), grad_on, strict=True):
            p.requires_grad_(r)
        model.train(was)
    return s.detach().to(slots.dtype), losses
