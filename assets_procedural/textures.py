"""Procedural floor and wall textures: a texture is a pure function of an integer id.

Where this sits: the Room presets' scene sampler picks a background id;
:func:`background_params` maps it to a (floor, wall) pair of texture ids;
``assets_procedural.cache`` writes ``texture_image(id, size)`` to a PNG once and
the Blender backend loads that PNG as an image texture. No torch, no bpy.

Families (:data:`FAMILIES`): wood planks (grain from stretched fractal noise),
tiles (grout lines, per-tile colour jitter), checker, stone/cobble (periodic
Voronoi cells), fabric/carpet (fine noise plus a weave), marble (turbulent veins),
plain painted wall (subtle noise) and brick (running bond). The family of id
``t`` is ``FAMILIES[t % len(FAMILIES)]``, so any 8 consecutive ids cover all
families; colours, scales and noise come from
``numpy.random.default_rng([TEXTURE_SALT, t])``.

Images are ``uint8 [size, size, 3]`` sRGB. Feature sizes are defined on the unit
square, so one id looks the same at any ``size`` (only sharper). All noise,
stripes and cell patterns are periodic on the unit square, so the textures tile
seamlessly (up to the per-row stagger of planks, which is also periodic).
Vectorised numpy (+ a scipy KD-tree for cells): ~10-60 ms per 256x256 texture.
"""

from __future__ import annotations

import colorsys
import functools
from dataclasses import dataclass
from numbers import Integral

import numpy as np

from assets_procedural.ids import check_id

TEXTURE_GENERATOR_VERSION = "textures-1.0.0"
"""Bump whenever the same id would produce different pixels (invalidates caches)."""

TEXTURE_SALT = 0x7E87
BACKGROUND_SALT = 0xB6

FAMILIES = ("wood", "tiles", "checker", "stone", "fabric", "marble", "painted", "brick")
FLOOR_FAMILIES = ("wood", "tiles", "checker", "stone", "fabric", "marble")
WALL_FAMILIES = ("painted", "brick", "wood", "tiles", "marble", "stone")

N_TEXTURES_DEFAULT = 50
"""Size of the default texture pool (ids ``0..49``) and number of backgrounds."""

RGB = tuple[float, float, float]


@dataclass(frozen=True)
class TextureParams:
    """Everything that defines one texture (colours are linear-ish sRGB in [0, 1])."""

    texture_id: int
    family: str  #: one of FAMILIES
    colors: tuple[RGB, ...]  #: family-specific palette (base, secondary, line/mortar...)
    scale: int  #: feature count across the unit square (planks, tiles, checks, cells...)
    aspect: float  #: feature aspect ratio (plank length, brick length, tile shape)
    line_width: float  #: grout/mortar/gap width as a fraction of a feature
    jitter: float  #: per-feature colour jitter amplitude
    noise_amp: float  #: fine-noise amplitude

    def to_dict(self) -> dict:
        """JSON-ready dictionary."""
        return {
            "texture_id": self.texture_id,
            "family": self.family,
            "colors": [list(c) for c in self.colors],
            "scale": self.scale,
            "aspect": self.aspect,
            "line_width": self.line_width,
            "jitter": self.jitter,
            "noise_amp": self.noise_amp,
        }


def _hsv(h: float, s: float, v: float) -> RGB:
    r, g, b = colorsys.hsv_to_rgb(h % 1.0, min(max(s, 0.0), 1.0), min(max(v, 0.0), 1.0))
    return (float(r), float(g), float(b))


def texture_params(texture_id: int) -> TextureParams:
    """Family, palette and scales of texture ``texture_id`` (pure function of the id).

    Raises:
        TypeError / ValueError: ``texture_id`` is not a non-negative integer.
    """
    tid = check_id(texture_id, "texture_id")
    family = FAMILIES[tid % len(FAMILIES)]
    rng = np.random.default_rng([TEXTURE_SALT, tid])
    u = rng.uniform
    if family == "wood":
        h, s, v = u(0.04, 0.11), u(0.35, 0.75), u(0.35, 0.85)
        colors = (_hsv(h, s, v), _hsv(h - 0.01, s + 0.1, v * 0.6), _hsv(h, s, v * 0.25))
        scale, aspect, line, jit = (
            int(rng.integers(4, 10)),
            float(u(2.0, 5.0)),
            float(u(0.02, 0.06)),
            float(u(0.04, 0.12)),
        )
    elif family == "tiles":
        h = u(0, 1)
        s = u(0.0, 0.5)
        v = u(0.45, 0.95)
        grout = _hsv(u(0, 1), u(0, 0.15), u(0.2, 0.9))
        colors = (_hsv(h, s, v), _hsv(h + u(-0.05, 0.05), s, v * u(0.75, 1.0)), grout)
        scale, aspect, line, jit = (
            int(rng.integers(3, 10)),
            float(rng.choice([1.0, 1.0, 2.0])),
            float(u(0.03, 0.09)),
            float(u(0.02, 0.1)),
        )
    elif family == "checker":
        h1 = u(0, 1)
        c1 = _hsv(h1, u(0.0, 0.7), u(0.65, 0.95))
        c2 = _hsv(h1 + u(0.3, 0.7), u(0.0, 0.7), u(0.08, 0.45))
        colors = (c1, c2)
        scale, aspect, line, jit = int(2 * rng.integers(2, 7)), 1.0, 0.0, float(u(0.0, 0.05))
    elif family == "stone":
        h, s, v = u(0.02, 0.15), u(0.0, 0.35), u(0.35, 0.75)
        colors = (_hsv(h, s, v), _hsv(h + 0.03, s * 0.8, v * 0.75), _hsv(h, s * 0.5, v * 0.35))
        scale, aspect, line, jit = (
            int(rng.integers(5, 13)),
            1.0,
            float(u(0.06, 0.16)),
            float(u(0.06, 0.16)),
        )
    elif family == "fabric":
        h, s, v = u(0, 1), u(0.2, 0.8), u(0.25, 0.8)
        colors = (_hsv(h, s, v), _hsv(h + u(-0.08, 0.08), s, v * 0.7))
        scale, aspect, line, jit = int(rng.integers(40, 96)), 1.0, 0.0, 0.0
    elif family == "marble":
        base_v = u(0.75, 0.97) if rng.random() < 0.7 else u(0.12, 0.3)
        h = u(0, 1)
        base = _hsv(h, u(0.0, 0.15), base_v)
        vein = _hsv(h + u(-0.1, 0.1), u(0.0, 0.3), 1.0 - base_v * u(0.5, 0.9))
        colors = (base, vein)
        scale, aspect, line, jit = (
            int(rng.integers(2, 6)),
            float(u(0.5, 2.0)),
            float(u(0.15, 0.5)),
            0.0,
        )
    elif family == "painted":
        colors = (_hsv(u(0, 1), u(0.05, 0.45), u(0.6, 0.95)),)
        scale, aspect, line, jit = int(rng.integers(4, 12)), 1.0, 0.0, 0.0
    else:  # brick
        h, s, v = u(0.0, 0.07), u(0.45, 0.8), u(0.35, 0.7)
        mortar = _hsv(u(0.05, 0.12), u(0.0, 0.2), u(0.55, 0.85))
        colors = (_hsv(h, s, v), _hsv(h + 0.02, s, v * 0.7), mortar)
        scale, aspect, line, jit = (
            int(rng.integers(6, 14)),
            float(u(1.8, 2.6)),
            float(u(0.06, 0.14)),
            float(u(0.06, 0.14)),
        )
    noise_amp = float(u(0.03, 0.12)) if family != "painted" else float(u(0.01, 0.03))
    return TextureParams(
        texture_id=tid,
        family=family,
        colors=tuple(tuple(float(x) for x in c) for c in colors),
        scale=int(scale),
        aspect=float(aspect),
        line_width=float(line),
        jitter=float(jit),
        noise_amp=noise_amp,
    )


# --------------------------------------------------------------------------- noise


def _periodic_noise(rng: np.random.Generator, size: int, cells_y: int, cells_x: int) -> np.ndarray:
    """Smooth value noise in [0, 1], periodic on the image, ``[size, size]`` float32."""
    grid = rng.random((cells_y, cells_x)).astype(np.float32)

    def axis(n_cells: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = (np.arange(size, dtype=np.float32) + 0.5) * (n_cells / size)
        i0 = np.floor(t).astype(np.int64)
        f = t - i0
        f = f * f * (3 - 2 * f)  # smoothstep
        return i0 % n_cells, (i0 + 1) % n_cells, f

    y0, y1, fy = axis(cells_y)
    x0, x1, fx = axis(cells_x)
    top = grid[y0][:, x0] * (1 - fx) + grid[y0][:, x1] * fx
    bot = grid[y1][:, x0] * (1 - fx) + grid[y1][:, x1] * fx
    return top * (1 - fy[:, None]) + bot * fy[:, None]


def _fbm(
    rng: np.random.Generator, size: int, cells: int, octaves: int = 4, stretch: int = 1
) -> np.ndarray:
    """Fractal sum of periodic value noise, normalised to zero mean, unit-ish std.

    ``stretch`` > 1 makes features ``stretch`` times longer along x (wood grain).
    """
    out = np.zeros((size, size), dtype=np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        cy = min(cells * 2**o, size)
        cx = max(1, min(cy // stretch, size))
        out += amp * _periodic_noise(rng, size, cy, cx)
        total += amp
        amp *= 0.5
    out /= total
    out -= out.mean()
    std = float(out.std())
    return out / std if std > 1e-6 else out


def _coords(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates on the unit square: ``(y, x)`` each ``[size, size]``."""
    t = (np.arange(size, dtype=np.float32) + 0.5) / size
    return np.meshgrid(t, t, indexing="ij")


def _mix(a, b, t: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float32)
    b = np.asarray(b, dtype=np.float32)
    return a + (b - a) * t[..., None]


def _line_mask(frac: np.ndarray, width: float, soft: float = 0.35) -> np.ndarray:
    """1 inside grout/mortar lines at the edges of a cell (``frac`` in [0, 1)), else 0."""
    d = np.minimum(frac, 1.0 - frac)  # distance to the nearest cell edge
    w = width / 2
    return np.clip((w - d) / max(w * soft, 1e-6) + 0.5, 0.0, 1.0)


# --------------------------------------------------------------------------- families


def _wood(p: TextureParams, rng, size: int) -> np.ndarray:
    y, x = _coords(size)
    n = p.scale  # planks across (rows along y)
    row_f = y * n
    row = np.floor(row_f).astype(np.int64)
    fy = row_f - row
    plank_len = 1.0 / max(1, round(n / p.aspect))  # planks per row: periodic in x
    offsets = rng.random(n).astype(np.float32)
    xs = x / plank_len + offsets[row]
    seg = np.floor(xs).astype(np.int64)
    fx = xs - seg
    plank_id = row * 1000 + seg
    # Grain: long stretched noise warps thin sinusoidal rings.
    grain_noise = _fbm(rng, size, 8, octaves=4, stretch=8)
    rings_per_plank = rng.uniform(2.5, 7.0)
    phase = rng.random(n * 64).astype(np.float32) * 6.283
    rings = 0.5 + 0.5 * np.sin(
        6.283 * rings_per_plank * fy + grain_noise * 2.5 + phase[plank_id % (n * 64)]
    )
    rings = rings**2
    base = _mix(p.colors[0], p.colors[1], rings * 0.8)
    tint = 1.0 + p.jitter * (
        rng.random(n * 64).astype(np.float32)[(plank_id * 7 + 3) % (n * 64)] * 2 - 1
    )
    img = base * tint[..., None]
    gaps = np.maximum(_line_mask(fy, p.line_width), _line_mask(fx, p.line_width / (n * plank_len)))
    return _mix_img(img, p.colors[2], gaps)


def _mix_img(img: np.ndarray, color, t: np.ndarray) -> np.ndarray:
    c = np.asarray(color, dtype=np.float32)
    return img + (c - img) * t[..., None]


def _tiles(p: TextureParams, rng, size: int) -> np.ndarray:
    y, x = _coords(size)
    ny = p.scale
    nx = max(1, round(ny / p.aspect))
    ty, tx = y * ny, x * nx
    iy, ix = np.floor(ty).astype(np.int64), np.floor(tx).astype(np.int64)
    fy, fx = ty - iy, tx - ix
    jit = rng.random((ny, nx)).astype(np.float32)
    alt = ((iy + ix) % 2).astype(np.float32) * (rng.random() < 0.4)
    base = _mix(p.colors[0], p.colors[1], np.maximum(jit[iy, ix] * 0.6, alt))
    base = base * (1.0 + p.jitter * (jit[iy, ix] * 2 - 1))[..., None]
    grout = np.maximum(_line_mask(fy, p.line_width), _line_mask(fx, p.line_width * nx / ny))
    return _mix_img(base, p.colors[2], grout)


def _checker(p: TextureParams, rng, size: int) -> np.ndarray:
    y, x = _coords(size)
    n = p.scale
    par = ((np.floor(y * n) + np.floor(x * n)) % 2).astype(np.float32)
    img = _mix(p.colors[0], p.colors[1], par)
    jit = rng.random((n, n)).astype(np.float32)
    img *= (1.0 + p.jitter * (jit[(y * n).astype(int) % n, (x * n).astype(int) % n] * 2 - 1))[
        ..., None
    ]
    return img


def _stone(p: TextureParams, rng, size: int) -> np.ndarray:
    from scipy.spatial import cKDTree

    # Jittered grid: cobbles of similar size (pure uniform points give shards).
    n_cells = p.scale * p.scale
    gy, gx = np.divmod(np.arange(n_cells), p.scale)
    pts = (np.stack([gy, gx], 1) + 0.5 + rng.uniform(-0.4, 0.4, (n_cells, 2))) / p.scale
    pts %= 1.0
    tree = cKDTree(pts, boxsize=1.0)
    y, x = _coords(size)
    q = np.stack([y.ravel(), x.ravel()], axis=1).astype(np.float64)
    d, idx = tree.query(q, k=2)
    d = d.reshape(size, size, 2).astype(np.float32)
    cell = idx[:, 0].reshape(size, size)
    edge = (d[..., 1] - d[..., 0]) * p.scale  # ~0 on the cell border
    jit = rng.random(n_cells).astype(np.float32)
    base = _mix(p.colors[0], p.colors[1], jit[cell])
    # Domed stones: darker towards the border.
    dome = np.clip(edge / 0.5, 0, 1) ** 0.5
    base = base * (0.75 + 0.25 * dome)[..., None]
    mortar = np.clip((p.line_width - edge) / (p.line_width * 0.4) + 0.5, 0, 1)
    return _mix_img(base, p.colors[2], mortar)


def _fabric(p: TextureParams, rng, size: int) -> np.ndarray:
    y, x = _coords(size)
    n = p.scale
    warp = 0.5 + 0.5 * np.sin(x * n * 2 * np.pi)
    weft = 0.5 + 0.5 * np.sin(y * n * 2 * np.pi)
    over = ((np.floor(x * n) + np.floor(y * n)) % 2).astype(np.float32)
    weave = over * warp + (1 - over) * weft
    fuzz = _fbm(rng, size, 64, octaves=2)
    blotch = _fbm(rng, size, 4, octaves=3)
    t = np.clip(0.5 * weave + 0.12 * fuzz + 0.15 * blotch, 0, 1)
    return _mix(p.colors[1], p.colors[0], t)


def _marble(p: TextureParams, rng, size: int) -> np.ndarray:
    y, x = _coords(size)
    ang = rng.uniform(0, np.pi)
    kx, ky = np.round(np.cos(ang) * p.scale), np.round(np.sin(ang) * p.scale)  # integer: periodic
    if kx == 0 and ky == 0:
        kx = 1.0
    turb = _fbm(rng, size, 3, octaves=3)
    s = np.sin(2 * np.pi * (kx * x + ky * y) + turb * 3.0)
    main = (1 - np.abs(s)) ** (2.0 / max(p.line_width, 0.05))
    turb2 = _fbm(rng, size, 5, octaves=3)
    s2 = np.sin(2 * np.pi * (ky * x - kx * y) * 2 + turb2 * 4.0)
    minor = (1 - np.abs(s2)) ** 12
    cloud = _fbm(rng, size, 4, octaves=3)
    t = np.clip(0.85 * main + 0.35 * minor + 0.08 * cloud, 0, 1)
    return _mix(p.colors[0], p.colors[1], t)


def _painted(p: TextureParams, rng, size: int) -> np.ndarray:
    low = _fbm(rng, size, p.scale, octaves=2)
    fine = _fbm(rng, size, 64, octaves=2)
    img = np.broadcast_to(np.asarray(p.colors[0], dtype=np.float32), (size, size, 3)).copy()
    return img * (1.0 + 0.5 * p.noise_amp * low + 0.5 * p.noise_amp * fine)[..., None]


def _brick(p: TextureParams, rng, size: int) -> np.ndarray:
    y, x = _coords(size)
    rows = p.scale if p.scale % 2 == 0 else p.scale + 1  # even: the bond is periodic
    per_row = max(1, round(rows / p.aspect))
    ty = y * rows
    iy = np.floor(ty).astype(np.int64)
    fy = ty - iy
    tx = x * per_row + 0.5 * (iy % 2)
    ix = np.floor(tx).astype(np.int64) % per_row
    fx = tx - np.floor(tx)
    jit = rng.random((rows, per_row)).astype(np.float32)
    base = _mix(p.colors[0], p.colors[1], jit[iy, ix])
    mortar = np.maximum(_line_mask(fy, p.line_width), _line_mask(fx, p.line_width * per_row / rows))
    return _mix_img(base, p.colors[2], mortar)


_FAMILY_FN = {
    "wood": _wood,
    "tiles": _tiles,
    "checker": _checker,
    "stone": _stone,
    "fabric": _fabric,
    "marble": _marble,
    "painted": _painted,
    "brick": _brick,
}


def texture_image(texture_id: int, size: int = 256) -> np.ndarray:
    """Render texture ``texture_id`` at ``size`` x ``size`` pixels.

    Args:
        texture_id: non-negative integer.
        size: image side in pixels (8..8192).

    Returns:
        ``uint8 [size, size, 3]`` sRGB image, identical for identical arguments.

    Example:
        >>> texture_image(3, 64).shape
        (64, 64, 3)
    """
    params = texture_params(texture_id)
    if isinstance(size, bool) or not isinstance(size, Integral) or not 8 <= size <= 8192:
        raise ValueError(f"size must be an int in [8, 8192], got {size!r}")
    size = int(size)
    rng = np.random.default_rng([TEXTURE_SALT, params.texture_id, 1])
    img = _FAMILY_FN[params.family](params, rng, size)
    if params.family != "painted":
        grain = _fbm(rng, size, 32, octaves=2)
        img = img * (1.0 + params.noise_amp * 0.5 * grain)[..., None]
    return np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- backgrounds


@functools.lru_cache(maxsize=8)
def _background_table(n_textures: int) -> tuple[tuple[int, int], ...]:
    """One (floor, wall) pair per background: all pairs distinct, families differ,
    and textures are used as evenly as possible (greedy over a seeded pair order).
    """
    fams = [FAMILIES[t % len(FAMILIES)] for t in range(n_textures)]
    floors = [t for t in range(n_textures) if fams[t] in FLOOR_FAMILIES]
    walls = [t for t in range(n_textures) if fams[t] in WALL_FAMILIES]
    pairs = [(f, w) for f in floors for w in walls if fams[f] != fams[w]]
    rng = np.random.default_rng([BACKGROUND_SALT, n_textures])
    order = [pairs[i] for i in rng.permutation(len(pairs))]
    usage = [0] * n_textures  # uses as floor or wall
    table: list[tuple[int, int]] = []
    remaining = list(order)
    while remaining and len(table) < 4 * n_textures:
        best = min(
            range(len(remaining)),
            key=lambda i: (usage[remaining[i][0]] + usage[remaining[i][1]], i),
        )
        f, w = remaining.pop(best)
        table.append((f, w))
        usage[f] += 1
        usage[w] += 1
    return tuple(table)


def background_params(bg_id: int, n_textures: int = N_TEXTURES_DEFAULT) -> tuple[int, int]:
    """Map background ``bg_id`` to ``(floor_texture_id, wall_texture_id)``.

    Both ids are in ``range(n_textures)``; the floor comes from a floor family
    (:data:`FLOOR_FAMILIES`), the wall from a wall family, never the same family.
    Backgrounds ``0..n_textures-1`` (the 50 backgrounds of ``room-diverse``) are
    pairwise distinct and together use every texture of the pool.

    Raises:
        ValueError: ``bg_id`` outside ``[0, 4 * n_textures)`` or ``n_textures < 8``.
    """
    check_id(bg_id, "bg_id")
    check_id(n_textures, "n_textures")
    if n_textures < len(FAMILIES):
        raise ValueError(f"n_textures must be >= {len(FAMILIES)}, got {n_textures}")
    table = _background_table(int(n_textures))
    if bg_id >= len(table):
        raise ValueError(
            f"bg_id must be in [0, {len(table)}) for n_textures={n_textures}, got {bg_id}"
        )
    return table[bg_id]
