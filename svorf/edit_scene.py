"""Scene editing of one dataset scene, set against the manipulation split's ground truth.

Where it sits: on top of :mod:`svorf.edit` (``move_object``, ``swap_background``) and
:mod:`svorf.data`. ``svorf edit`` and the benchmark's ``editing`` protocol (through its
adapter) call :func:`edit_scene`; :func:`read_manip_truth` reads the moved and
background-changed ground truth that ``generate --split manip`` writes
(``scenefmt.ManipLayout``).

The slot to move is chosen as uORF does (KovenYu/uORF ``models/uorf_manip_model.py``):
render the unedited input view, take each foreground slot's arg-max mask and pick the slot
whose mask has the highest IoU with the moved object's mask (``_mask_for_moving``) in that
view (:func:`pick_slot`). The last slot is sVORF's background and is never moved.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from scenefmt import (
    MANIP_MASK_ON,
    ManipLayout,
    read_instances,
    read_json,
    read_movement_txt,
    read_rgb,
)
from svorf.data import MultiViewDataset
from svorf.edit import move_object, swap_background
from svorf.model import SVORF

__all__ = ["EditResult", "ManipTruth", "edit_scene", "pick_slot", "read_manip_truth"]


@dataclass(frozen=True)
class ManipTruth:
    """Ground truth of one manipulation scene at one resolution (CPU tensors).

    Attributes:
        instance_id: the moved object (``instance_id`` of the scene JSON).
        offset: ``(dx, dy)`` world units, the movement file's values.
        donor_scene: the scene whose background the changed views show.
        background_differs: whether the donor's background differs from the scene's own.
        moved: float32 [V, 3, H, W] in [0, 1]; moved_ids: int64 [V, H, W].
        changed: float32 [V, 3, H, W]; changed_ids: int64 [V, H, W].
        providing: float32 [V, 3, H, W], the donor scene from this scene's cameras.
        mask_for_moving: bool [V, H, W], the moved object in the unedited views.
    """

    instance_id: int
    offset: tuple[float, float]
    donor_scene: int
    background_differs: bool
    moved: Tensor
    moved_ids: Tensor
    changed: Tensor
    changed_ids: Tensor
    providing: Tensor
    mask_for_moving: Tensor


def _nearest_index(src: int, dst: int) -> Tensor:
    idx = torch.floor((torch.arange(dst, dtype=torch.float64) + 0.5) * (src / dst)).long()
    return idx.clamp_(0, src - 1)


def _rgb(paths: list[Path], hw: tuple[int, int]) -> Tensor:
    """[V, 3, H, W] float32 in [0, 1], area-resized like ``MultiViewDataset``."""
    x = torch.from_numpy(np.stack([read_rgb(p) for p in paths])).permute(0, 3, 1, 2).float()
    if tuple(x.shape[-2:]) != hw:
        x = F.interpolate(x, size=hw, mode="area").round().clamp(0, 255)
    return x / 255.0


def _ids(paths: list[Path], hw: tuple[int, int]) -> Tensor:
    """[V, H, W] int64, nearest-resized like ``MultiViewDataset``."""
    x = torch.from_numpy(np.stack([read_instances(p) for p in paths])).long()
    h, w = x.shape[-2:]
    if (h, w) != hw:
        x = x[:, _nearest_index(h, hw[0])][:, :, _nearest_index(w, hw[1])]
    return x.contiguous()


def read_manip_truth(
    root: str | Path, scene: int, hw: tuple[int, int] | None = None, n_views: int = 4
) -> ManipTruth:
    """Read the manipulation ground truth of ``scene`` from a ``--split manip`` folder.

    Args:
        root: the split folder.
        scene: scene number (``sc%04d``).
        hw: resolution to resize to (None = stored).
        n_views: views per scene.

    Raises:
        ValueError: the scene has no ``manipulation`` record (not a manipulation split).
        OSError: a file is missing.
    """
    lay = ManipLayout(Path(root), n_views=n_views)
    meta = read_json(lay.scene_json(scene))
    rec = meta.get("manipulation")
    if not isinstance(rec, dict):
        raise ValueError(  # noqa: TRY004 - a data problem, not a wrong argument type
            f"{lay.scene_json(scene)}: no 'manipulation' record; make the data with "
            "`generate --split manip`"
        )
    views = range(n_views)
    if hw is None:
        hw = tuple(read_rgb(lay.rgb(scene, 0)).shape[:2])  # type: ignore[assignment]
    assert hw is not None
    masks = _ids([lay.mask_for_moving(scene, v) for v in views], hw) == MANIP_MASK_ON
    return ManipTruth(
        instance_id=int(rec["move"]["instance_id"]),
        offset=read_movement_txt(lay.movement(scene)),
        donor_scene=int(rec["background"]["donor_scene"]),
        background_differs=bool(rec["background"]["differs"]),
        moved=_rgb([lay.moved(scene, v) for v in views], hw),
        moved_ids=_ids([lay.variant_instances(scene, v, "moved") for v in views], hw),
        changed=_rgb([lay.changed(scene, v) for v in views], hw),
        changed_ids=_ids([lay.variant_instances(scene, v, "changed") for v in views], hw),
        providing=_rgb([lay.providing_bg(scene, v) for v in views], hw),
        mask_for_moving=masks,
    )


def pick_slot(labels: Tensor, target: Tensor, num_slots: int) -> tuple[int, list[float]]:
    """uORF's choice of the slot to move: the foreground slot whose arg-max mask has the
    highest IoU with ``target``.

    Args:
        labels: int64 [H, W] arg-max slot of the unedited render of the input view.
        target: bool [H, W] the object to move (``_mask_for_moving`` of the input view).
        num_slots: K; slots ``0 .. K-2`` are candidates (``K-1`` is the background).

    Returns:
        ``(slot, IoU per candidate slot)``; an empty union counts as IoU 0 and ties go to
        the lowest slot (``argmax``).
    """
    if labels.shape != target.shape:
        raise ValueError(
            f"pick_slot: labels {tuple(labels.shape)} and target {tuple(target.shape)} differ"
        )
    if num_slots < 2:
        raise ValueError(f"pick_slot: num_slots must be >= 2, got {num_slots}")
    target = target.bool()
    ious = []
    for k in range(num_slots - 1):
        m = labels == k
        union = int((m | target).sum())
        ious.append(float((m & target).sum()) / union if union else 0.0)
    return int(np.argmax(ious)), ious


@dataclass(frozen=True)
class EditResult:
    """Renders of one scene from its input view, unedited and edited (CPU tensors).

    Attributes:
        recon: float32 [V, 3, H, W] unedited render; recon_labels int64 [V, H, W].
        moved / moved_labels / moved_depth: with the chosen slot moved (None without a move).
        changed / changed_labels: with the background slot swapped (None without a swap).
        slot: the moved slot (None without a move); ious: IoU per candidate slot.
    """

    recon: Tensor
    recon_labels: Tensor
    moved: Tensor | None = None
    moved_labels: Tensor | None = None
    moved_depth: Tensor | None = None
    changed: Tensor | None = None
    changed_labels: Tensor | None = None
    slot: int | None = None
    ious: tuple[float, ...] = ()


def _translation(dx: float, dy: float) -> Tensor:
    t = torch.eye(4)
    t[0, 3], t[1, 3] = float(dx), float(dy)
    return t


@torch.no_grad()
def edit_scene(
    model: SVORF,
    dataset: MultiViewDataset,
    pos: int,
    *,
    input_view: int = 0,
    target_mask: Tensor | None = None,
    offset: tuple[float, float] | None = None,
    donor_image: Tensor | None = None,
    chunk: int = 4096,
) -> EditResult:
    """Render scene ``pos`` of ``dataset`` unedited, with one object moved, and with another
    image's background, all from ``input_view``.

    Args:
        model: a trained model.
        dataset: holds the scene; its resolution is the render resolution.
        pos: scene position in ``dataset``.
        input_view: the view fed to the encoder.
        target_mask: bool [H, W], the object to move in the input view (picks the slot,
            :func:`pick_slot`); with ``offset``.
        offset: ``(dx, dy)`` world units; the slot is moved by this translation.
        donor_image: float32 [3, H, W] in [0, 1]: the background slot is replaced by the
            one encoded from this image (uORF: the donor scene seen from this camera).
        chunk: rays per rendering chunk.

    Returns:
        :class:`EditResult`.
    """
    if (target_mask is None) != (offset is None):
        raise ValueError("edit_scene: target_mask and offset go together (a move needs both)")
    device = next(model.parameters()).device
    was_training = model.training
    model.eval()
    try:
        sv = dataset[pos]
        v, (h, w) = dataset.n_views, dataset.image_hw
        slots, extra = model.encode_for_render(sv.images[input_view : input_view + 1].to(device))
        c2w = sv.cam_to_world[input_view : input_view + 1].to(device)

        def render(s: Tensor, kw: dict, transform: Tensor | None = None, k: int = 0):
            rgb, labels, depth = [], [], []
            for j in range(v):
                o = sv.rays_o[j].reshape(1, h * w, 3).to(device)
                d = sv.rays_d[j].reshape(1, h * w, 3).to(device)
                if transform is None:
                    out = model.render_chunked(s, o, d, chunk, input_c2w=c2w, **kw)
                else:
                    out = move_object(model, s, k, transform, o, d, chunk=chunk,
                                      input_c2w=c2w, **kw)  # fmt: skip
                rgb.append(out.rgb[0].float().cpu().reshape(h, w, 3).permute(2, 0, 1))
                labels.append(out.slot_probs[0].float().cpu().argmax(-1).reshape(h, w))
                depth.append(out.depth[0].float().cpu().reshape(h, w) * sv.z_scale[j])
            return (torch.stack(rgb).clamp(0, 1), torch.stack(labels), torch.stack(depth))

        recon, recon_labels, _ = render(slots, extra)
        res: dict = {"recon": recon, "recon_labels": recon_labels}
        if offset is not None:
            assert target_mask is not None
            slot, ious = pick_slot(recon_labels[input_view], target_mask.cpu(), slots.shape[1])
            moved, moved_labels, moved_depth = render(
                slots, extra, _translation(*offset).to(device), slot
            )
            res.update(moved=moved, moved_labels=moved_labels, moved_depth=moved_depth,
                       slot=slot, ious=tuple(ious))  # fmt: skip
        if donor_image is not None:
            if donor_image.shape != (3, h, w):
                raise ValueError(
                    f"edit_scene: donor_image must be [3, {h}, {w}], got {tuple(donor_image.shape)}"
                )
            slots_b, extra_b = model.encode_for_render(donor_image[None].to(device))
            kw = dict(extra)
            if "slot_attn" in kw and "slot_attn" in extra_b:  # the background's attention too
                kw["slot_attn"] = torch.cat(
                    [kw["slot_attn"][:, :-1], extra_b["slot_attn"][:, -1:]], 1
                )
            changed, changed_labels, _ = render(swap_background(slots, slots_b), kw)
            res.update(changed=changed, changed_labels=changed_labels)
    finally:
        model.train(was_training)
    return EditResult(**res)
