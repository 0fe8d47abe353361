"""CLEVR's object vocabulary, shared by the generator and the numpy-only test writer.

Kept in the format package because ``svorf`` must not import ``generators`` and both
need the same values (the scene JSON records colour names with these RGB values).
"""

from __future__ import annotations

#: CLEVR's eight colours, 8-bit sRGB values from CLEVR's ``properties.json``.
CLEVR_COLORS: dict[str, tuple[int, int, int]] = {
    "gray": (87, 87, 87),
    "red": (173, 35, 35),
    "blue": (42, 75, 215),
    "green": (29, 105, 20),
    "brown": (129, 74, 25),
    "purple": (129, 38, 192),
    "cyan": (41, 208, 208),
    "yellow": (255, 238, 51),
}

#: CLEVR's size names -> r (sphere radius, cylinder radius = half height; cubes use r/sqrt 2).
CLEVR_SIZES: dict[str, float] = {"small": 0.35, "large": 0.7}
