"""Contact sheets of procedural chairs and textures, for eyeballing the generators.

Not used by the dataset pipeline; a developer tool:
``python -m assets_procedural.preview --out /tmp/assets_preview`` writes
``chairs.png`` (shaded 3/4 views of a grid of chair ids) and ``textures.png``
(the default texture pool). Matplotlib is imported lazily (Agg backend).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    return plt, Poly3DCollection


def chair_sheet(ids: list[int], path: Path, cols: int = 4) -> Path:
    """Render shaded 3/4 views (front-left, looking down ~20 deg) of ``ids`` into a PNG."""
    from assets_procedural.chairs import chair_mesh, chair_params

    plt, Poly3DCollection = _plt()
    rows = (len(ids) + cols - 1) // cols
    fig = plt.figure(figsize=(3.2 * cols, 3.6 * rows), dpi=80)
    light = np.array([-0.4, -0.7, 0.6])
    light /= np.linalg.norm(light)
    for n, aid in enumerate(ids):
        ax = fig.add_subplot(rows, cols, n + 1, projection="3d")
        mesh = chair_mesh(aid)
        tri = mesh.vertices[mesh.faces]
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True) + 1e-12
        shade = 0.25 + 0.75 * np.clip(nrm @ light, 0, 1)
        colors = np.clip(shade[:, None] * np.array([0.75, 0.55, 0.35]), 0, 1)
        ax.add_collection3d(Poly3DCollection(tri, facecolors=colors, edgecolors="none"))
        h = mesh.extents[2]
        ax.set_xlim(-0.6, 0.6)
        ax.set_ylim(-0.6, 0.6)
        ax.set_zlim(0, max(1.2, h))
        ax.set_box_aspect((1.2, 1.2, max(1.2, h)))
        ax.view_init(elev=18, azim=-60)  # camera in front-left (-y is the front)
        ax.set_axis_off()
        p = chair_params(aid)
        ax.set_title(
            f"{aid}: {p.leg_style}/{p.back_style}/{p.arm_style}\n{p.seat_shape}", fontsize=8
        )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def texture_sheet(ids: list[int], path: Path, size: int = 128, cols: int = 10) -> Path:
    """Tile ``texture_image(id, size)`` for ``ids`` into one PNG (ids labelled)."""
    from PIL import Image, ImageDraw

    from assets_procedural.textures import texture_image, texture_params

    rows = (len(ids) + cols - 1) // cols
    sheet = Image.new("RGB", (cols * (size + 4), rows * (size + 16)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for n, tid in enumerate(ids):
        r, c = divmod(n, cols)
        x, y = c * (size + 4), r * (size + 16)
        sheet.paste(Image.fromarray(texture_image(tid, size)), (x, y + 14))
        draw.text((x + 2, y + 1), f"{tid} {texture_params(tid).family}", fill=(0, 0, 0))
    path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(path)
    return path


def main(argv: list[str] | None = None) -> None:
    """CLI: write ``chairs.png`` and ``textures.png`` into ``--out``."""
    from assets_procedural.textures import N_TEXTURES_DEFAULT

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("/tmp/assets_preview"))
    ap.add_argument("--first", type=int, default=0, help="first chair id")
    ap.add_argument("--n", type=int, default=16, help="number of chairs")
    args = ap.parse_args(argv)
    print(chair_sheet(list(range(args.first, args.first + args.n)), args.out / "chairs.png"))
    print(texture_sheet(list(range(N_TEXTURES_DEFAULT)), args.out / "textures.png"))


if __name__ == "__main__":
    main()
