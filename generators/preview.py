"""Contact sheet of a split folder: RGB | coloured instance ids | depth, per view.

Data flow: split folder (``scenefmt``) -> :func:`contact_sheet` (uint8 image) ->
PNG. ``generate preview`` renders a few scenes into ``DIR/split`` and writes
``DIR/preview.png``, with a legend strip below (tile order and a depth colour bar).

Depth convention (shared with ``svorf render``): viridis with near = bright yellow,
far = dark purple; no hit (inf) is black.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scenefmt import Manifest, SplitLayout, read_depth_exr, read_instances, read_json, read_rgb

#: Instance colours (id 0 = black background).
_PALETTE = np.array(
    [[0, 0, 0], [230, 25, 75], [60, 180, 75], [255, 225, 25], [0, 130, 200], [245, 130, 48],
     [145, 30, 180], [70, 240, 240], [240, 50, 230], [210, 245, 60], [250, 190, 212],
     [0, 128, 128], [220, 190, 255], [170, 110, 40]]
    + [[255, 255, 255]] * 242,
    dtype=np.uint8,
)  # fmt: skip


def colour_ids(ids: np.ndarray) -> np.ndarray:
    """uint8 [H, W] ids -> uint8 [H, W, 3] colours."""
    return _PALETTE[ids]


#: The fixed depth range of the preview's colour scale (world units).
DEPTH_NEAR, DEPTH_FAR = 6.0, 20.0


def colour_depth(depth: np.ndarray, near: float = DEPTH_NEAR, far: float = DEPTH_FAR) -> np.ndarray:
    """float [H, W] planar depth -> uint8 [H, W, 3]: viridis, ``near`` = bright yellow,
    ``far`` = dark purple (clipped outside); inf = black."""
    import matplotlib

    x = np.clip((np.nan_to_num(depth, posinf=far) - near) / (far - near), 0, 1)
    rgb = (matplotlib.colormaps["viridis"](1 - x)[..., :3] * 255).astype(np.uint8)
    rgb[~np.isfinite(depth)] = 0
    return rgb


def contact_sheet(root: str | Path, n_scenes: int | None = None, gap: int = 2) -> np.ndarray:
    """One row per scene, per view three tiles (RGB, ids, depth). uint8 [H', W', 3]."""
    root = Path(root)
    mf = Manifest.from_json(read_json(root / "manifest.json"))
    layout = SplitLayout(root, n_views=mf.n_views)
    scenes = layout.scene_indices()[: n_scenes if n_scenes is not None else None]
    if not scenes:
        raise ValueError(f"{root}: no scenes to preview")
    rows = []
    for s in scenes:
        tiles = []
        for v in range(layout.n_views):
            for t in (read_rgb(layout.rgb(s, v)), colour_ids(read_instances(layout.instances(s, v))),
                      colour_depth(read_depth_exr(layout.depth(s, v)))):  # fmt: skip
                tiles.append(np.pad(t, ((gap, gap), (gap, gap), (0, 0)), constant_values=255))
        rows.append(np.concatenate(tiles, axis=1))
    return np.concatenate(rows, axis=0)


def with_legend(sheet: np.ndarray, near: float = DEPTH_NEAR, far: float = DEPTH_FAR) -> np.ndarray:
    """``sheet`` with a white strip below: the tile order and a depth colour bar labelled
    'near' (bright) ... 'far' (dark) in world units. uint8 [H', W, 3]."""
    from PIL import Image, ImageDraw, ImageFont

    w = sheet.shape[1]
    size = 12
    try:
        font = ImageFont.load_default(size=size)
    except (TypeError, ValueError, OSError, ImportError):  # pragma: no cover - no FreeType
        font = ImageFont.load_default()
    im = Image.new("RGB", (w, 2 * size + 14), (255, 255, 255))
    draw = ImageDraw.Draw(im)
    draw.text((4, 4), "rows: scenes; per view: RGB | ids | depth", fill=(0, 0, 0), font=font)
    bar_w = max(40, min(200, w // 3))
    x0 = w - bar_w - 8
    ramp = np.linspace(near, far, bar_w)[None, :].repeat(size, axis=0)
    im.paste(Image.fromarray(colour_depth(ramp, near, far)), (x0, 4))
    ty = 4 + size + 2
    draw.text((x0, ty), f"near {near:g}", fill=(0, 0, 0), font=font, anchor="la")
    draw.text((x0 + bar_w, ty), f"far {far:g}", fill=(0, 0, 0), font=font, anchor="ra")
    return np.concatenate([sheet, np.asarray(im)], axis=0)


def write_contact_sheet(root: str | Path, path: str | Path, n_scenes: int | None = None) -> Path:
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(with_legend(contact_sheet(root, n_scenes))).save(path)
    return path
