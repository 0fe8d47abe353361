"""Scene sampling rules (pure Python + embree ray casts; no bpy)."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest

from generators import geometry
from generators.presets import CLEVR_COLORS, CLEVR_SIZES, PRESETS, get_preset
from generators.raycast import cast_view
from generators.sampling import (
    _CORNER_FRACTION,
    attempt_rng,
    make_scene,
    sample_scene,
    scene_seed,
)
from generators.spec import SceneSpec
from scenefmt import sentinel_size

P = get_preset("clevr567")


@pytest.fixture(scope="module")
def scenes():
    return [make_scene(P, "train", i, 0) for i in range(6)]


def test_scene_seed_formula_and_splits_differ():
    assert scene_seed(3, "train", 17) == 3_000_017
    assert scene_seed(3, "test", 17) == 3_100_017
    tr, te = make_scene(P, "train", 0, 0), make_scene(P, "test", 0, 0)
    assert tr.scene_seed != te.scene_seed
    assert tr.to_json() != te.to_json()
    for bad in [(-1, "train", 0), (0, "val", 0), (0, "train", 100_000)]:
        with pytest.raises(ValueError):
            scene_seed(*bad)


def test_make_scene_is_deterministic(scenes):
    again = make_scene(P, "train", 3, 0)
    assert json.dumps(again.to_json()) == json.dumps(scenes[3].to_json())
    assert make_scene(P, "train", 3, 1).to_json() != scenes[3].to_json()


def test_sample_scene_consumes_only_its_rng():
    a = sample_scene(P, attempt_rng(5, 0))
    b = sample_scene(P, np.random.default_rng(5))
    assert a == b


def test_clevr_object_rules(scenes):
    for s in scenes:
        assert 5 <= len(s.objects) <= 7
        assert [o.instance_id for o in s.objects] == list(range(1, len(s.objects) + 1))
        for o in s.objects:
            assert o.color in CLEVR_COLORS and o.rgb == CLEVR_COLORS[o.color]
            assert o.size in CLEVR_SIZES.values() and o.material == "rubber"
            assert -3 <= o.position[0] <= 3 and -3 <= o.position[1] <= 3
            zmin = o.world_mesh().vertices[:, 2].min()
            assert abs(zmin) < 1e-9  # rests on z = 0
            if o.shape == "cube":
                assert o.dimensions()["edge"] == pytest.approx(2 * o.size / math.sqrt(2))
        for a, b in itertools.combinations(s.objects, 2):
            d = math.hypot(a.position[0] - b.position[0], a.position[1] - b.position[1])
            assert d - a.size - b.size >= P.min_gap - 1e-12


def test_lights_and_cameras(scenes):
    for s in scenes:
        assert [lt.name for lt in s.lights] == ["key", "fill", "back"]
        assert len(s.views) == 4
        for v in s.views:
            assert abs(v.radius - 12.4) <= 0.2 + 1e-9 and abs(v.elevation_deg - 40) <= 3 + 1e-9
            c2w = v.c2w()
            assert np.allclose(c2w[:3, :3].T @ c2w[:3, :3], np.eye(3), atol=1e-12)
            # optical axis through the origin, camera at the stated radius
            eye, fwd = c2w[:3, 3], c2w[:3, 2]
            assert np.linalg.norm(eye) == pytest.approx(v.radius)
            assert np.allclose(np.cross(fwd, -eye / np.linalg.norm(eye)), 0, atol=1e-12)
            assert c2w[2, 0] == pytest.approx(0, abs=1e-12)  # no roll: x axis horizontal
        azis = [v.azimuth_deg for v in s.views]
        assert len(set(azis)) == 4


@pytest.mark.parametrize("res", [16, 32, 128, 256])
def test_visibility_rules(scenes, res):
    b = sentinel_size(res, res)
    for s in scenes[:3]:
        for v in range(4):
            ids = cast_view(s, v, res).ids
            assert not ids[:b, :b].any(), "the sentinel block must be background"
        if res == 128:
            counts = np.bincount(cast_view(s, 0, P.visibility_resolution).ids.ravel(), minlength=16)
            assert all(counts[o.instance_id] >= P.min_pixels for o in s.objects)


def test_sentinel_block_lies_in_the_checked_corner():
    """The sampler's background corner (top-left 1/32 x 1/32) holds the whole sentinel
    block at every resolution >= 16: pixel (0, 0)'s centre below 128 px, all b x b
    pixels (b <= R / 32) from 128 px up."""
    for r in range(16, 4097):
        b = sentinel_size(r, r)
        assert (b - 0.5) / r <= _CORNER_FRACTION, r
        if r < 128:
            assert b == 1, r
        else:
            assert b <= r / 32, r


def test_json_round_trip(scenes):
    for s in scenes[:3]:
        d = json.loads(json.dumps(s.to_json(["a.png", "b.png", "c.png", "d.png"])))
        back = SceneSpec.from_json(d)
        assert back == s
        assert back.to_json(["a.png", "b.png", "c.png", "d.png"]) == d
        for key in ("seed", "preset", "split", "index", "objects", "lights", "ground", "views",
                    "render"):  # fmt: skip
            assert key in d
        assert d["camera_convention"] == "opencv" and d["depth"] == "planar_z"


def test_heldout_split_rules():
    p = get_preset("clevr567-heldout")
    held = {("cylinder", "red"), ("sphere", "blue")}
    for i in range(4):
        tr = make_scene(p, "train", i, 0)
        te = make_scene(p, "test", i, 0)
        assert not any((o.shape, o.color) in held for o in tr.objects)
        assert all((o.shape, o.color) in held for o in te.objects)


def test_gray_preset_reuses_clevr567_scenes():
    g = make_scene(get_preset("clevr567-gray"), "test", 2, 0)
    c = make_scene(P, "test", 2, 0)
    assert g.objects == c.objects and g.views == c.views


def test_packed_clevr11_has_eleven_objects():
    s = make_scene(get_preset("packed-clevr11"), "test", 0, 0)
    assert len(s.objects) == 11


def test_projection_matches_raycast_depth(scenes):
    s = scenes[0]
    v = s.views[1]
    res = 32
    cast = cast_view(s, 1, res)
    # ground point hit through pixel (u, v): project it back
    K = v.K(res, res)
    o, d = geometry.pixel_rays(K, v.c2w(), res, res)
    t = -o[:, 2] / d[:, 2]  # ray-plane z = 0, planar depth (dirs have camera z 1)
    ground = cast.ids.ravel() == 0
    assert np.allclose(cast.depth_z.ravel()[ground], t[ground], rtol=1e-5)
    _, z = geometry.project(K, v.c2w(), o[ground][:5] + d[ground][:5] * t[ground][:5, None])
    assert np.allclose(z, t[ground][:5])


def test_all_presets_registered():
    assert {"clevr567", "clevr567-heldout", "packed-clevr11", "clevr567-gray"} <= set(PRESETS)
    with pytest.raises(ValueError, match="unknown preset .*choose from"):
        get_preset("nope")


@pytest.mark.parametrize("name", ["room-chair", "room-diverse"])
def test_room_presets(name):
    p = get_preset(name)
    s = make_scene(p, "train", 1, 0)
    assert p.room.n_chairs[0] <= len(s.objects) <= p.room.n_chairs[1]
    assets = [o.asset_id for o in s.objects]
    if p.room.same_shape:
        assert len(set(assets)) == 1
    else:
        assert len(set(assets)) == len(assets)
    assert all(o.shape == "chair" and o.position[2] == 0.0 for o in s.objects)
    assert 0 <= s.ground.background_id < p.room.n_backgrounds
    assert s.ground.wall_mesh() is not None
    for a, b in itertools.combinations(s.objects, 2):
        d = math.hypot(a.position[0] - b.position[0], a.position[1] - b.position[1])
        assert d - a.bounding_radius_xy - b.bounding_radius_xy >= p.min_gap - 1e-12
    d = json.loads(json.dumps(s.to_json(["a", "b", "c", "d"])))
    assert SceneSpec.from_json(d) == s
    for v in range(4):
        ids = cast_view(s, v, 16).ids
        assert ids[0, 0] == 0
        assert np.isfinite(cast_view(s, v, 16).depth_z).all()  # walls close the room
