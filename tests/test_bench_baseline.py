"""benchmark.tools.bench_baseline: generate vs the straightforward bpy script, at a tiny size.

Every bpy render runs in a subprocess (``compare`` is only the driver): bpy must not be
imported into the test process, or the Blender backend's lazy import later in the
session fails.
"""

from __future__ import annotations

import math

import pytest

from benchmark.tools import bench_baseline
from generators.blender_backend import bpy_available
from generators.spec import RenderSettings


@pytest.mark.blender
@pytest.mark.skipif(not bpy_available(), reason="bpy not installed")
@pytest.mark.timeout(120)
def test_compare_tiny_side_by_side(tmp_path):
    r = bench_baseline.compare(
        "clevr567", 2, 32, 16, None, None, tmp_path, 2, samples=2, generate_samples=1
    )
    gen, naive = tmp_path / "generate", tmp_path / "naive"
    names = sorted(p.relative_to(gen).as_posix() for p in gen.rglob("*") if p.is_file())
    assert {"manifest.json", "sc0000.json", "sc0001.json"} <= set(names)
    assert len([n for n in names if n.startswith("depth/")]) == 8
    assert names == sorted(p.relative_to(naive).as_posix() for p in naive.rglob("*") if p.is_file())
    assert r["same_files"] and r["masks_identical"] and r["depth_identical"]
    # the baseline: a factory reset per scene, Blender's default light paths
    assert r["naive"]["factory_resets"] == 2
    lp = r["settings"]["naive"]["light_path"]
    dn = r["settings"]["naive"]["denoiser"]
    assert {**lp, **dn} == r["settings"]["naive"]["rna_defaults"]
    # the straightforward script only switches OIDN on: Blender's prefilter and quality
    assert r["settings"]["naive"]["baseline_denoiser"] == "factory"
    assert (dn["denoising_prefilter"], dn["denoising_quality"]) == ("ACCURATE", "HIGH")
    assert r["settings"]["naive"]["render"]["denoise_prefilter"] == "ACCURATE"
    d = RenderSettings()
    assert d.denoise_prefilter != "ACCURATE"  # generate's own setting
    shipped = (d.max_bounces, d.glossy_bounces, d.transmission_bounces, d.transparent_bounces,
               d.caustics)  # fmt: skip
    naive_lp = (lp["max_bounces"], lp["glossy_bounces"], lp["transmission_bounces"],
                lp["transparent_max_bounces"], lp["caustics_reflective"])  # fmt: skip
    assert naive_lp != shipped
    assert r["settings"]["generate"]["render"]["max_bounces"] == d.max_bounces
    assert r["settings"]["generate"]["render"]["samples"] == 1  # the equal-PSNR knob
    assert r["settings"]["naive"]["render"]["samples"] == 2 and lp["use_adaptive_sampling"]
    for side in ("generate", "naive"):
        assert math.isfinite(r[side]["psnr_db"]) and r[side]["psnr_db"] > 0
        assert len(r[side]["psnr_db_per_view"]) == 8
        assert r[side]["s_per_view"] == pytest.approx(r[side]["wall_s"] / 8, rel=1e-2)
    assert r["speedup"] == pytest.approx(r["naive"]["wall_s"] / r["generate"]["wall_s"], rel=1e-2)
    assert len(r["load_before"]) == 3 and r["machine"]["cores"] >= 1


@pytest.mark.blender
@pytest.mark.skipif(not bpy_available(), reason="bpy not installed")
@pytest.mark.timeout(120)
def test_tuned_baseline_borrows_generates_denoiser(tmp_path):
    r = bench_baseline.compare(
        "clevr567", 1, 32, 4, None, None, tmp_path, 1, samples=1, baseline_denoiser="tuned"
    )
    d = RenderSettings()
    naive = r["settings"]["naive"]
    assert naive["baseline_denoiser"] == "tuned"
    assert naive["denoiser"]["denoising_prefilter"] == d.denoise_prefilter
    assert naive["denoiser"]["denoising_quality"] == d.denoise_quality
    assert set(naive["rna_defaults"]) == set(naive["light_path"])  # only light paths kept
    assert r["masks_identical"] and r["depth_identical"]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"n_scenes": 0}, "n_scenes"), ({"psnr_scenes": 3, "n_scenes": 2}, "psnr_scenes"),
     ({"ref_samples": 0}, "ref_samples"), ({"threads": 0}, "threads"),
     ({"generate_samples": 0}, "generate_samples"),
     ({"baseline_denoiser": "nope"}, "baseline_denoiser"),
     ({"resolution": 8}, "resolution"), ({"preset_name": "nope"}, "preset")],
)  # fmt: skip
def test_bad_arguments_raise_before_anything_runs(tmp_path, kwargs, match):
    with pytest.raises(ValueError, match=match):
        bench_baseline.compare(**{"out_root": tmp_path, **kwargs})
    assert list(tmp_path.iterdir()) == []


def test_cli_bad_input_is_one_line(capsys):
    assert bench_baseline.main(["--n", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("bench_baseline: error:") and "n_scenes" in err and "\n" not in err
