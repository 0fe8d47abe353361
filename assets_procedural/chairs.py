"""Procedural chair geometry: the closed parts of a chair, in a canonical frame.

Where this sits: the Room presets' scene sampler (``room-chair``, ``room-diverse``)
picks chair ids; ``assets_procedural.cache`` turns an id into a mesh file once
(:func:`chair_mesh`); the Blender backend imports that file. The parameters of a chair
and how they are drawn from its id are in ``assets_procedural.chair_spec`` (every name
re-exported here); this module turns them into geometry: ``build_chair(params)``, and
``chair_mesh(asset_id)`` = ``build_chair(chair_params(asset_id))``. Nothing here imports
torch or bpy.

Canonical size and frame (the contract tested in ``tests/test_assets.py``):

* world units are abstract; the chair is **scaled uniformly** (proportions of the
  metric design are kept) so that its largest horizontal extent
  ``max(x extent, y extent)`` is exactly 1.0;
* the footprint's bounding box is centred on ``x = y = 0``;
* it rests on the floor: ``min z == 0.0`` exactly; ``z`` is up;
* the front (where one sits down) faces ``-y``; the back rest is on the ``+y`` side;
* the height (z extent) is then whatever the proportions give, within
  :data:`HEIGHT_RANGE` (measured over ids 0..1199: from about 0.65 for a low
  stool on a wide star base up to about 2.75 for a narrow, tall-backed chair).
  ``mesh.metadata["metres_per_unit"]`` gives the metric design's scale, so a scene
  sampler that wants realistic relative sizes can rescale by it (a chair of ~0.45 m
  seat height has ``metres_per_unit`` ~0.5).

Geometry: every part (seat, each leg, slat, rail, arm, ...) is a separate closed,
watertight, outward-oriented triangle mesh; parts may overlap (no boolean union),
so the chair is "closed per part" and ``mesh.volume`` is the sum of part volumes.
Cylinders use few segments (8) to keep building 1,200 chairs cheap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import trimesh

from assets_procedural import _geometry as g
from assets_procedural.chair_spec import (
    ARM_STYLES,
    BACK_STYLES,
    BASE_KINDS,
    CHAIR_GENERATOR_VERSION,
    GENERATOR_SALT,
    LEG_SECTIONS,
    LEG_STYLES,
    SEAT_SHAPES,
    STRETCHER_STYLES,
    ChairParams,
    chair_params,
)

# With the names re-exported from assets_procedural.chair_spec (their old home).
__all__ = [
    "ARM_STYLES",
    "BACK_STYLES",
    "BASE_KINDS",
    "CHAIR_GENERATOR_VERSION",
    "GENERATOR_SALT",
    "HEIGHT_RANGE",
    "LEG_SECTIONS",
    "LEG_STYLES",
    "SEAT_SHAPES",
    "STRETCHER_STYLES",
    "ChairParams",
    "ChairPart",
    "build_chair",
    "build_chair_parts",
    "chair_mesh",
    "chair_params",
]

HEIGHT_RANGE = (0.6, 2.9)
"""Bounds on the normalised chair height (z extent) over all ids (tested on a sample)."""

_ROUND_SEGMENTS = 8


@dataclass(frozen=True)
class ChairPart:
    """One closed part of a chair, already in the canonical (normalised) frame."""

    name: str
    vertices: np.ndarray  #: float64 [n, 3]
    faces: np.ndarray  #: int64 [m, 3]


class _Builder:
    """Builds the parts of one chair in metres (seat centred at x=y=0)."""

    def __init__(self, p: ChairParams):
        self.p = p
        self.parts: list[tuple[str, np.ndarray, np.ndarray]] = []
        self.zs = p.seat_height  # seat top
        self.zb = p.seat_height - p.seat_thickness  # seat underside
        self.hw = p.seat_width / 2
        self.hd = p.seat_depth / 2

    # -- helpers
    def add(self, name: str, part: g.Part) -> None:
        self.parts.append((name, part[0], part[1]))

    def section(self, thickness: float) -> np.ndarray:
        if self.p.leg_section == "round":
            return g.circle_profile(thickness / 2, _ROUND_SEGMENTS)
        return g.rect_profile(thickness, thickness)

    def half_width_at(self, y: float) -> float:
        """Half width of the seat outline at depth ``y`` (accounts for taper/shape)."""
        p = self.p
        scale = 1.0 + (p.seat_taper - 1.0) * (y + self.hd) / (2 * self.hd)
        if p.seat_shape == "rect":
            return self.hw * scale
        t = min(abs(y) / self.hd, 1.0)
        return self.hw * scale * (1.0 - t**p.seat_exponent) ** (1.0 / p.seat_exponent)

    def y_edge_at(self, x: float) -> float:
        """Depth of the seat's rear edge at lateral position ``x`` (``+y`` side)."""
        p = self.p
        if p.seat_shape == "rect":
            return self.hd
        hw_back = self.hw * p.seat_taper
        t = min(abs(x) / hw_back, 1.0)
        return self.hd * (1.0 - t**p.seat_exponent) ** (1.0 / p.seat_exponent)

    def leg_corners(self) -> list[tuple[float, float]]:
        """Top positions of four legs: front-left, front-right, back-right, back-left."""
        p = self.p
        # Corner of the outline on the diagonal: (hw*s, hd*s) for a superellipse.
        s = 2.0 ** (-1.0 / p.seat_exponent) if p.seat_shape != "rect" else 1.0
        y = self.hd * s - p.leg_inset
        out = []
        for sy in (-1.0, 1.0):
            x = max(self.half_width_at(sy * self.hd * s) - p.leg_inset, p.leg_thickness)
            out.append((-x, sy * y))
            out.append((x, sy * y))
        # order: FL, FR, BL, BR -> FL, FR, BR, BL
        return [out[0], out[1], out[3], out[2]]

    # -- seat
    def seat(self) -> None:
        p = self.p
        if p.seat_shape == "rect":
            hb = self.hw * p.seat_taper
            outline = np.array(
                [[-self.hw, -self.hd], [self.hw, -self.hd], [hb, self.hd], [-hb, self.hd]]
            )
        else:
            outline = g.superellipse(self.hw, self.hd, p.seat_exponent, n=24)
            if p.seat_taper != 1.0:
                outline[:, 0] *= 1.0 + (p.seat_taper - 1.0) * (outline[:, 1] + self.hd) / (
                    2 * self.hd
                )
        self.add(
            "seat",
            g.plate(
                outline,
                (0, 0, self.zs - p.seat_thickness / 2),
                (1, 0, 0),
                (0, 1, 0),
                p.seat_thickness,
            ),
        )

    # -- legs
    def four_legs(self) -> list[tuple[np.ndarray, np.ndarray]]:
        p = self.p
        top_z = self.zb + min(p.seat_thickness * 0.5, 0.02)
        legs = []
        for i, (x, y) in enumerate(self.leg_corners()):
            top = np.array([x, y, top_z])
            foot = np.array([x, y, 0.0])
            if p.leg_style == "splayed":
                out = np.array([np.sign(x), np.sign(y) * 0.8, 0.0])
                out /= np.linalg.norm(out)
                foot[:2] += out[:2] * math.tan(math.radians(p.leg_splay_deg)) * top_z
            back_leg = i >= 2
            if back_leg and p.rear_posts_from_legs:
                continue  # built with the back (one bent post from floor to back top)
            legs.append((foot, top))
            self.add("leg", g.tube(foot, top, self.section(p.leg_thickness)))
        return legs

    def stretchers_and_apron(self) -> None:
        p = self.p
        corners = self.leg_corners()
        top_z = self.zb
        t = p.leg_thickness * 0.6

        def at_height(c: tuple[float, float], z: float) -> np.ndarray:
            x, y = c
            if p.leg_style == "splayed":
                out = np.array([np.sign(x), np.sign(y) * 0.8])
                out /= np.linalg.norm(out)
                d = out * math.tan(math.radians(p.leg_splay_deg)) * (top_z - z)
                return np.array([x + d[0], y + d[1], z])
            return np.array([x, y, z])

        if p.stretchers != "none":
            z = max(p.stretcher_height_frac * top_z, t)
            fl, fr, br, bl = (at_height(c, z) for c in corners)
            prof = self.section(t)
            self.add("stretcher", g.tube(fl, bl, prof))
            self.add("stretcher", g.tube(fr, br, prof))
            if p.stretchers == "h":
                self.add("stretcher", g.tube((fl + bl) / 2, (fr + br) / 2, prof))
            else:
                z2 = z * 1.08  # offset so crossing rails do not share a height exactly
                fl2, fr2, br2, bl2 = (at_height(c, z2) for c in corners)
                self.add("stretcher", g.tube(fl2, fr2, prof))
                self.add("stretcher", g.tube(bl2, br2, prof))
        if p.apron:
            h = p.apron_height
            zc = top_z - h / 2 + 0.005
            fl, fr, br, bl = (np.array([c[0], c[1], zc]) for c in corners)
            prof = g.rect_profile(h, 0.02)  # h along the reference (vertical) axis
            for a, b in ((fl, fr), (bl, br), (fl, bl), (fr, br)):
                self.add("apron", g.tube(a, b, prof, ref=(0, 0, 1)))

    def pedestal(self) -> None:
        p = self.p
        r = p.column_radius
        base_top = 0.06 if p.base_kind == "star" else 0.03
        self.add(
            "column",
            g.tube(
                (0, 0, base_top * 0.5), (0, 0, self.zb + 0.01), g.circle_profile(r, _ROUND_SEGMENTS)
            ),
        )
        # Seat mechanism / mounting plate.
        self.add(
            "mount", g.box((0, 0, self.zb - 0.02), (min(0.22, self.hw), min(0.22, self.hd), 0.045))
        )
        R = p.base_radius
        if p.is_stool and p.seat_height > 0.6:
            # Bar stool foot ring on three spokes.
            zr, rr = 0.42 * p.seat_height, 0.55 * R
            a = np.linspace(0.0, 2 * math.pi, 16, endpoint=False)
            ring = np.stack([rr * np.cos(a), rr * np.sin(a), np.full_like(a, zr)], axis=1)
            self.add(
                "foot_ring", g.sweep(ring, g.circle_profile(0.011, 6), ref=(0, 0, 1), closed=True)
            )
            for k in range(3):
                d = np.array(
                    [math.cos(2 * math.pi * k / 3 + 0.5), math.sin(2 * math.pi * k / 3 + 0.5), 0.0]
                )
                self.add(
                    "spoke", g.tube((0, 0, zr), d * rr + [0, 0, zr], g.circle_profile(0.009, 6))
                )
        if p.base_kind == "disc":
            self.add("base", g.tube((0, 0, 0), (0, 0, 0.025), g.circle_profile(R, 16)))
            return
        n = p.base_arms
        phase = -math.pi / 2  # one arm points to the front (-y)
        self.add(
            "hub",
            g.tube(
                (0, 0, 0.02 if p.base_kind == "star" else 0.0),
                (0, 0, base_top + 0.02),
                g.circle_profile(r * 1.6, _ROUND_SEGMENTS),
            ),
        )
        for k in range(n):
            a = phase + 2 * math.pi * k / n
            d = np.array([math.cos(a), math.sin(a), 0.0])
            if p.base_kind == "star":
                start = np.array([0, 0, base_top])
                end = d * R + np.array([0, 0, base_top * 0.6])
                self.add("base_arm", g.tube(start, end, g.rect_profile(0.04, 0.035), ref=(0, 0, 1)))
                # Caster: stem + wheel.
                self.add(
                    "caster",
                    g.tube(end + [0, 0, 0.0], end + [0, 0, -0.02], g.circle_profile(0.012, 6)),
                )
                wheel_axis = np.array([-d[1], d[0], 0.0])
                wc = d * R + np.array([0, 0, 0.025])
                self.add(
                    "caster",
                    g.tube(
                        wc - wheel_axis * 0.015,
                        wc + wheel_axis * 0.015,
                        g.circle_profile(0.025, _ROUND_SEGMENTS),
                    ),
                )
            else:  # cross base with glides, arms resting on the floor
                self.add(
                    "base_arm",
                    g.tube(
                        np.array([0, 0, 0.02]),
                        d * R + [0, 0, 0.02],
                        g.rect_profile(0.04, 0.04),
                        ref=(0, 0, 1),
                    ),
                )

    def sled(self) -> None:
        p = self.p
        t = p.leg_thickness
        prof = self.section(t)
        x = self.hw - p.leg_inset
        yf = -self.hd + p.leg_inset
        yb = self.hd - p.leg_inset
        zt = self.zb + 0.01
        for sx in (-1.0, 1.0):
            path = np.array(
                [
                    [sx * x, yf, zt],
                    [sx * x, -self.hd - p.runner_overhang, t / 2],
                    [sx * x, self.hd + p.runner_overhang * 0.5, t / 2],
                    [sx * x, yb, zt],
                ]
            )
            self.add("runner", g.sweep(g.round_corners(path, 0.05, 3), prof, ref=(1, 0, 0)))
        for y in (yf + 0.02, yb - 0.02):
            self.add(
                "crossbar",
                g.tube((-x, y, self.zb - t / 2), (x, y, self.zb - t / 2), prof, ref=(0, 0, 1)),
            )

    def cantilever(self) -> None:
        p = self.p
        t = p.leg_thickness * 0.8
        prof = (
            g.circle_profile(t / 2, _ROUND_SEGMENTS)
            if p.leg_section == "round"
            else g.rect_profile(t, t)
        )
        x = self.hw - p.leg_inset
        yb = self.hd - p.leg_inset
        yf = -self.hd + p.leg_inset + 0.02
        yfl = -self.hd - p.runner_overhang
        yend = self.hd * 0.75
        z = self.zb - t / 2
        path = np.array(
            [
                [-x, yb, z],
                [-x, yf, z],
                [-x, yfl, t / 2],
                [-x, yend, t / 2],
                [x, yend, t / 2],
                [x, yfl, t / 2],
                [x, yf, z],
                [x, yb, z],
            ]
        )
        self.add("frame", g.sweep(g.round_corners(path, 0.07, 4), prof, ref=(0, 0, 1)))

    # -- back
    def back_frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        """Origin (bottom centre), lateral axis, up axis, half width, back-plane y."""
        p = self.p
        th = math.radians(p.back_tilt_deg)
        up = np.array([0.0, math.sin(th), math.cos(th)])
        hb = self.hw * p.seat_taper * p.back_width_frac
        if p.rear_posts_from_legs:
            # Posts continue the rear legs: same x and y as the back leg axes.
            bx, y0 = self.leg_corners()[2]
            hb = abs(bx) + p.post_thickness / 2
        else:
            y0 = self.y_edge_at(hb) - p.back_thickness / 2
            y0 = max(y0, self.hd * 0.3)
        origin = np.array([0.0, y0, self.zs + p.back_gap])
        return origin, np.array([1.0, 0.0, 0.0]), up, hb, y0

    def back(self) -> None:
        p = self.p
        if p.back_style == "none":
            return
        origin, ex, up, hb, _ = self.back_frame()
        h = p.back_height
        bt = p.back_thickness
        if p.back_style == "solid":
            w_top = hb * p.back_top_width_frac
            r = p.back_top_round * h
            arc = np.linspace(0.0, math.pi, 11)
            top = np.stack([w_top * np.cos(arc), (h - r) + r * np.sin(arc) ** 0.7], axis=1)
            outline = np.vstack([[[-hb, 0.0], [hb, 0.0]], top])
            # plate() centres on the plane; shift so the panel's bottom touches the seat.
            o = origin + up * (-p.seat_thickness * 0.3 if p.back_gap == 0 else 0.0)
            self.add("back", g.plate(outline, o, ex, up, bt))
        elif p.back_style == "curved":
            n = 9
            xs = np.linspace(-hb, hb, n)
            wrap = -p.back_curvature * (xs / hb) ** 2
            normal = np.cross(ex, up)  # points to -y (front) for an upright back
            mid = origin + up * (h / 2)
            path = mid + xs[:, None] * ex - wrap[:, None] * normal
            self.add("back", g.sweep(path, g.rect_profile(h, bt), ref=up))
        else:
            self.posts_and_fill(origin, ex, up, hb, h)
        if p.back_gap > 0:
            # Spine joining the seat to a floating back.
            spine_bot = np.array([0.0, origin[1] - 0.02, self.zb - 0.01])
            spine_top = origin + up * min(0.08, h * 0.3)
            w = min(0.08, hb)
            self.add("spine", g.tube(spine_bot, spine_top, g.rect_profile(w, 0.025), ref=(1, 0, 0)))

    def posts_and_fill(self, origin, ex, up, hb, h) -> None:
        p = self.p
        pt = p.post_thickness
        prof = self.section(pt) if p.leg_section == "round" else g.rect_profile(pt, pt)
        xpost = hb - pt / 2
        top_h = h
        for sx in (-1.0, 1.0):
            base = origin + ex * (sx * xpost)
            top = base + up * top_h
            if p.rear_posts_from_legs:
                foot = np.array([base[0], base[1], 0.0])
                path = np.array([foot, base, top])
                self.add("post", g.sweep(path, self.section(p.leg_thickness), ref=(1, 0, 0)))
            else:
                start = base - up * (p.seat_thickness * 0.5)
                self.add("post", g.tube(start, top, prof, ref=(1, 0, 0)))
        inner = xpost - pt / 2
        if p.back_style == "slats":
            top_rail_h = min(0.07, h * 0.18)
            zr = h - top_rail_h / 2
            self.add(
                "rail",
                g.tube(
                    origin + ex * -inner + up * zr,
                    origin + ex * inner + up * zr,
                    g.rect_profile(top_rail_h, p.back_thickness * 0.9),
                    ref=up,
                ),
            )
            n = p.back_count
            gapw = 2 * inner / (n + 1)
            sw = min(gapw * 0.55, 0.06)
            for k in range(n):
                x = -inner + gapw * (k + 1)
                a = origin + ex * x - up * (p.seat_thickness * 0.3)
                b = origin + ex * x + up * (h - top_rail_h * 0.5)
                self.add(
                    "slat", g.tube(a, b, g.rect_profile(sw, p.back_thickness * 0.7), ref=(1, 0, 0))
                )
        else:  # ladder
            n = p.back_count
            rh = min(0.06, h / (2 * n + 1))
            for k in range(n):
                zr = h * (0.3 + 0.7 * (k + 1) / n) - rh / 2
                a = origin + ex * -inner + up * zr
                b = origin + ex * inner + up * zr
                self.add("rail", g.tube(a, b, g.rect_profile(rh, p.back_thickness * 0.8), ref=up))

    # -- arms
    def arms(self) -> None:
        p = self.p
        if p.arm_style == "none":
            return
        _, _, up, _, y_back = self.back_frame()
        za = self.zs + p.arm_height
        w = p.arm_width
        y_front = -self.hd + 0.03
        y_rear = y_back + up[1] / max(up[2], 1e-6) * p.arm_height  # where the back is at za
        for sx in (-1.0, 1.0):
            x = sx * (self.half_width_at(0.0) - w / 2 + 0.01)
            if p.arm_style == "bar":
                post_y = y_front + 0.06
                self.add(
                    "arm_post",
                    g.tube(
                        (x, post_y, self.zb), (x, post_y, za), g.rect_profile(min(w, 0.04), 0.035)
                    ),
                )
                self.add(
                    "arm_rest",
                    g.tube(
                        (x, y_front - 0.02, za + 0.012),
                        (x, y_rear, za + 0.012),
                        g.rect_profile(w, 0.025),
                        ref=(1, 0, 0),
                    ),
                )
            elif p.arm_style == "panel":
                bottom = (
                    self.zb - 0.05 if p.leg_style not in ("straight", "splayed") else self.zb - 0.02
                )
                depth = y_rear - (-self.hd)
                cy = (y_rear + -self.hd) / 2
                self.add("arm_panel", g.box((x, cy, (bottom + za) / 2), (w, depth, za - bottom)))
            else:  # loop
                r = min(w, 0.04) / 2
                path = np.array(
                    [
                        [x, y_rear - 0.02, self.zs - 0.01],
                        [x, y_rear, za],
                        [x, y_front, za],
                        [x, y_front + 0.05, self.zb],
                    ]
                )
                self.add(
                    "arm_loop",
                    g.sweep(
                        g.round_corners(path, 0.05, 3),
                        g.circle_profile(r, _ROUND_SEGMENTS),
                        ref=(1, 0, 0),
                    ),
                )

    def build(self) -> list[tuple[str, np.ndarray, np.ndarray]]:
        p = self.p
        self.seat()
        if p.leg_style in ("straight", "splayed"):
            self.four_legs()
            self.stretchers_and_apron()
        elif p.leg_style == "pedestal":
            self.pedestal()
        elif p.leg_style == "sled":
            self.sled()
        else:
            self.cantilever()
        self.back()
        self.arms()
        return self.parts


def _normalise(parts: list[tuple[str, np.ndarray, np.ndarray]]) -> tuple[list[ChairPart], float]:
    allv = np.concatenate([v for _, v, _ in parts])
    lo, hi = allv.min(0), allv.max(0)
    shift = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    ext = max(hi[0] - lo[0], hi[1] - lo[1])
    scale = 1.0 / ext
    out = [ChairPart(name, (v - shift) * scale, f) for name, v, f in parts]
    return out, float(ext)


def build_chair_parts(params: ChairParams) -> list[ChairPart]:
    """Build the closed parts of a chair in the canonical frame (see module docstring).

    Args:
        params: the chair's parameters (from :func:`chair_params` or hand-made).

    Returns:
        Parts in a fixed order (seat first); each is watertight and outward-oriented.
    """
    if not isinstance(params, ChairParams):
        raise TypeError(f"params must be ChairParams, got {type(params).__name__}")
    parts, _ = _normalise(_Builder(params).build())
    return parts


def build_chair(params: ChairParams) -> trimesh.Trimesh:
    """Build the chair mesh for ``params``: all parts concatenated, canonical frame.

    Returns:
        ``trimesh.Trimesh`` (``process=False``: vertices/faces exactly as built) with
        ``metadata`` keys ``asset_id``, ``generator_version``, ``metres_per_unit``,
        ``part_names`` and ``part_face_counts`` (faces are stored part by part in
        that order, so a renderer can give e.g. legs and seat different materials).
    """
    if not isinstance(params, ChairParams):
        raise TypeError(f"params must be ChairParams, got {type(params).__name__}")
    raw = _Builder(params).build()
    parts, ext = _normalise(raw)
    offsets = np.cumsum([0] + [len(pt.vertices) for pt in parts[:-1]])
    verts = np.concatenate([pt.vertices for pt in parts])
    faces = np.concatenate([pt.faces + o for pt, o in zip(parts, offsets)])
    mesh = trimesh.Trimesh(vertices=verts, faces=faces, process=False, validate=False)
    mesh.metadata.update(
        {
            "asset_id": params.asset_id,
            "generator_version": CHAIR_GENERATOR_VERSION,
            "metres_per_unit": ext,
            "part_names": [pt.name for pt in parts],
            "part_face_counts": [len(pt.faces) for pt in parts],
        }
    )
    return mesh


def chair_mesh(asset_id: int) -> trimesh.Trimesh:
    """The chair with id ``asset_id`` (``build_chair(chair_params(asset_id))``)."""
    return build_chair(chair_params(asset_id))
