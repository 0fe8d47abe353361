"""PNG figures of one scene's predictions (``svorf render``).

Where this sits: ``svorf.train.predict_scene`` renders a scene; this module turns the
result plus the dataset's ground truth into 8-bit images: per view the ground-truth
RGB, the rendered RGB (a reconstruction for the input view, a novel view otherwise),
predicted and ground-truth masks in colour and predicted and ground-truth planar
depth, and one grid with the views as rows and those six panels as columns, labelled,
with a depth colour bar.

Depth convention (shared with ``generate preview``): viridis with near = bright yellow,
far = dark purple; no hit (inf) is black. Both depth columns of a scene share one range.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont
from torch import Tensor

from scenefmt import write_rgb
from svorf.data import MultiViewDataset
from svorf.predict import ScenePrediction

__all__ = [
    "COLUMN_LABELS",
    "PALETTE",
    "colorize_depth",
    "colorize_labels",
    "save_scene_figures",
    "to_uint8",
]

#: Distinct colours for labels 1..; label 0 (ground-truth background) and the last slot
#: (the model's background slot) are drawn in BACKGROUND.
PALETTE = np.array(
    [
        (230, 25, 75),
        (60, 180, 75),
        (255, 225, 25),
        (0, 130, 200),
        (245, 130, 48),
        (145, 30, 180),
        (70, 240, 240),
        (240, 50, 230),
        (210, 245, 60),
        (250, 190, 212),
        (0, 128, 128),
        (220, 190, 255),
        (170, 110, 40),
        (255, 250, 200),
        (128, 0, 0),
        (170, 255, 195),
        (128, 128, 0),
        (255, 215, 180),
        (0, 0, 128),
        (128, 128, 128),
    ],
    dtype=np.uint8,
)
BACKGROUND = np.array((40, 40, 40), dtype=np.uint8)
COLUMNS = ("gt", "render", "mask_pred", "mask_gt", "depth_pred", "depth_gt")
#: The grid's column headings, in :data:`COLUMNS` order.
COLUMN_LABELS = ("gt", "render", "predicted mask", "true mask", "predicted depth", "true depth")


def to_uint8(rgb: Tensor | np.ndarray) -> np.ndarray:
    """Float [H, W, 3] in [0, 1] -> uint8 [H, W, 3] (clipped, rounded)."""
    x = rgb.detach().cpu().numpy() if isinstance(rgb, Tensor) else np.asarray(rgb)
    return np.clip(np.round(x * 255.0), 0, 255).astype(np.uint8)


def colorize_labels(labels: Tensor | np.ndarray, background: int | None = 0) -> np.ndarray:
    """Integer labels [H, W] -> uint8 [H, W, 3]; ``background`` (if not None) is dark grey.

    Label ``k`` gets ``PALETTE[(k - 1) % len]`` when a background label 0 exists, else
    ``PALETTE[k % len]``, so ground-truth object k and slot k are coloured consistently
    within each kind of map.
    """
    lab = labels.cpu().numpy() if isinstance(labels, Tensor) else np.asarray(labels)
    lab = lab.astype(np.int64)
    shift = 1 if background == 0 else 0
    out = PALETTE[(lab - shift) % len(PALETTE)].copy()
    if background is not None:
        out[lab == background] = BACKGROUND
    return out


def colorize_depth(depth: Tensor | np.ndarray, vmin: float, vmax: float) -> np.ndarray:
    """Depth [H, W] -> uint8 [H, W, 3] with viridis, near (``vmin``) = bright yellow, far
    (``vmax``) = dark purple; inf/nan are black (``generate preview``'s convention)."""
    from matplotlib import colormaps  # lazy: only figures need matplotlib

    d = depth.cpu().numpy() if isinstance(depth, Tensor) else np.asarray(depth)
    ok = np.isfinite(d)
    x = np.clip((np.where(ok, d, vmax) - vmin) / max(vmax - vmin, 1e-9), 0.0, 1.0)
    rgb = (colormaps["viridis"](1.0 - x)[..., :3] * 255.0).round().astype(np.uint8)
    rgb[~ok] = 0
    return rgb


def _font(size: int) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    try:
        return ImageFont.load_default(size=size)  # Pillow's bundled font (needs FreeType)
    except (TypeError, ValueError, OSError, ImportError):  # pragma: no cover - no FreeType
        return ImageFont.load_default()


def _fit_font(labels: list[str], width: int, size: int):
    """The largest font (<= ``size``) whose widest label fits in ``width`` pixels."""
    while True:
        font = _font(size)
        draw = ImageDraw.Draw(Image.new("RGB", (1, 1)))
        if size <= 6 or max(draw.textlength(t, font=font) for t in labels) <= width:
            return font
        size -= 1


def _annotate_grid(
    grid: np.ndarray, n_rows: int, row_labels: list[str], lo: float, hi: float
) -> np.ndarray:
    """Add column headings above, view labels on the left and a depth colour bar under
    the two depth columns (near = bright ... far = dark, in world units)."""
    h, w = grid.shape[:2]
    tile_w, tile_h = w // len(COLUMNS), h // n_rows
    size = max(8, min(16, tile_w // 9))
    font = _fit_font(list(COLUMN_LABELS), tile_w - 4, size)
    rfont = _font(size)
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    gutter = int(max(probe.textlength(t, font=rfont) for t in row_labels)) + 8
    head = size + 8
    foot = 2 * size + 16
    bg = (255, 255, 255)
    im = Image.new("RGB", (gutter + w, head + h + foot), bg)
    im.paste(Image.fromarray(grid), (gutter, head))
    draw = ImageDraw.Draw(im)
    for c, text in enumerate(COLUMN_LABELS):
        x = gutter + c * tile_w + tile_w / 2
        draw.text((x, head / 2), text, fill=(0, 0, 0), font=font, anchor="mm")
    for r, text in enumerate(row_labels):
        draw.text(
            (4, head + r * tile_h + tile_h / 2), text, fill=(0, 0, 0), font=rfont, anchor="lm"
        )
    # Colour bar under the depth columns: left = near (lo), right = far (hi).
    c0 = COLUMNS.index("depth_pred")
    x0, x1 = gutter + c0 * tile_w + 4, gutter + (c0 + 2) * tile_w - 4
    y0 = head + h + 4
    ramp = np.linspace(lo, hi, max(2, x1 - x0))[None, :].repeat(size, axis=0)
    im.paste(Image.fromarray(colorize_depth(ramp, lo, hi)), (x0, y0))
    ty = y0 + size + 2
    draw.text((x0, ty), f"near {lo:.2f}", fill=(0, 0, 0), font=rfont, anchor="la")
    draw.text((x1, ty), f"far {hi:.2f}", fill=(0, 0, 0), font=rfont, anchor="ra")
    draw.text((x0 - 6, y0 + size / 2), "depth", fill=(0, 0, 0), font=rfont, anchor="rm")
    return np.asarray(im)


def _depth_range(*maps: Tensor) -> tuple[float, float]:
    for m in maps:
        ok = torch.isfinite(m)
        if ok.any():
            vals = m[ok].float()
            lo, hi = float(vals.min()), float(vals.max())
            return lo, hi if hi > lo else lo + 1.0
    return 0.0, 1.0


def save_scene_figures(
    pred: ScenePrediction,
    dataset: MultiViewDataset,
    position: int,
    out_dir: str | os.PathLike,
    *,
    grid_min_size: int = 128,
) -> list[Path]:
    """Write the PNGs of one predicted scene.

    Args:
        pred: what :func:`svorf.predict.predict_scene` returned.
        dataset: the dataset the prediction was made on (ground truth).
        position: the scene's dataset position.
        out_dir: folder to write into (created).
        grid_min_size: the grid's tiles are up-scaled (nearest) to at least this size.

    Returns:
        Paths written: ``input.png``, per view ``vXX_{gt,render,mask_pred,mask_gt,
        depth_pred,depth_gt}.png`` and ``grid.png`` (views as rows, labelled; the six
        panels as columns, headed by :data:`COLUMN_LABELS`; a depth colour bar below).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sv = dataset[position]
    k = pred.slot_probs.shape[-1]
    lo, hi = _depth_range(sv.depth_z, pred.depth_z)
    written: list[Path] = []
    rows = []
    inp = int(pred.input_view)
    write_rgb(out / "input.png", to_uint8(sv.images[inp].permute(1, 2, 0)))
    written.append(out / "input.png")
    for v in range(dataset.n_views):
        panels = {
            "gt": to_uint8(sv.images[v].permute(1, 2, 0)),
            "render": to_uint8(pred.rgb[v]),
            # Predicted labels: the last slot is the background slot.
            "mask_pred": colorize_labels(pred.labels[v] + 1, background=k),
            "mask_gt": colorize_labels(sv.instances[v], background=0),
            "depth_pred": colorize_depth(pred.depth_z[v], lo, hi),
            "depth_gt": colorize_depth(sv.depth_z[v], lo, hi),
        }
        kind = "recon" if v == inp else "novel"
        for name in COLUMNS:
            p = out / f"v{v:02d}_{name}{'_' + kind if name == 'render' else ''}.png"
            write_rgb(p, panels[name])
            written.append(p)
        rows.append(np.concatenate([panels[c] for c in COLUMNS], axis=1))
    grid = np.concatenate(rows, axis=0)
    h = dataset.image_hw[0]
    scale = max(1, -(-grid_min_size // h))
    if scale > 1:
        grid = np.asarray(
            Image.fromarray(grid).resize(
                (grid.shape[1] * scale, grid.shape[0] * scale), Image.NEAREST
            )
        )
    row_labels = [f"view {v}" + (" (input)" if v == inp else "") for v in range(dataset.n_views)]
    grid = _annotate_grid(grid, dataset.n_views, row_labels, lo, hi)
    write_rgb(out / "grid.png", grid)
    written.append(out / "grid.png")
    return written
