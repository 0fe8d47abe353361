"""``svorf edit``: move an object of a scene or swap its background, beside the ground truth.

    svorf edit RUN --data DIR --scene I [--move-object K --offset DX DY]
               [--swap-background DONOR] [--out DIR] [--force] [--input-view V]
               [--chunk N] [--device auto|cpu|cuda]

Where it sits: a subcommand of ``svorf`` (:mod:`svorf.cli` registers it) over
:func:`svorf.edit_scene.edit_scene`. ``--move-object K`` is the scene's object
``instance_id`` K: the slot to move is the foreground slot whose rendered mask overlaps
K's mask in the input view best (IoU; the manipulation split's ``_mask_for_moving`` when K
is its moved object, else the instance ids). ``--swap-background DONOR`` takes the
background slot from scene DONOR of the same folder: from its ``_providing_bg`` view (the
donor seen from this camera) when DONOR is the manipulation split's donor, else from
DONOR's own input view. Writes ``RUN/edit/PRESET-SPLIT/scNNNN/`` (or ``--out``):
``vNN_{recon,moved,changed}.png`` and their label maps, the ground truth beside them
(``vNN_{moved,changed}_gt.png``) when the data is a manipulation split with the same edit,
and ``edit.json`` (chosen slot, IoUs, PSNR per view against that ground truth).
"""

from __future__ import annotations

import argparse
import json
import math
import re
from pathlib import Path

import torch

from scenefmt import MANIP_SPLIT, DatasetError, Manifest, atomic_write_json, read_json, write_rgb

__all__ = ["add_edit_parser", "cmd_edit"]

#: Files ``svorf edit`` writes (removed from the output folder first under ``--force``).
_EDIT_FILES = re.compile(r"(edit\.json|v\d\d_\w+\.png)")


def add_edit_parser(sub) -> None:
    """Add the ``edit`` subcommand to the ``svorf`` sub-parsers ``sub``."""
    e = sub.add_parser("edit", help="move an object or swap the background of one scene")
    e.add_argument("run", help="run folder written by `svorf train`")
    e.add_argument("--data", required=True, help="split folder holding the scene")
    e.add_argument("--scene", type=int, required=True, help="scene number (sc%%04d)")
    e.add_argument("--move-object", type=int, metavar="K", help="instance id of the object to move")
    e.add_argument("--offset", type=float, nargs=2, metavar=("DX", "DY"),
                   help="translation on the floor, world units (with --move-object)")  # fmt: skip
    e.add_argument("--swap-background", type=int, metavar="DONOR",
                   help="scene number whose background replaces this scene's")  # fmt: skip
    e.add_argument("--out", help="output folder (default RUN/edit/PRESET-SPLIT/scNNNN)")
    e.add_argument("--force", action="store_true", help="overwrite an output folder with files")
    e.add_argument("--input-view", type=int, default=0, help="view fed to the encoder")
    e.add_argument("--chunk", type=int, default=4096, help="rays per rendering chunk")
    e.add_argument("--device", default="auto", help="auto (default), cpu, cuda or cuda:N")


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float | None:
    mse = float(((a - b) ** 2).mean())
    return None if mse <= 0 else -10.0 * math.log10(mse)


def _check_args(a: argparse.Namespace) -> None:
    if a.scene < 0:
        raise ValueError(f"--scene must be >= 0, got {a.scene}")
    if a.chunk < 1:
        raise ValueError(f"--chunk must be >= 1, got {a.chunk}")
    if (a.move_object is None) != (a.offset is None):
        raise ValueError("--move-object K and --offset DX DY go together; pass both")
    if a.move_object is None and a.swap_background is None:
        raise ValueError("nothing to edit; pass --move-object K --offset DX DY and/or "
                         "--swap-background DONOR")  # fmt: skip
    if a.offset is not None and not all(math.isfinite(x) for x in a.offset):
        raise ValueError(f"--offset must be finite numbers, got {a.offset}")
    if a.swap_background is not None and a.swap_background == a.scene:
        raise ValueError("--swap-background must name another scene than --scene")


def _read_manifest(data: str) -> Manifest | None:
    """The manifest of split folder ``data``, None for a folder without one (uORF layout).

    A manifest that is not a :class:`scenefmt.Manifest` fails with the message the dataset
    loader (``svorf.data``) gives for it.
    """
    path = Path(data) / "manifest.json"
    if not path.is_file():
        return None
    raw = read_json(path)
    try:
        return Manifest.from_json(raw)
    except ValueError as e:
        raise DatasetError(f"{path}: {e}; run `generate verify {Path(data)}`") from e


def _out_dir(a: argparse.Namespace, meta: Manifest | None) -> Path:
    if a.out:
        out = Path(a.out)
    else:
        root = Path(a.data).resolve()
        preset = (meta.preset if meta is not None else "") or root.parent.name
        split = (meta.split if meta is not None else "") or root.name
        name = re.sub(r"[^A-Za-z0-9._-]+", "_", f"{preset}-{split}").strip("._") or "data"
        out = Path(a.run) / "edit" / name / f"sc{a.scene:04d}"
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not a.force:
            raise ValueError(f"{out} already holds files; pass --force to overwrite them or "
                             "--out DIR to write elsewhere")  # fmt: skip
        for p in out.iterdir():
            if p.is_file() and _EDIT_FILES.fullmatch(p.name):
                p.unlink()
    return out


def cmd_edit(a: argparse.Namespace) -> int:
    """Run ``svorf edit`` (bad input raises ValueError / DatasetError: one line, status 2)."""
    from svorf.data import MultiViewDataset
    from svorf.edit_scene import edit_scene, read_manip_truth
    from svorf.train import load_run, resolve_device
    from svorf.viz import colorize_labels, to_uint8

    _check_args(a)
    meta = _read_manifest(a.data)
    device = resolve_device(a.device)
    model, info = load_run(a.run, device=device)
    hw = info.dataset.get("image_hw") or info.model.image_size
    ds = MultiViewDataset(a.data, image_size=hw, scenes=[a.scene])
    if not 0 <= a.input_view < ds.n_views:
        raise ValueError(f"--input-view must be in [0, {ds.n_views}), got {a.input_view}")
    truth = None
    if meta is not None and meta.split == MANIP_SPLIT:
        truth = read_manip_truth(a.data, a.scene, ds.image_hw, ds.n_views)
    same_move = (
        truth is not None
        and a.move_object == truth.instance_id
        and all(abs(x - y) < 1e-6 for x, y in zip(a.offset or (), truth.offset))
    )
    same_donor = truth is not None and a.swap_background == truth.donor_scene
    target = offset = donor = None
    if a.move_object is not None:
        sv = ds[0]
        ids = sv.instances[a.input_view]
        if truth is not None and a.move_object == truth.instance_id:
            target = truth.mask_for_moving[a.input_view]
        else:
            target = ids == a.move_object
        if not target.any():
            raise ValueError(f"object {a.move_object} is not visible in view {a.input_view} of "
                             f"scene {a.scene}; pick another --move-object or --input-view")  # fmt: skip
        offset = (float(a.offset[0]), float(a.offset[1]))
    if a.swap_background is not None:
        if same_donor:
            donor = truth.providing[a.input_view]
        else:
            dd = MultiViewDataset(a.data, image_size=ds.image_hw, scenes=[a.swap_background])
            donor = dd[0].images[a.input_view]
    out = _out_dir(a, meta)
    res = edit_scene(model, ds, 0, input_view=a.input_view, target_mask=target, offset=offset,
                     donor_image=donor, chunk=a.chunk)  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    record: dict = {"scene": a.scene, "input_view": a.input_view, "run": str(a.run),
                    "data": str(a.data), "resolution": list(ds.image_hw)}  # fmt: skip
    for v in range(ds.n_views):
        write_rgb(out / f"v{v:02d}_recon.png", to_uint8(res.recon[v].permute(1, 2, 0)))
        for name, rgb, lab, gt, has_gt in (
            ("moved", res.moved, res.moved_labels, truth and truth.moved, same_move),
            ("changed", res.changed, res.changed_labels, truth and truth.changed, same_donor),
        ):
            if rgb is None:
                continue
            write_rgb(out / f"v{v:02d}_{name}.png", to_uint8(rgb[v].permute(1, 2, 0)))
            write_rgb(out / f"v{v:02d}_{name}_labels.png", colorize_labels(lab[v], None))
            if has_gt:
                write_rgb(out / f"v{v:02d}_{name}_gt.png", to_uint8(gt[v].permute(1, 2, 0)))
    if res.moved is not None:
        record["move"] = {"instance_id": a.move_object, "offset": list(offset or ()),
                          "slot": res.slot, "ious": list(res.ious), "ground_truth": same_move}  # fmt: skip
        if same_move:
            record["move"]["psnr"] = [
                _psnr(res.moved[v], truth.moved[v]) for v in range(ds.n_views)
            ]
            record["move"]["psnr_no_edit"] = [_psnr(res.recon[v], truth.moved[v])
                                              for v in range(ds.n_views)]  # fmt: skip
    if res.changed is not None:
        record["background"] = {"donor_scene": a.swap_background, "ground_truth": same_donor,
                                "donor_image": "providing_bg" if same_donor else "donor input view"}  # fmt: skip
        if same_donor:
            record["background"]["psnr"] = [_psnr(res.changed[v], truth.changed[v])
                                            for v in range(ds.n_views)]  # fmt: skip
            record["background"]["psnr_no_edit"] = [_psnr(res.recon[v], truth.changed[v])
                                                    for v in range(ds.n_views)]  # fmt: skip
    atomic_write_json(out / "edit.json", json.loads(json.dumps(record)))
    slot = f"slot {res.slot} moved (IoU {max(res.ious):.2f}); " if res.slot is not None else ""
    gt = "with ground truth" if (same_move or same_donor) else "no ground truth for this edit"
    print(f"svorf edit: {slot}wrote renders to {out} ({gt}; {out / 'edit.json'})")
    return 0
