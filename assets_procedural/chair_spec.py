"""Chair parameters: what defines one procedural chair, and how they are drawn from its id.

Where this sits: below ``assets_procedural.chairs``, which builds the geometry of a
:class:`ChairParams` (``build_chair``, ``chair_mesh``) and re-exports every name here.
Nothing here imports torch, bpy or trimesh.

``chair_params(asset_id)`` draws a frozen :class:`ChairParams` from
``numpy.random.default_rng([GENERATOR_SALT, asset_id])``: a chair is a pure function of
an integer id. The parameter space spans common real chairs: rectangular (optionally
tapered), rounded (superellipse) or round seats of varying thickness; four straight legs,
four splayed legs, a pedestal/swivel column on a star, disc or cross base, sled runners
or a cantilever tube frame; square or round leg sections, optional stretchers and apron;
solid (optionally round-topped / tapered) panel backs, vertical slats, horizontal ladder
rails, a curved panel, or no back (stools, including bar stools); back height and tilt;
armrests (post-and-bar, solid side panel or bent loop) or none. Lengths are metres of the
metric design (the geometry is normalised afterwards), angles degrees.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from assets_procedural.ids import check_id

__all__ = [
    "ARM_STYLES",
    "BACK_STYLES",
    "BASE_KINDS",
    "CHAIR_GENERATOR_VERSION",
    "GENERATOR_SALT",
    "LEG_SECTIONS",
    "LEG_STYLES",
    "SEAT_SHAPES",
    "STRETCHER_STYLES",
    "ChairParams",
    "chair_params",
]

CHAIR_GENERATOR_VERSION = "chairs-1.0.0"
"""Bump whenever the same id would produce different geometry (invalidates caches)."""

GENERATOR_SALT = 0x5C4A17
"""First word of the RNG seed; the asset id is the second."""

SEAT_SHAPES = ("rect", "rounded", "round")
LEG_STYLES = ("straight", "splayed", "pedestal", "sled", "cantilever")
LEG_SECTIONS = ("square", "round")
BACK_STYLES = ("solid", "slats", "ladder", "curved", "none")
ARM_STYLES = ("none", "bar", "panel", "loop")
STRETCHER_STYLES = ("none", "h", "box")
BASE_KINDS = ("star", "disc", "cross")


@dataclass(frozen=True)
class ChairParams:
    """All draws that define one chair. Lengths are metres of the metric design
    (before the uniform normalisation), angles degrees. Plain Python scalars only,
    so ``dataclasses.asdict`` is JSON-serialisable.
    """

    asset_id: int
    seat_shape: str  #: one of SEAT_SHAPES
    seat_exponent: float  #: superellipse exponent (rounded: 2.5-6; round: 2; rect: 0 = unused)
    seat_width: float  #: x extent of the seat front edge
    seat_depth: float  #: y extent
    seat_thickness: float
    seat_height: float  #: floor to top of seat
    seat_taper: float  #: back width / front width (1 = rectangular)
    leg_style: str  #: one of LEG_STYLES
    leg_section: str  #: one of LEG_SECTIONS
    leg_thickness: float  #: side (square) or diameter (round)
    leg_inset: float  #: distance of leg axes from the seat edge
    leg_splay_deg: float  #: splayed legs only
    stretchers: str  #: one of STRETCHER_STYLES (four-legged chairs)
    stretcher_height_frac: float  #: stretcher height / seat underside height
    apron: bool  #: skirt boards under the seat (four-legged chairs)
    apron_height: float
    base_kind: str  #: pedestal only: one of BASE_KINDS
    base_arms: int  #: pedestal star base arm count
    base_radius: float  #: pedestal base radius
    column_radius: float  #: pedestal column radius
    runner_overhang: float  #: sled/cantilever: how far the floor runners pass the seat
    back_style: str  #: one of BACK_STYLES ("none" = stool)
    back_height: float  #: along the tilted back, from the seat top
    back_width_frac: float  #: back width / seat width at the back edge
    back_tilt_deg: float  #: lean backwards from vertical
    back_thickness: float
    back_top_round: float  #: solid back: fraction of the height taken by the rounded top
    back_top_width_frac: float  #: solid back: top width / bottom width
    back_gap: float  #: gap between seat top and back bottom (office-style backs)
    back_count: int  #: number of slats (slats) or rails (ladder)
    back_curvature: float  #: curved back: how far the sides wrap forward (metres)
    post_thickness: float  #: back uprights
    rear_posts_from_legs: bool  #: straight legs continue up as back posts
    arm_style: str  #: one of ARM_STYLES
    arm_height: float  #: above the seat top
    arm_width: float

    def __post_init__(self) -> None:
        for name, options in (
            ("seat_shape", SEAT_SHAPES),
            ("leg_style", LEG_STYLES),
            ("leg_section", LEG_SECTIONS),
            ("back_style", BACK_STYLES),
            ("arm_style", ARM_STYLES),
            ("stretchers", STRETCHER_STYLES),
            ("base_kind", BASE_KINDS),
        ):
            if getattr(self, name) not in options:
                raise ValueError(f"{name} must be one of {options}, got {getattr(self, name)!r}")
        for name in ("seat_width", "seat_depth", "seat_thickness", "seat_height", "leg_thickness"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0 (metres), got {getattr(self, name)!r}")
        if self.seat_shape != "rect" and not self.seat_exponent >= 1.0:
            raise ValueError(
                f"seat_exponent must be >= 1 for a {self.seat_shape} seat, got {self.seat_exponent}"
            )
        if self.back_style != "none" and not (self.back_height > 0 and self.back_thickness > 0):
            raise ValueError("back_height and back_thickness must be > 0 when the chair has a back")
        if self.back_style in ("slats", "ladder") and self.back_count < 1:
            raise ValueError(f"back_count must be >= 1 for a {self.back_style} back")
        if self.leg_style == "pedestal" and not (self.base_radius > 0 and self.column_radius > 0):
            raise ValueError("base_radius and column_radius must be > 0 for a pedestal")

    @property
    def is_stool(self) -> bool:
        """A stool is a chair without a back."""
        return self.back_style == "none"

    def to_dict(self) -> dict:
        """JSON-ready dictionary of all fields (for the scene JSON)."""
        return dataclasses.asdict(self)


def _choice(rng: np.random.Generator, options: tuple, p: list[float]) -> str:
    return options[int(rng.choice(len(options), p=np.asarray(p) / np.sum(p)))]


def chair_params(asset_id: int) -> ChairParams:
    """Draw the parameters of chair ``asset_id`` (pure function of the id).

    Args:
        asset_id: non-negative integer.

    Returns:
        The frozen :class:`ChairParams`.

    Raises:
        TypeError / ValueError: ``asset_id`` is not a non-negative integer.
    """
    aid = check_id(asset_id, "asset_id")
    rng = np.random.default_rng([GENERATOR_SALT, aid])
    u = rng.uniform

    back_style = _choice(rng, BACK_STYLES, [0.24, 0.19, 0.19, 0.20, 0.18])
    stool = back_style == "none"
    if stool:
        leg_style = _choice(rng, LEG_STYLES, [0.45, 0.30, 0.25, 0.0, 0.0])
    else:
        leg_style = _choice(rng, LEG_STYLES, [0.30, 0.18, 0.20, 0.16, 0.16])

    seat_shape = _choice(rng, SEAT_SHAPES, [0.3, 0.35, 0.35] if stool else [0.45, 0.4, 0.15])
    if seat_shape == "round":
        seat_exponent = 2.0
    elif seat_shape == "rounded":
        seat_exponent = float(u(2.5, 6.0))
    else:
        seat_exponent = 0.0
    seat_width = float(u(0.32, 0.45) if stool else u(0.40, 0.58))
    seat_depth = float(u(0.32, 0.45) if stool else u(0.38, 0.55))
    if seat_shape == "round":
        seat_depth = seat_width
    seat_thickness = float(u(0.025, 0.06) if rng.random() < 0.6 else u(0.06, 0.12))
    if stool:
        seat_height = float(u(0.45, 0.55) if rng.random() < 0.4 else u(0.60, 0.80))
    else:
        seat_height = float(u(0.40, 0.50))
    seat_taper = float(u(0.78, 1.0)) if seat_shape == "rect" and rng.random() < 0.5 else 1.0

    leg_section = _choice(rng, LEG_SECTIONS, [0.5, 0.5])
    leg_thickness = float(u(0.025, 0.06))
    leg_inset = float(u(0.02, 0.06))
    leg_splay_deg = float(u(5.0, 14.0)) if leg_style == "splayed" else 0.0
    four = leg_style in ("straight", "splayed")
    if four:
        tall = seat_height > 0.58
        stretchers = "box" if tall else _choice(rng, STRETCHER_STYLES, [0.5, 0.25, 0.25])
        stretcher_height_frac = float(u(0.15, 0.45))
        apron = bool(rng.random() < (0.25 if stool else 0.5))
        apron_height = float(u(0.04, 0.10)) if apron else 0.0
    else:
        stretchers, stretcher_height_frac, apron, apron_height = "none", 0.0, False, 0.0
    if leg_style == "pedestal":
        base_kind = _choice(rng, BASE_KINDS, [0.6, 0.2, 0.2])
        base_arms = int(rng.integers(4, 6)) if base_kind == "star" else 4
        base_radius = float(u(0.24, 0.34))
        column_radius = float(u(0.02, 0.045))
    else:
        base_kind, base_arms, base_radius, column_radius = "star", 0, 0.0, 0.0
    runner_overhang = float(u(0.0, 0.08)) if leg_style in ("sled", "cantilever") else 0.0

    # Back.
    back_height = back_width_frac = back_tilt_deg = back_thickness = 0.0
    back_top_round = back_gap = back_curvature = post_thickness = 0.0
    back_top_width_frac = 1.0
    back_count = 0
    rear_posts_from_legs = False
    if not stool:
        back_height = float(u(0.28, 0.65))
        back_width_frac = float(u(0.7, 1.0))
        back_tilt_deg = float(u(0.0, 18.0))
        back_thickness = float(u(0.015, 0.05))
        post_thickness = float(u(0.022, 0.045))
        if back_style == "solid":
            back_top_round = float(u(0.1, 0.5)) if rng.random() < 0.6 else 0.0
            back_top_width_frac = float(u(0.75, 1.15))
            back_gap = float(u(0.03, 0.12)) if rng.random() < 0.4 else 0.0
        elif back_style == "slats":
            back_count = int(rng.integers(2, 8))
        elif back_style == "ladder":
            back_count = int(rng.integers(2, 6))
        elif back_style == "curved":
            back_curvature = float(u(0.03, 0.14))
            back_gap = float(u(0.03, 0.12)) if rng.random() < 0.4 else 0.0
        if leg_style == "pedestal" and back_gap == 0.0 and back_style in ("solid", "curved"):
            back_gap = float(u(0.04, 0.12))
        rear_posts_from_legs = bool(
            leg_style == "straight" and back_style in ("slats", "ladder") and rng.random() < 0.6
        )

    arm_style, arm_height, arm_width = "none", 0.0, 0.0
    if not stool and rng.random() < 0.35:
        if leg_style in ("sled", "cantilever"):
            arm_style = _choice(rng, ARM_STYLES, [0, 0.3, 0.2, 0.5])
        elif leg_style == "pedestal":
            arm_style = "bar"
        else:
            arm_style = _choice(rng, ARM_STYLES, [0, 0.5, 0.3, 0.2])
        arm_height = float(u(0.17, 0.28))
        arm_width = float(u(0.035, 0.09))

    return ChairParams(
        asset_id=aid,
        seat_shape=seat_shape,
        seat_exponent=seat_exponent,
        seat_width=seat_width,
        seat_depth=seat_depth,
        seat_thickness=seat_thickness,
        seat_height=seat_height,
        seat_taper=seat_taper,
        leg_style=leg_style,
        leg_section=leg_section,
        leg_thickness=leg_thickness,
        leg_inset=leg_inset,
        leg_splay_deg=leg_splay_deg,
        stretchers=stretchers,
        stretcher_height_frac=stretcher_height_frac,
        apron=apron,
        apron_height=apron_height,
        base_kind=base_kind,
        base_arms=base_arms,
        base_radius=base_radius,
        column_radius=column_radius,
        runner_overhang=runner_overhang,
        back_style=back_style,
        back_height=back_height,
        back_width_frac=back_width_frac,
        back_tilt_deg=back_tilt_deg,
        back_thickness=back_thickness,
        back_top_round=back_top_round,
        back_top_width_frac=back_top_width_frac,
        back_gap=back_gap,
        back_count=back_count,
        back_curvature=back_curvature,
        post_thickness=post_thickness,
        rear_posts_from_legs=rear_posts_from_legs,
        arm_style=arm_style,
        arm_height=arm_height,
        arm_width=arm_width,
    )
