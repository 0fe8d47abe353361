"""The manipulation split's edits, in pure Python: which object moves where, whose background.

Data flow: ``worker.render_manip_one`` -> :func:`make_manip_scene` (``sampling.make_scene``
for ``split="manip"``, then the edits drawn here) -> :func:`variant_spec` for each variant
-> ``blender_backend`` -> ``manip_writer``. :meth:`ManipEdit.to_json` is the scene JSON's
``"manipulation"`` record; :func:`variant_specs_from_json` rebuilds every variant's
:class:`~generators.spec.SceneSpec` from a scene JSON alone, so a variant re-renders
without the preset or the donor scene's own JSON. Nothing here imports bpy.

The edits (uORF's scene-manipulation test, KovenYu/uORF ``scripts/eval_scene_manip.sh``):

- *moved*: one object of the scene translated on the floor by ``(dx, dy)``. Drawn from
  ``numpy.random.default_rng([scene_seed, 0, 1])`` (:func:`manip_rng`): the objects in a
  random order; per object up to :data:`MOVE_TRIES` offsets, direction uniform, length
  uniform in :data:`OFFSET_RANGE` world units. An offset is kept when the moved centre
  stays in the preset's placement square (``+-xy_range``), its bounding circle keeps
  ``min_gap`` to every other object, and the moved scene passes the sampler's visibility
  check (every object, the moved one included, covers ``min_pixels`` of view 0; the
  top-left sentinel corner of every view stays background).
- *changed*: the scene with the background (``ground``: floor and walls with their
  textures or colour, and ``world``: the environment light) of a donor scene of the same
  split; objects, lights and cameras stay. The donor is drawn from the same stream among
  the other scenes ``0 .. n-1`` of the split: the first of up to :data:`DONOR_CANDIDATES`
  whose background differs, else the first drawn. Presets without rooms have one ground
  for every scene, so there the background does not change (``differs: false``).
- *providing_bg*: the donor scene (its objects, lights and background) seen from this
  scene's cameras: the image a model takes the new background from.

The donor depends on the split's scene count ``n`` (it is drawn from ``0 .. n-1``); the
manifest of a manipulation split records ``n`` and a rerun with another ``--n`` is refused.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from generators.presets import Preset
from generators.sampling import make_scene, visibility_problems, visible_pixel_counts
from generators.spec import GroundSpec, LightSpec, ObjectSpec, RenderSettings, SceneSpec, WorldSpec
from scenefmt import MANIP_SPLIT, MANIP_VARIANTS

__all__ = [
    "DONOR_CANDIDATES",
    "MOVE_TRIES",
    "OFFSET_RANGE",
    "BackgroundEdit",
    "ManipEdit",
    "MoveEdit",
    "choose_donor",
    "choose_move",
    "make_manip_scene",
    "manip_rng",
    "variant_spec",
    "variant_specs_from_json",
]

#: Length of the translation of the moved object, world units (uniform in this range).
OFFSET_RANGE = (1.0, 2.5)
#: Offsets tried per object before the next object is tried.
MOVE_TRIES = 60
#: Donor scenes examined for a background that differs from the scene's own.
DONOR_CANDIDATES = 16


def manip_rng(scene_seed: int) -> np.random.Generator:
    """The edit stream of a scene: ``default_rng([scene_seed, 0, 1])`` (three words, so it
    never equals a sampling attempt's ``default_rng([scene_seed, k])``)."""
    return np.random.default_rng([int(scene_seed), 0, 1])


@dataclass(frozen=True)
class MoveEdit:
    """Object ``instance_id`` translated by ``offset`` (world units, world x and y)."""

    instance_id: int
    offset: tuple[float, float]
    position_before: tuple[float, float, float]
    position_after: tuple[float, float, float]

    def to_json(self) -> dict[str, Any]:
        return {
            "instance_id": self.instance_id,
            "offset": list(self.offset),
            "position_before": list(self.position_before),
            "position_after": list(self.position_after),
            "units": "world units, world frame (+z up); only x and y change",
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> MoveEdit:
        return cls(
            int(d["instance_id"]),
            (float(d["offset"][0]), float(d["offset"][1])),
            tuple(float(v) for v in d["position_before"]),  # type: ignore[arg-type]
            tuple(float(v) for v in d["position_after"]),  # type: ignore[arg-type]
        )


@dataclass(frozen=True)
class BackgroundEdit:
    """The donor scene: its background (``ground``, ``world``) and, for the providing
    view, its objects and lights."""

    donor_scene: int
    differs: bool
    ground: GroundSpec
    world: WorldSpec
    donor_objects: tuple[ObjectSpec, ...]
    donor_lights: tuple[LightSpec, ...]

    def to_json(self) -> dict[str, Any]:
        return {
            "donor_scene": self.donor_scene,
            "differs": self.differs,
            "ground": self.ground.to_json(),
            "world": self.world.to_json(),
            "donor_objects": [o.to_json() for o in self.donor_objects],
            "donor_lights": [x.to_json() for x in self.donor_lights],
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> BackgroundEdit:
        return cls(
            int(d["donor_scene"]),
            bool(d["differs"]),
            GroundSpec.from_json(d["ground"]),
            WorldSpec.from_json(d["world"]),
            tuple(ObjectSpec.from_json(o) for o in d["donor_objects"]),
            tuple(LightSpec.from_json(x) for x in d["donor_lights"]),
        )


@dataclass(frozen=True)
class ManipEdit:
    """Both edits of one manipulation scene (the scene JSON's ``manipulation`` record)."""

    move: MoveEdit
    background: BackgroundEdit

    def to_json(self) -> dict[str, Any]:
        return {
            "format": "svorf-manip",
            "rng": "numpy.random.default_rng([scene_seed, 0, 1])",
            "variants": list(MANIP_VARIANTS),
            "move": self.move.to_json(),
            "background": self.background.to_json(),
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> ManipEdit:
        return cls(MoveEdit.from_json(d["move"]), BackgroundEdit.from_json(d["background"]))


# ---------------------------------------------------------------------------- variants


def variant_spec(spec: SceneSpec, edit: ManipEdit, variant: str) -> SceneSpec:
    """The scene to render for ``variant`` (``moved``, ``changed`` or ``providing_bg``)."""
    if variant == "moved":
        k, (dx, dy) = edit.move.instance_id, edit.move.offset
        objs = tuple(
            replace(o, position=(o.position[0] + dx, o.position[1] + dy, o.position[2]))
            if o.instance_id == k
            else o
            for o in spec.objects
        )
        if objs == spec.objects:
            raise ValueError(f"edit: the scene has no object with instance_id {k}")
        return replace(spec, objects=objs)
    bg = edit.background
    if variant == "changed":
        return replace(spec, ground=bg.ground, world=bg.world)
    if variant == "providing_bg":
        return replace(
            spec, objects=bg.donor_objects, lights=bg.donor_lights, ground=bg.ground,
            world=bg.world,
        )  # fmt: skip
    raise ValueError(f"variant must be one of {MANIP_VARIANTS}, got {variant!r}")


def variant_specs_from_json(scene_json: dict[str, Any]) -> dict[str, SceneSpec]:
    """Every variant's spec from a manipulation scene's JSON alone (``sc%04d.json``)."""
    if "manipulation" not in scene_json:
        raise ValueError("scene JSON has no 'manipulation' record (not a manip split scene)")
    spec = SceneSpec.from_json(scene_json)
    spec = replace(spec, extra=tuple((k, v) for k, v in spec.extra if k != "manipulation"))
    edit = ManipEdit.from_json(scene_json["manipulation"])
    return {v: variant_spec(spec, edit, v) for v in MANIP_VARIANTS}


# ---------------------------------------------------------------------------- drawing


def choose_move(preset: Preset, spec: SceneSpec, rng: np.random.Generator) -> MoveEdit:
    """Draw the moved object and its offset (rules in the module docstring).

    Raises:
        RuntimeError: no object of the scene can be moved within the rules.
    """
    counts = visible_pixel_counts(spec, preset.visibility_resolution)
    objs = [o for o in spec.objects if counts[o.instance_id] >= preset.min_pixels]
    lo, hi = OFFSET_RANGE
    lim = preset.xy_range
    for i in rng.permutation(len(objs)):
        o = objs[int(i)]
        r = o.bounding_radius_xy
        others = [(p.position[0], p.position[1], p.bounding_radius_xy) for p in spec.objects
                  if p.instance_id != o.instance_id]  # fmt: skip
        for _ in range(MOVE_TRIES):
            ang = float(rng.uniform(0.0, 2.0 * np.pi))
            length = float(rng.uniform(lo, hi))
            dx, dy = length * np.cos(ang), length * np.sin(ang)
            x, y = o.position[0] + dx, o.position[1] + dy
            if abs(x) > lim or abs(y) > lim:
                continue
            if any(np.hypot(x - px, y - py) - r - pr < preset.min_gap for px, py, pr in others):
                continue
            move = MoveEdit(o.instance_id, (float(dx), float(dy)), o.position,
                            (float(x), float(y), o.position[2]))  # fmt: skip
            probe = ManipEdit(move, _no_background(spec))
            if not visibility_problems(variant_spec(spec, probe, "moved"), preset):
                return move
    raise RuntimeError(
        f"scene {spec.index}: no object can be moved by {lo}-{hi} world units within "
        f"+-{lim} without a collision or hiding an object"
    )


def _no_background(spec: SceneSpec) -> BackgroundEdit:
    return BackgroundEdit(spec.index, False, spec.ground, spec.world, (), ())


def choose_donor(
    preset: Preset,
    index: int,
    n: int,
    seed: int,
    rng: np.random.Generator,
    own: SceneSpec,
    render: RenderSettings | None = None,
) -> tuple[int, SceneSpec]:
    """Draw the donor scene among ``0 .. n-1`` without ``index`` (module docstring).

    Returns:
        ``(donor index, donor spec)``.
    """
    if n < 2:
        raise ValueError(
            "--n must be >= 2 for the manip split (the background comes from another scene)"
        )
    order = [int(j) for j in rng.permutation(n) if int(j) != index]
    first: tuple[int, SceneSpec] | None = None
    for j in order[:DONOR_CANDIDATES]:
        donor = make_scene(preset, MANIP_SPLIT, j, seed, render)
        if first is None:
            first = (j, donor)
        if preset.room is None:  # one ground for every scene: nothing differs
            break
        if (donor.ground, donor.world) != (own.ground, own.world):
            return j, donor
    assert first is not None
    return first


def make_manip_scene(
    preset: Preset, index: int, n: int, seed: int, render: RenderSettings | None = None
) -> tuple[SceneSpec, ManipEdit]:
    """Scene ``index`` of the manipulation split of ``preset`` and its edits: a pure
    function of the arguments.

    Args:
        preset: the dataset preset (not a derived one such as ``clevr567-gray``).
        index: scene index, ``0 <= index < n``.
        n: scene count of the split (the donor is one of its other scenes).
        seed: dataset seed.
        render: render settings recorded in the spec.
    """
    if preset.scene_source:
        raise ValueError(
            f"--split {MANIP_SPLIT}: preset {preset.name!r} converts another preset's scenes; "
            f"make the manip split of {preset.scene_source!r} instead"
        )
    if not 0 <= index < n:
        raise ValueError(f"index must be in [0, {n}), got {index}")
    spec = make_scene(preset, MANIP_SPLIT, index, seed, render)
    rng = manip_rng(spec.scene_seed)
    move = choose_move(preset, spec, rng)
    j, donor = choose_donor(preset, index, n, seed, rng, spec, render)
    differs = (donor.ground, donor.world) != (spec.ground, spec.world)
    bg = BackgroundEdit(j, differs, donor.ground, donor.world, donor.objects, donor.lights)
    return spec, ManipEdit(move, bg)
