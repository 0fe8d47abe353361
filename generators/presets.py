"""The preset registry: every dataset the generator can make, as frozen config.

Data flow: ``generate --preset NAME`` -> :func:`get_preset` -> :class:`Preset` ->
``sampling.sample_scene(preset, rng)`` -> ``SceneSpec``. Nothing here imports bpy;
a preset is plain data (saved verbatim in ``manifest.json``).

Adding a preset = adding one entry to :data:`PRESETS`. Split-specific object rules
(held-out combinations) live in :attr:`Preset.split_objects`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Any

from scenefmt.clevr import CLEVR_COLORS, CLEVR_SIZES  # re-exported: presets use both
from scenefmt.cli_util import choose
from scenefmt.layout import MANIP_SPLIT

CLEVR_SHAPES: tuple[str, ...] = ("cube", "sphere", "cylinder")

#: Materials the backend knows (Principled BSDF parameters are recorded in the scene JSON).
MATERIALS: dict[str, dict[str, float]] = {
    # CLEVR's "Rubber" is a matte material: mostly diffuse with a faint broad highlight.
    "rubber": {"roughness": 0.9, "specular_ior_level": 0.25, "metallic": 0.0},
}

#: Split -> code in the scene seed. ``manip`` is the manipulation split (moved and
#: background-changed variants, ``generators.manip``): scenes of their own, never a test scene.
SPLIT_CODES: dict[str, int] = {"train": 0, "test": 1, MANIP_SPLIT: 2}


@dataclass(frozen=True)
class ObjectRules:
    """What objects a scene may contain.

    Attributes:
        n_objects: inclusive (min, max) object count per scene.
        shapes: allowed shape names.
        colors: allowed CLEVR colour names.
        sizes: allowed CLEVR size names.
        materials: allowed material names.
        allowed_combos: if set, each object's (shape, colour) is drawn uniformly from
            this list (``shapes``/``colors`` are then ignored).
        forbidden_combos: (shape, colour) pairs that are re-drawn when they come up.
    """

    n_objects: tuple[int, int] = (5, 7)
    shapes: tuple[str, ...] = CLEVR_SHAPES
    colors: tuple[str, ...] = tuple(CLEVR_COLORS)
    sizes: tuple[str, ...] = tuple(CLEVR_SIZES)
    materials: tuple[str, ...] = ("rubber",)
    allowed_combos: tuple[tuple[str, str], ...] | None = None
    forbidden_combos: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        lo, hi = self.n_objects
        if not 1 <= lo <= hi:
            raise ValueError(f"n_objects must be 1 <= min <= max, got {self.n_objects}")
        for s in self.shapes:
            if s not in CLEVR_SHAPES:
                raise ValueError(f"shapes: unknown shape {s!r} (known: {CLEVR_SHAPES})")
        for c in self.colors:
            if c not in CLEVR_COLORS:
                raise ValueError(f"colors: unknown colour {c!r} (known: {tuple(CLEVR_COLORS)})")
        for z in self.sizes:
            if z not in CLEVR_SIZES:
                raise ValueError(f"sizes: unknown size {z!r} (known: {tuple(CLEVR_SIZES)})")
        for m in self.materials:
            if m not in MATERIALS:
                raise ValueError(f"materials: unknown material {m!r} (known: {tuple(MATERIALS)})")
        for s, c in (self.allowed_combos or ()) + self.forbidden_combos:
            if s not in CLEVR_SHAPES or c not in CLEVR_COLORS:
                raise ValueError(f"combo ({s!r}, {c!r}) names an unknown shape or colour")
        if self.allowed_combos is None:
            n_ok = sum(
                (s, c) not in self.forbidden_combos for s in self.shapes for c in self.colors
            )
            if n_ok == 0:
                raise ValueError("forbidden_combos excludes every (shape, colour) pair")
        elif len(self.allowed_combos) == 0:
            raise ValueError("allowed_combos must not be empty")


@dataclass(frozen=True)
class CameraRig:
    """The uORF-style camera rig: ``n_views`` cameras on a sphere looking at the origin.

    Attributes:
        n_views: views per scene.
        radius: distance of the camera centre from the look-at point (world units).
        radius_jitter: radius is drawn uniformly in ``radius +- radius_jitter``.
        elevation_deg: elevation above the ground plane.
        elevation_jitter_deg: elevation drawn uniformly in ``elevation +- jitter``.
        azimuth: ``"uniform"`` (each view's azimuth uniform in [0, 360), independent)
            or ``"stratified"`` (a random base azimuth, view k at ``base + k*360/n_views``
            plus a uniform ``+- azimuth_jitter_deg``).
        azimuth_jitter_deg: only for ``"stratified"``.
        lens_mm: focal length; with ``sensor_width_mm`` it fixes the field of view
            (35/32 is CLEVR's and uORF's camera: 49.1 degrees horizontal).
        sensor_width_mm: Blender sensor width (sensor fit HORIZONTAL).
    """

    n_views: int = 4
    radius: float = 12.4
    radius_jitter: float = 0.2
    elevation_deg: float = 40.0
    elevation_jitter_deg: float = 3.0
    azimuth: str = "uniform"
    azimuth_jitter_deg: float = 20.0
    lens_mm: float = 35.0
    sensor_width_mm: float = 32.0

    def __post_init__(self) -> None:
        if self.n_views < 1:
            raise ValueError(f"n_views must be >= 1, got {self.n_views}")
        if not self.radius - self.radius_jitter > 0:
            raise ValueError(f"radius must exceed radius_jitter, got {self.radius}")
        if self.azimuth not in ("uniform", "stratified"):
            raise ValueError(f"azimuth must be 'uniform' or 'stratified', got {self.azimuth!r}")
        if not 0 < self.elevation_deg < 90:
            raise ValueError(f"elevation_deg must be in (0, 90), got {self.elevation_deg}")


@dataclass(frozen=True)
class LightRig:
    """CLEVR-style three-point lighting: area lights aimed at the origin.

    Base positions follow CLEVR's ``base_scene.blend`` (key front-right, fill left,
    back light behind); each coordinate gets a uniform ``+- jitter`` per scene, as
    CLEVR's ``--key_light_jitter`` etc. Energies are Cycles watts.
    """

    key_position: tuple[float, float, float] = (6.4467, -2.9052, 4.2584)
    fill_position: tuple[float, float, float] = (-4.6711, -4.0136, 3.0112)
    back_position: tuple[float, float, float] = (-1.1685, 2.6460, 5.8157)
    jitter: float = 1.0
    key_energy: float = 350.0
    fill_energy: float = 100.0
    back_energy: float = 150.0
    size: float = 2.0
    world_color: tuple[float, float, float] = (0.3, 0.3, 0.3)
    world_strength: float = 1.0


@dataclass(frozen=True)
class GroundRules:
    """CLEVR-like ground: a large matte grey plane at z=0 (background, instance id 0)."""

    size: float = 100.0
    color_linear: tuple[float, float, float] = (0.28, 0.28, 0.28)
    roughness: float = 0.9


@dataclass(frozen=True)
class RoomRules:
    """Room presets: procedural chairs on a textured floor, textured walls around.

    Attributes:
        n_chairs: inclusive (min, max) chairs per scene.
        asset_pool: number of procedural chair ids to draw from (ids ``0..pool-1``).
        same_shape: one chair id for all chairs of a scene (else distinct ids).
        n_backgrounds: background ids ``0..n-1`` (``background_params`` -> floor, wall
            texture ids).
        chair_scale: uniform scale of the canonical chair (max horizontal extent 1.0).
        room_half_size: walls stand at ``x, y = +-room_half_size`` (cameras inside).
        wall_height: wall height (world units).
        texture_tile: world units per texture repeat (box projection).
        texture_size: texture image side in pixels.
    """

    n_chairs: tuple[int, int] = (3, 4)
    asset_pool: int = 1
    same_shape: bool = True
    n_backgrounds: int = 3
    chair_scale: float = 1.3
    room_half_size: float = 11.0
    wall_height: float = 6.0
    texture_tile: float = 4.0
    texture_size: int = 256

    def __post_init__(self) -> None:
        lo, hi = self.n_chairs
        if not 1 <= lo <= hi:
            raise ValueError(f"n_chairs must be 1 <= min <= max, got {self.n_chairs}")
        if self.asset_pool < 1 or self.n_backgrounds < 1:
            raise ValueError("asset_pool and n_backgrounds must be >= 1")
        if not self.same_shape and self.asset_pool < hi:
            raise ValueError(f"asset_pool {self.asset_pool} < {hi} distinct chairs per scene")


@dataclass(frozen=True)
class Preset:
    """One dataset recipe.

    Attributes:
        name: registry key (``--preset``).
        description: one line for ``--help`` and the manifest.
        splits: ((split name, default scene count), ...).
        objects: object rules for every split not overridden in ``split_objects``.
        split_objects: ((split, rules), ...) overrides (held-out combinations).
        xy_range: object centres are uniform in ``[-xy_range, xy_range]^2``.
        min_gap: minimum distance between the xy bounding circles of two objects
            (world units); 0 means touching allowed, never interpenetrating.
        max_placement_tries: tries per object before the whole layout restarts.
        camera: the camera rig.
        lights: the light rig.
        ground: the ground plane.
        min_pixels: every object must cover at least this many pixels of view 0 in a
            ``visibility_resolution`` square ray cast, else the scene is re-sampled.
        visibility_resolution: resolution of that ray cast; fixed (not the output
            resolution) so that a scene does not depend on ``--resolution``.
        max_attempts: re-sampling attempts before giving up with an error.
        num_slots: suggested slot count for models (objects + background).
        scene_source: preset whose scene sampling (and seeds) this preset reuses.
        grayscale: RGB is converted to Rec.601 luma, stored as 3 equal channels.
        room: chairs-in-a-room rules (None = CLEVR objects on a plain ground).
    """

    name: str
    description: str
    splits: tuple[tuple[str, int], ...]
    objects: ObjectRules = field(default_factory=ObjectRules)
    split_objects: tuple[tuple[str, ObjectRules], ...] = ()
    xy_range: float = 3.0
    min_gap: float = 0.25
    max_placement_tries: int = 100
    camera: CameraRig = field(default_factory=CameraRig)
    lights: LightRig = field(default_factory=LightRig)
    ground: GroundRules = field(default_factory=GroundRules)
    min_pixels: int = 16
    visibility_resolution: int = 128
    max_attempts: int = 500
    num_slots: int = 8
    scene_source: str | None = None
    grayscale: bool = False
    room: RoomRules | None = None

    def split_names(self) -> tuple[str, ...]:
        """The preset's splits, then ``manip`` for presets that sample their own scenes."""
        names = tuple(s for s, _ in self.splits)
        return names if self.scene_source else (*names, MANIP_SPLIT)

    def split_size(self, split: str) -> int:
        """Default scene count of ``split`` (``manip``: the last split's, uORF's 500 test
        scenes); ValueError if the preset has no such split."""
        for s, n in self.splits:
            if s == split:
                return n
        if split == MANIP_SPLIT and not self.scene_source:
            return self.splits[-1][1]
        raise ValueError(
            f"split: preset {self.name!r} has no split {split!r} (it has: {', '.join(self.split_names())})"
        )

    def rules(self, split: str) -> ObjectRules:
        """Object rules of ``split``."""
        for s, r in self.split_objects:
            if s == split:
                return r
        return self.objects

    def with_camera_radius(self, radius: float) -> Preset:
        """Copy with another camera radius (closer cameras for small CPU-scale datasets)."""
        if radius <= self.camera.radius_jitter:
            raise ValueError(f"camera_radius must exceed {self.camera.radius_jitter}, got {radius}")
        return replace(self, camera=replace(self.camera, radius=float(radius)))

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


_HELDOUT = (("cylinder", "red"), ("sphere", "blue"))

PRESETS: dict[str, Preset] = {}


def register(preset: Preset) -> Preset:
    """Add ``preset`` to :data:`PRESETS` (name must be new)."""
    if preset.name in PRESETS:
        raise ValueError(f"preset {preset.name!r} is already registered")
    PRESETS[preset.name] = preset
    return preset


register(
    Preset(
        name="clevr567",
        description="5-7 CLEVR objects (uORF CLEVR-567)",
        splits=(("train", 1000), ("test", 500)),
    )
)
register(
    Preset(
        name="clevr567-heldout",
        description="CLEVR-567; train never has a red cylinder or blue sphere, test has only those",
        splits=(("train", 1000), ("test", 500)),
        objects=ObjectRules(forbidden_combos=_HELDOUT),
        split_objects=(("test", ObjectRules(allowed_combos=_HELDOUT)),),
    )
)
register(
    Preset(
        name="packed-clevr11",
        description="exactly 11 CLEVR objects packed into the CLEVR-567 area (occlusions)",
        splits=(("test", 500),),
        objects=ObjectRules(n_objects=(11, 11)),
        # Touching is allowed, interpenetration never; 0.02 keeps coincident faces apart.
        min_gap=0.02,
        max_placement_tries=200,
        # Heavy occlusion: an object only has to show a few pixels in view 0.
        min_pixels=4,
        max_attempts=2000,
        num_slots=12,
    )
)
register(
    Preset(
        name="clevr567-gray",
        description="the clevr567 scenes (same seeds) in grayscale (Rec.601 luma, 3 equal channels)",
        splits=(("test", 500),),
        scene_source="clevr567",
        grayscale=True,
    )
)


register(
    Preset(
        name="room-chair",
        description="3-4 chairs of one procedural shape in a room, 3 floor/wall backgrounds",
        splits=(("train", 1000), ("test", 500)),
        room=RoomRules(n_chairs=(3, 4), asset_pool=1, same_shape=True, n_backgrounds=3),
        min_gap=0.1,
        num_slots=5,
    )
)
register(
    Preset(
        name="room-diverse",
        description="4 distinct chairs per scene from 1200 procedural shapes, 50 backgrounds",
        splits=(("train", 5000), ("test", 500)),
        room=RoomRules(n_chairs=(4, 4), asset_pool=1200, same_shape=False, n_backgrounds=50),
        min_gap=0.1,
        num_slots=5,
    )
)


def get_preset(name: str) -> Preset:
    """The registered preset ``name``; otherwise a one-line ValueError that lists the
    known ones (and says "did you mean ...?" for a near miss)."""
    return PRESETS[choose(name, sorted(PRESETS), "preset")]


def scene_preset(preset: Preset) -> Preset:
    """The preset whose sampling rules make ``preset``'s scenes (follows ``scene_source``)."""
    return get_preset(preset.scene_source) if preset.scene_source else preset
