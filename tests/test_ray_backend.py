"""generate --backend ray: a local Ray cluster (2 CPUs) started by the test writes the
same bytes as the local process pool, resumes, recycles actors, and fails in one line."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

from generators.blender_backend import bpy_available
from generators.ray_backend import RayMissingError, import_ray, init_ray, plan

RES = 32
KW = {"preset": "clevr567", "resolution": RES, "samples": 2, "progress": False}


def _gen(out, n=2, **kw):
    from generators.pipeline import GenerateConfig, generate_dataset

    return generate_dataset(GenerateConfig(n=n, out=out, **{**KW, **kw}))


@pytest.mark.blender
@pytest.mark.timeout(600)  # Blender + Ray start-up: slow on a loaded 2-core machine
@pytest.mark.skipif(not bpy_available(), reason="bpy not installed")
def test_ray_backend_matches_local_run_resumes_and_recycles(ray_cluster, tmp_path):
    from generators.verify import verify_split
    from scenefmt import SplitLayout, read_depth_exr

    local = tmp_path / "local"
    _gen(local, workers=1)
    # 3 scenes on 2 one-thread actors that retire after each scene: 2 actors + 1 fresh.
    rayd = tmp_path / "ray"
    s = _gen(rayd, n=3, backend="ray", workers=2, threads=1, recycle_after=1)
    assert (s.scenes_this_run, s.workers, s.threads, s.complete) == (3, 2, 1, True)
    assert s.views_rendered == 12 and s.render_s > 0
    assert verify_split(rayd) == []
    a, b = SplitLayout(local), SplitLayout(rayd)
    for sc in range(2):  # scene i does not depend on n
        assert a.scene_json(sc).read_bytes() == b.scene_json(sc).read_bytes()
        for v in range(4):
            for pa, pb in zip(a.view_files(sc, v), b.view_files(sc, v), strict=True):
                if pa.suffix == ".exr":  # OIIO stamps a DateTime into the EXR header
                    assert np.array_equal(read_depth_exr(pa), read_depth_exr(pb)), pa.name
                else:  # masks, ids, RGB, cameras
                    assert pa.read_bytes() == pb.read_bytes(), pa.name

    # Resume: complete scenes are skipped and not touched; a missing one is re-rendered.
    before = {p: p.stat().st_mtime_ns for p in b.scene_files(0)}
    b.scene_json(2).unlink()
    s2 = _gen(rayd, n=3, backend="ray", workers=2, threads=1)
    assert (s2.scenes_skipped, s2.scenes_this_run, s2.workers) == (2, 1, 1)
    assert {p: p.stat().st_mtime_ns for p in b.scene_files(0)} == before
    assert verify_split(rayd) == [] and not list(rayd.rglob(".*.tmp*"))


def test_ray_plan_defaults_and_errors():
    assert plan(None, None, 2, 10) == plan(1, 2, 2, 10)  # one 2-thread actor on 2 CPUs
    assert plan(None, None, 16, 10).workers == 8
    assert plan(None, None, 16, 3).workers == 3  # never more actors than scenes
    assert plan(None, 1, 2, 10).workers == 2
    with pytest.raises(ValueError, match="--workers 4 x --threads 2 = 8 CPUs.*has 2"):
        plan(4, 2, 2, 10)


def test_ray_cli_bad_input_is_one_line(tmp_path, capsys, monkeypatch):
    from generators.cli import main

    out = str(tmp_path / "x")
    assert main(["--preset", "clevr567", "--n", "1", "--out", out, "--address", "auto"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "generate: error: --address is a Ray cluster address; pass it with --backend ray"
    with pytest.raises(SystemExit) as e:  # argparse choices: generate's parser exits 2
        main(["--preset", "clevr567", "--n", "1", "--out", out, "--backend", "dask"])
    assert e.value.code == 2
    assert "--backend" in capsys.readouterr().err

    # ray not installed (import fails): the install hint, nothing written.
    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(RayMissingError):
        import_ray()
    argv = ["--preset", "clevr567", "--n", "1", "--out", out, "--backend", "ray", "--no-progress"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "pip install 'svorf-toolkit[ray]'" in err, err
    assert not (tmp_path / "x").exists()


def test_init_ray_starts_workers_at_normal_priority_unless_told(monkeypatch):
    """A local Ray instance started by the CLIs gets RAY_worker_niceness=0 (Ray's default
    15 starves its trainings beside other work); a value the user set is kept."""
    calls = []

    class FakeRay:
        @staticmethod
        def init(**kw):
            calls.append((kw, os.environ.get("RAY_worker_niceness")))

    monkeypatch.delenv("RAY_worker_niceness", raising=False)
    init_ray(FakeRay, None)
    assert calls[-1] == (
        {"address": None, "include_dashboard": False, "log_to_driver": False},
        "0",
    )
    monkeypatch.setenv("RAY_worker_niceness", "10")
    init_ray(FakeRay, "auto")
    assert calls[-1][0]["address"] == "auto" and calls[-1][1] == "10"
