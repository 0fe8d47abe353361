"""Per-scene prediction of a trained sVORF, and the default held-out evaluation.

Where this sits: on top of ``svorf.model`` and ``svorf.data``. :func:`predict_scene`
encodes one view of a dataset scene and renders every view (``svorf render``, the
recipe's metrics and the benchmark adapter use it); :func:`default_eval` is the held-out
evaluation ``svorf.train.train`` runs when no ``eval_fn`` is given. Both names are
re-exported by ``svorf.train``, their old home. A prediction is a :class:`ScenePrediction`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from svorf.data import MultiViewDataset
from svorf.model import SVORF
from svorf.refine import REFINE_LR, refine_slots

__all__ = ["ScenePrediction", "default_eval", "predict_scene"]


@dataclass(frozen=True)
class ScenePrediction:
    """What :func:`predict_scene` renders for one scene (CPU tensors).

    V views of H x W pixels, K slots.

    Attributes:
        rgb: float32 [V, H, W, 3] in [0, 1].
        depth_z: float32 [V, H, W] planar depth (world units, converted from the rendered
            distance ``depth_t`` with the dataset's ``z_scale``).
        depth_t: float32 [V, H, W] expected distance along the unit ray direction.
        acc: float32 [V, H, W] accumulated opacity.
        slot_probs: float32 [V, H, W, K] rendered soft slot masks (rows sum to 1).
        labels: int64 [V, H, W] arg-max slot of ``slot_probs``.
        input_view: the view the model encoded.
        scene: the scene number (not the dataset position).
    """

    rgb: Tensor
    depth_z: Tensor
    depth_t: Tensor
    acc: Tensor
    slot_probs: Tensor
    labels: Tensor
    input_view: int
    scene: int


@torch.no_grad()
def predict_scene(
    model: SVORF,
    dataset: MultiViewDataset,
    scene: int,
    input_view: int = 0,
    chunk: int = 4096,
    slots_scene: int | None = None,
    refine_steps: int = 0,
    refine_lr: float = REFINE_LR,
) -> ScenePrediction:
    """Encode one view of a scene and render every view at the dataset's resolution.

    Args:
        model: a trained model (any device; left in the train/eval mode it came in).
        dataset: the scenes; its resolution is the render resolution.
        scene: dataset position (``0 <= scene < len(dataset)``; ``dataset.scene_ids``
            maps positions to scene numbers).
        input_view: the view fed to the encoder.
        chunk: rays per rendering chunk (memory bound).
        slots_scene: if given, the slots come from this scene's ``input_view`` instead
            (placed in ``scene``'s input-camera frame): a control that shows how much of a
            segmentation does not depend on the scene (a fixed spatial tiling scores the
            same with another scene's slots; a decomposition does not).
        refine_steps: if > 0, the encoder's slots are refined this many steps on the
            pixels of the view they were encoded from before rendering
            (:func:`svorf.refine.refine_slots`; 0 = the encoder's slots, the paper's
            evaluation).
        refine_lr: the slots' Adam learning rate of that refinement.

    Returns:
        The :class:`ScenePrediction` of every view (V = ``dataset.n_views``).
    """
    if not 0 <= scene < len(dataset):
        raise ValueError(f"scene position must be in [0, {len(dataset)}), got {scene}")
    if not 0 <= input_view < dataset.n_views:
        raise ValueError(f"input_view must be in [0, {dataset.n_views}), got {input_view}")
    device = next(model.parameters()).device
    was_training = model.training
    model.eval()
    try:
        sv = dataset[scene]
        v, (h, w) = dataset.n_views, dataset.image_hw
        src = sv if slots_scene is None else dataset[slots_scene]
        slots, extra = model.encode_for_render(src.images[input_view : input_view + 1].to(device))
        input_c2w = sv.cam_to_world[input_view : input_view + 1].to(device)
        if refine_steps > 0:  # on the slots' own view, in its own input-camera frame
            slots, _ = refine_slots(
                model,
                slots,
                src.rays_o[input_view].reshape(-1, 3),
                src.rays_d[input_view].reshape(-1, 3),
                src.images[input_view].permute(1, 2, 0).reshape(-1, 3),
                steps=refine_steps,
                lr=refine_lr,
                input_c2w=src.cam_to_world[input_view : input_view + 1].to(device),
                seed=int(src.scene),
            )
        rgb, depth_t, acc, probs = [], [], [], []
        for j in range(v):
            o = sv.rays_o[j].reshape(1, h * w, 3).to(device)
            d = sv.rays_d[j].reshape(1, h * w, 3).to(device)
            out = model.render_chunked(slots, o, d, chunk, input_c2w=input_c2w, **extra)
            rgb.append(out.rgb[0].float().cpu())
            depth_t.append(out.depth[0].float().cpu())
            acc.append(out.acc[0].float().cpu())
            probs.append(out.slot_probs[0].float().cpu())
    finally:
        model.train(was_training)
    k = probs[0].shape[-1]
    depth_t_t = torch.stack(depth_t).view(v, h, w)
    slot_probs = torch.stack(probs).view(v, h, w, k)
    return ScenePrediction(
        rgb=torch.stack(rgb).view(v, h, w, 3),
        depth_z=depth_t_t * sv.z_scale,
        depth_t=depth_t_t,
        acc=torch.stack(acc).view(v, h, w),
        slot_probs=slot_probs,
        labels=slot_probs.argmax(-1),
        input_view=int(input_view),
        scene=int(sv.scene),
    )


def default_eval(model: SVORF, dataset: MultiViewDataset, max_scenes: int = 4) -> dict[str, float]:
    """Minimal held-out evaluation (no segmentation metrics: plug those in via ``eval_fn``).

    Renders the first ``max_scenes`` scenes from input view 0 and returns
    ``psnr_input`` (view 0), ``psnr_novel`` (the other views; PSNR of the mean MSE),
    ``depth_abs_err`` (mean |depth_z - gt| over pixels with finite ground truth) and
    ``n_scenes``.
    """
    n = min(max_scenes, len(dataset))
    mse_in, mse_nv, derr = [], [], []
    for i in range(n):
        p = predict_scene(model, dataset, i, input_view=0)
        gt = dataset.images(i).permute(0, 2, 3, 1)
        err = ((p.rgb - gt) ** 2).mean(dim=(1, 2, 3))
        mse_in.append(err[0])
        if len(err) > 1:
            mse_nv.append(err[1:].mean())
        gtd = dataset[i].depth_z
        ok = torch.isfinite(gtd)
        if ok.any():
            derr.append((p.depth_z[ok] - gtd[ok]).abs().mean())

    def psnr(xs: list[Tensor]) -> float:
        return (
            float(-10.0 * torch.log10(torch.stack(xs).mean().clamp_min(1e-10))) if xs else math.nan
        )

    return {
        "psnr_input": psnr(mse_in),
        "psnr_novel": psnr(mse_nv),
        "depth_abs_err": float(torch.stack(derr).mean()) if derr else math.nan,
        "n_scenes": float(n),
    }
