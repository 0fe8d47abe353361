"""benchmark.scaling: 1 vs 2 generation workers give the same bytes; training rows and the
figure come out of real runs (tiny sizes)."""

from __future__ import annotations

import json

import pytest

from benchmark import scaling
from generators.blender_backend import bpy_available


# generate runs in subprocesses: bpy must not be imported into the test process here
# (a second, lazy import by the Blender backend later in the session would fail).
@pytest.mark.skipif(not bpy_available(), reason="bpy not installed")
@pytest.mark.timeout(600)
def test_generation_rows_are_real_runs_with_identical_bytes(tmp_path):
    rows = scaling.measure_generation(tmp_path, [1, 2], scenes=2, resolution=32, samples=1)
    assert [r["workers"] for r in rows] == [1, 2]
    assert all(r["same_bytes_as_first"] for r in rows)
    assert rows[0]["speedup"] == 1.0 and rows[1]["speedup"] > 0
    assert all(r["wall_s"] > 0 and r["s_per_view"] == pytest.approx(r["wall_s"] / 8, abs=1e-3)
               for r in rows)  # fmt: skip
    assert (tmp_path / "gen_local_2" / "manifest.json").is_file()


@pytest.mark.timeout(600)
def test_training_rows_and_the_report(tmp_path, monkeypatch):
    rows = scaling.measure_training(tmp_path / "w", [1], scale="smoke", steps=2, image=16)
    assert rows[0]["s_per_step"] > 0 and rows[0]["speedup"] == 1.0
    assert rows[0]["final_loss"] is not None
    monkeypatch.setattr(scaling, "measure_generation", lambda *a, **k: [])
    monkeypatch.setattr(scaling, "measure_training", lambda *a, **k: rows)
    out = tmp_path / "rep"
    assert scaling.main(["--out", str(out), "--workers", "1"]) == 0
    rep = json.loads((out / "scaling.json").read_text())
    assert rep["rows"] == rows and rep["machine"]["cpu_count"] >= 1
    assert (out / "scaling.png").stat().st_size > 1000
    with pytest.raises(SystemExit, match="--workers"):
        scaling.main(["--out", str(out), "--workers", "1,x"])
