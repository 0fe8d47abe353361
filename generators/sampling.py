"""Scene sampling: preset + seed -> SceneSpec, in pure Python (no bpy).

Data flow: ``pipeline`` calls :func:`make_scene` for every scene index; it derives
the scene seed (:func:`scene_seed`), draws a scene with :func:`sample_scene`, and
re-draws (from a documented derived stream) until :func:`visibility_problems`
finds nothing wrong. The result goes to ``blender_backend`` and the writer.

Seeds are data: ``scene_seed = seed * 1_000_000 + split_code * 100_000 + index``
(split_code train 0, test 1; index < 100_000), so train and test scenes never share
a random stream. Attempt 0 uses ``numpy.random.default_rng(scene_seed)``, attempt
k >= 1 uses ``numpy.random.default_rng([scene_seed, k])``; the JSON stores
``seed``, ``scene_seed`` and ``attempt``.

Object placement follows CLEVR's ``render_images.py``: objects are added one at a
time at uniform positions in ``[-xy_range, xy_range]^2``; a position is rejected if
the xy bounding circles (radius r for every CLEVR shape: sphere/cylinder radius r,
cube half-diagonal (r/sqrt 2)*sqrt 2) come closer than ``min_gap``; after
``max_placement_tries`` failures for one object the whole layout restarts.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from generators import geometry
from generators.presets import (
    CLEVR_COLORS,
    CLEVR_SIZES,
    SPLIT_CODES,
    ObjectRules,
    Preset,
    scene_preset,
)
from generators.spec import (
    GroundSpec,
    LightSpec,
    ObjectSpec,
    RenderSettings,
    SceneSpec,
    ViewSpec,
    WorldSpec,
)

MAX_SCENES_PER_SPLIT = 100_000
_MAX_LAYOUT_RESTARTS = 10_000
#: The ``_mask.png`` sentinel block must be background at every output resolution
#: R >= 16. It is ``b x b`` top-left pixels with ``b = scenefmt.sentinel_size(R, R)``:
#: b = 1 (pixel (0, 0), centre at 0.5 / R <= 1/32) for R < 128, and
#: b = R // 128 + 1 <= R / 32 for R >= 128, so the whole block lies in the top-left
#: 1/32 x 1/32 of the image, the corner region checked here by a 5x5 ray grid
#: (``tests/test_sampling.py`` checks this for R = 16 .. 4096).
_CORNER_FRACTION = 1.0 / 32.0


def scene_seed(seed: int, split: str, index: int) -> int:
    """``seed * 1_000_000 + split_code * 100_000 + index`` (train 0, test 1)."""
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    if split not in SPLIT_CODES:
        raise ValueError(f"split must be one of {tuple(SPLIT_CODES)}, got {split!r}")
    if not 0 <= index < MAX_SCENES_PER_SPLIT:
        raise ValueError(f"index must be in [0, {MAX_SCENES_PER_SPLIT}), got {index}")
    return seed * 1_000_000 + SPLIT_CODES[split] * 100_000 + index


def attempt_rng(scene_seed_: int, attempt: int) -> np.random.Generator:
    """The random stream of sampling attempt ``attempt`` (see module docstring)."""
    if attempt == 0:
        return np.random.default_rng(scene_seed_)
    return np.random.default_rng([scene_seed_, attempt])


def _draw_shape_color(rules: ObjectRules, rng: np.random.Generator) -> tuple[str, str]:
    if rules.allowed_combos is not None:
        return rules.allowed_combos[int(rng.integers(len(rules.allowed_combos)))]
    while True:
        shape = rules.shapes[int(rng.integers(len(rules.shapes)))]
        color = rules.colors[int(rng.integers(len(rules.colors)))]
        if (shape, color) not in rules.forbidden_combos:
            return shape, color


def _layout(preset: Preset, rules: ObjectRules, rng: np.random.Generator) -> list[ObjectSpec]:
    lo, hi = rules.n_objects
    lim = preset.xy_range
    for _ in range(_MAX_LAYOUT_RESTARTS):
        n = int(rng.integers(lo, hi + 1))
        placed: list[tuple[float, float, float]] = []  # (x, y, bounding radius)
        objects: list[ObjectSpec] = []
        for i in range(n):
            size_name = rules.sizes[int(rng.integers(len(rules.sizes)))]
            r = CLEVR_SIZES[size_name]
            for _try in range(preset.max_placement_tries):
                x, y = (float(v) for v in rng.uniform(-lim, lim, size=2))
                if all(
                    np.hypot(x - px, y - py) - r - pr >= preset.min_gap for px, py, pr in placed
                ):
                    break
            else:
                break  # this object did not fit: restart the layout
            shape, color = _draw_shape_color(rules, rng)
            material = rules.materials[int(rng.integers(len(rules.materials)))]
            yaw = float(rng.uniform(0.0, 360.0))
            z = r / np.sqrt(2.0) if shape == "cube" else r  # rest on z = 0
            placed.append((x, y, r))
            objects.append(
                ObjectSpec(
                    instance_id=i + 1,
                    shape=shape,
                    color=color,
                    rgb=CLEVR_COLORS[color],
                    material=material,
                    size=r,
                    size_name=size_name,
                    position=(x, y, float(z)),
                    rotation=yaw,
                )
            )
        if len(objects) == n:
            return objects
    raise RuntimeError(
        f"preset {preset.name!r}: could not place {rules.n_objects} objects with min_gap "
        f"{preset.min_gap} in +-{lim} after {_MAX_LAYOUT_RESTARTS} restarts"
    )


def _room_layout(preset: Preset, rng: np.random.Generator) -> tuple[list[ObjectSpec], GroundSpec]:
    """Chairs (procedural assets) placed like CLEVR objects, plus a textured room.

    Draw order: chair count, asset id(s), then per chair: position tries, yaw, colour;
    finally the background id.
    """
    from assets_procedural import background_params

    room = preset.room
    assert room is not None
    lo, hi = room.n_chairs
    lim = preset.xy_range
    colors = tuple(CLEVR_COLORS)
    for _ in range(_MAX_LAYOUT_RESTARTS):
        n = int(rng.integers(lo, hi + 1))
        if room.same_shape:
            ids = [int(rng.integers(room.asset_pool))] * n
        else:
            ids = [int(i) for i in rng.choice(room.asset_pool, size=n, replace=False)]
        placed: list[tuple[float, float, float]] = []
        objects: list[ObjectSpec] = []
        for i, asset in enumerate(ids):
            probe = ObjectSpec(i + 1, "chair", "", (0, 0, 0), "rubber", room.chair_scale, "",
                               (0.0, 0.0, 0.0), 0.0, asset)  # fmt: skip
            r = probe.bounding_radius_xy
            for _try in range(preset.max_placement_tries):
                x, y = (float(v) for v in rng.uniform(-lim, lim, size=2))
                if all(
                    np.hypot(x - px, y - py) - r - pr >= preset.min_gap for px, py, pr in placed
                ):
                    break
            else:
                break
            yaw = float(rng.uniform(0.0, 360.0))
            color = colors[int(rng.integers(len(colors)))]
            placed.append((x, y, r))
            objects.append(replace(probe, color=color, rgb=CLEVR_COLORS[color],
                                   position=(x, y, 0.0), rotation=yaw))  # fmt: skip
        if len(objects) == n:
            break
    else:
        raise RuntimeError(f"preset {preset.name!r}: could not place {room.n_chairs} chairs")
    bg = int(rng.integers(room.n_backgrounds))
    floor_id, wall_id = background_params(bg)
    g = preset.ground
    ground = GroundSpec(
        size=2 * room.room_half_size, color_linear=g.color_linear, roughness=g.roughness,
        type="room", background_id=bg, floor_texture_id=int(floor_id),
        wall_texture_id=int(wall_id), wall_half_size=room.room_half_size,
        wall_height=room.wall_height, texture_tile=room.texture_tile,
        texture_size=room.texture_size,
    )  # fmt: skip
    return objects, ground


def _lights(preset: Preset, rng: np.random.Generator) -> tuple[LightSpec, ...]:
    rig = preset.lights
    out = []
    for name, base, energy in (
        ("key", rig.key_position, rig.key_energy),
        ("fill", rig.fill_position, rig.fill_energy),
        ("back", rig.back_position, rig.back_energy),
    ):
        pos = np.asarray(base, dtype=np.float64) + rng.uniform(-rig.jitter, rig.jitter, size=3)
        out.append(
            LightSpec(
                name=name,
                position=tuple(float(v) for v in pos),  # type: ignore[arg-type]
                target=(0.0, 0.0, 0.0),
                energy=float(energy),
                size=float(rig.size),
            )
        )
    return tuple(out)


def _views(preset: Preset, rng: np.random.Generator) -> tuple[ViewSpec, ...]:
    cam = preset.camera
    base = float(rng.uniform(0.0, 360.0)) if cam.azimuth == "stratified" else 0.0
    views = []
    for k in range(cam.n_views):
        if cam.azimuth == "stratified":
            az = (
                base
                + k * 360.0 / cam.n_views
                + rng.uniform(-cam.azimuth_jitter_deg, cam.azimuth_jitter_deg)
            )
        else:
            az = rng.uniform(0.0, 360.0)
        az = float(az % 360.0)
        el = float(
            cam.elevation_deg + rng.uniform(-cam.elevation_jitter_deg, cam.elevation_jitter_deg)
        )
        rad = float(cam.radius + rng.uniform(-cam.radius_jitter, cam.radius_jitter))
        c2w = geometry.look_at_cam_to_world(geometry.camera_position(rad, az, el))
        views.append(
            ViewSpec(
                azimuth_deg=az,
                elevation_deg=el,
                radius=rad,
                cam_to_world=tuple(tuple(float(x) for x in row) for row in c2w),  # type: ignore[arg-type]
                lens_mm=cam.lens_mm,
                sensor_width_mm=cam.sensor_width_mm,
            )
        )
    return tuple(views)


def sample_scene(preset: Preset, rng: np.random.Generator, *, split: str = "train") -> SceneSpec:
    """Draw one scene (no visibility check; see :func:`make_scene`).

    Draw order (part of the format: changing it changes every dataset): objects
    (count, then per object size, position tries, shape/colour, material, yaw),
    lights (key, fill, back jitter), cameras (per view azimuth, elevation, radius).

    Args:
        preset: the preset whose rules apply (use ``scene_preset`` for derived presets).
        rng: the random stream; consumed.
        split: selects split-specific object rules.

    Returns:
        A SceneSpec with ``index``/``seed``/``scene_seed``/``attempt`` set to 0
        (:func:`make_scene` fills them in).
    """
    g = preset.ground
    if preset.room is not None:
        objects, ground = _room_layout(preset, rng)
    else:
        objects = _layout(preset, preset.rules(split), rng)
        ground = GroundSpec(size=g.size, color_linear=g.color_linear, roughness=g.roughness)
    lights = _lights(preset, rng)
    views = _views(preset, rng)
    return SceneSpec(
        preset=preset.name,
        split=split,
        index=0,
        seed=0,
        scene_seed=0,
        attempt=0,
        objects=tuple(objects),
        lights=lights,
        ground=ground,
        world=WorldSpec(
            color_linear=preset.lights.world_color, strength=preset.lights.world_strength
        ),
        views=views,
    )


def visible_pixel_counts(spec: SceneSpec, resolution: int, view: int = 0) -> dict[int, int]:
    """Pixels of each instance id (objects only) in a ray cast of ``view``."""
    from generators.raycast import cast_view

    ids = cast_view(spec, view, resolution).ids
    counts = np.bincount(ids.ravel(), minlength=256)
    return {o.instance_id: int(counts[o.instance_id]) for o in spec.objects}


def _corner_ids(spec: SceneSpec, meshes) -> np.ndarray:
    """Instance ids hit by a 5x5 ray grid over each view's top-left corner region."""
    from generators.raycast import intersector

    merged, owner = geometry.concat_meshes(meshes[0])
    face_ids = np.asarray(meshes[1], dtype=np.uint8)[owner]
    inter = intersector(merged)
    t = np.linspace(0.0, _CORNER_FRACTION, 5)
    uu, vv = np.meshgrid(t, t)
    hits = []
    for view in spec.views:
        K = view.K(1, 1)  # normalised image coordinates
        c2w = view.c2w()
        d_cam = np.stack(
            [(uu.ravel() - K[0, 2]) / K[0, 0], (vv.ravel() - K[1, 2]) / K[1, 1], np.ones(uu.size)],
            1,
        )
        dirs = d_cam @ c2w[:3, :3].T
        origins = np.broadcast_to(c2w[:3, 3], dirs.shape).copy()
        tri = inter.intersects_first(origins, dirs)
        hits.append(np.where(tri >= 0, face_ids[np.maximum(tri, 0)], 0))
    return np.concatenate(hits)


def visibility_problems(spec: SceneSpec, preset: Preset) -> list[str]:
    """Why ``spec`` is not acceptable (empty list = accept).

    Rules: in a ``preset.visibility_resolution`` square ray cast of view 0 every
    object covers at least ``preset.min_pixels`` pixels; in every view the top-left
    corner region (which holds the uORF mask sentinel block, ``scenefmt.sentinel_size``,
    at any resolution >= 16) sees background only.
    """
    problems = []
    meshes = spec.meshes()
    from generators.raycast import cast_view

    ids = cast_view(spec, 0, preset.visibility_resolution, meshes=meshes).ids
    counts = np.bincount(ids.ravel(), minlength=256)
    for o in spec.objects:
        if counts[o.instance_id] < preset.min_pixels:
            problems.append(
                f"object {o.instance_id} covers {counts[o.instance_id]} < {preset.min_pixels} pixels in view 0"
            )
    if np.any(_corner_ids(spec, meshes) != 0):
        problems.append("an object covers the top-left (sentinel) corner of a view")
    return problems


def make_scene(
    preset: Preset,
    split: str,
    index: int,
    seed: int,
    render: RenderSettings | None = None,
) -> SceneSpec:
    """The accepted scene ``index`` of ``split``: a pure function of its arguments.

    Args:
        preset: the dataset preset (its ``scene_source`` preset does the sampling,
            so derived presets such as ``clevr567-gray`` get identical scenes).
        split: ``train`` or ``test`` (must be one of the preset's splits).
        index: scene index in the split, ``0 <= index < 100_000``.
        seed: dataset seed, >= 0.
        render: render settings recorded in the spec.

    Raises:
        ValueError: bad argument. RuntimeError: no attempt passed the checks.
    """
    preset.split_size(split)  # validates the split name
    sp = scene_preset(preset) if preset.scene_source else preset
    if preset.scene_source and preset.camera != sp.camera:
        sp = replace(sp, camera=preset.camera)  # e.g. a camera-radius override
    ss = scene_seed(seed, split, index)
    last: list[str] = []
    for attempt in range(sp.max_attempts):
        spec = sample_scene(sp, attempt_rng(ss, attempt), split=split)
        last = visibility_problems(spec, sp)
        if not last:
            return replace(
                spec,
                index=index,
                seed=seed,
                scene_seed=ss,
                attempt=attempt,
                render=render or RenderSettings(),
            )
    raise RuntimeError(
        f"preset {preset.name!r} scene {index}: no acceptable scene in {sp.max_attempts} "
        f"attempts (last problems: {'; '.join(last)})"
    )
