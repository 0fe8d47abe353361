"""Occlusion from the scene JSONs (benchmark/tools/occlusion.py): the visible pixels equal the
ray cast's instance ids, hidden fractions and occluders are right on a hand-built pair,
and ``recipe diagnose --occlusion`` breaks the failures down by them."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from benchmark.tools.occlusion import SplitOcclusion, summarize_occlusion, view_occlusion
from generators import geometry
from generators.raycast import cast_view
from generators.spec import SceneSpec
from generators.testing import write_raycast_split
from scenefmt import SplitLayout, read_json


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return write_raycast_split(tmp_path_factory.mktemp("occ") / "test", n=3, resolution=32)


def _camera(res: int):
    c2w = geometry.look_at_cam_to_world(np.array([8.0, 0, 0.5]), np.array([0, 0, 0.5]))
    return geometry.intrinsics(35.0, 32.0, res, res), c2w


def test_a_box_behind_another_is_hidden_by_it_and_not_the_other_way():
    front = geometry.box_mesh((1.0, -0.5, 0.0), (1.5, 0.5, 1.0))
    back = geometry.box_mesh((-1.0, -1.0, 0.0), (-0.5, 1.0, 1.0))  # wider: its sides show
    side = geometry.box_mesh((0.0, 3.0, 0.0), (0.5, 3.5, 1.0))  # off to the side
    K, c2w = _camera(32)
    occ = view_occlusion([front, back, side], [1, 2, 3], K, c2w, 32)
    assert occ[1]["hidden"] == 0.0 and occ[1]["occluders"] == []
    assert 0.5 < occ[2]["hidden"] < 1.0 and occ[2]["occluders"] == [1]
    assert occ[2]["visible"] < occ[2]["silhouette"] and occ[2]["visible"] > 0
    assert occ[3] == {**occ[3], "hidden": 0.0, "occluders": []} and occ[3]["visible"] > 0
    far = geometry.box_mesh((0.0, 50.0, 0.0), (0.5, 50.5, 1.0))  # outside the view
    assert view_occlusion([far], [7], K, c2w, 32)[7] == {
        "silhouette": 0, "visible": 0, "hidden": 0.0, "occluders": []
    }  # fmt: skip


def test_visible_pixels_equal_the_ray_cast_ids_of_every_view(split):
    layout = SplitLayout(split)
    for scene in range(3):
        spec = SceneSpec.from_json(read_json(layout.scene_json(scene)))
        for view in (0, 3):
            occ = SplitOcclusion(split, 24)(scene, view)
            ids = cast_view(spec, view, 24).ids
            assert sorted(occ) == sorted(o.instance_id for o in spec.objects)
            for oid, o in occ.items():
                assert o["visible"] == int((ids == oid).sum())
                assert o["silhouette"] >= o["visible"] and 0 <= o["hidden"] <= 1
                assert (o["hidden"] > 0) == bool(o["occluders"])


def test_summary_counts_kinds_per_bin_and_merges_into_an_occluder():
    rows = [
        {"kind": "own", "hidden": 0.0, "occluders": []},
        {"kind": "lost", "hidden": 0.02, "occluders": [3]},
        {"kind": "merged", "hidden": 0.3, "occluders": [5], "merged_with": [5]},
        {"kind": "merged", "hidden": 0.3, "occluders": [5], "merged_with": [6]},
        {"kind": "own", "hidden": 0.7, "occluders": [2]},
        {"kind": "merged", "hidden": 1.0, "occluders": [2], "merged_with": [2, 4]},
    ]
    s = summarize_occlusion(rows)
    assert s["bins"] == {"visible": [0.0, 0.05], "partly": [0.05, 0.5], "mostly": [0.5, 1.0]}
    assert s["visible"] == {
        "objects": 2, "lost": 0.5, "merged": 0.0, "own": 0.5, "merged_into_occluder": 0.0
    }  # fmt: skip
    assert s["partly"]["merged"] == 1.0 and s["partly"]["merged_into_occluder"] == 0.5
    assert s["mostly"]["objects"] == 2 and s["mostly"]["merged_into_occluder"] == 0.5
    assert math.isnan(summarize_occlusion([])["partly"]["own"])


def test_diagnose_breaks_failures_down_by_occlusion(split, tmp_path, capsys):
    from benchmark.tools.recipe import main, train_eval
    from svorf.config import model_config
    from svorf.train import train_config

    mcfg = model_config("smoke", num_slots=4)
    tcfg = train_config("smoke", steps=10_000, eval_every=0, ckpt_every=100)
    train_eval(split, split, tmp_path / "r", 0.0, mcfg, tcfg, grid_scenes=1)
    argv = ["diagnose", str(tmp_path / "r"), "--test", str(split), "--threads", "1"]
    assert main([*argv, "--occlusion"]) == 0
    out = json.loads(capsys.readouterr().out)
    occ = out["occlusion"]
    assert sum(occ[b]["objects"] for b in ("visible", "partly", "mostly")) == out["objects"]
    for b in ("visible", "partly", "mostly"):
        if occ[b]["objects"]:
            assert math.isclose(sum(occ[b][k] for k in ("lost", "merged", "own")), 1.0)
    assert main(argv) == 0 and "occlusion" not in json.loads(capsys.readouterr().out)
