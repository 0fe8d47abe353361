"""``benchmark run editing``: registration, a run without generator data, a smoke run."""

from __future__ import annotations

import json

import pytest

from benchmark.cli import main
from benchmark.protocols import PROTOCOLS
from benchmark.schema import PROTOCOLS as SCHEMA_PROTOCOLS
from benchmark.schema import validate_report
from generators.blender_backend import bpy_available


def test_editing_is_registered():
    assert "editing" in PROTOCOLS and "editing" in SCHEMA_PROTOCOLS


def test_without_generator_data_rows_are_null_with_a_reason(tmp_path):
    argv = ["run", "editing", "--scale", "smoke", "--out", str(tmp_path / "o"),
            "--data", str(tmp_path / "d"), "--data-source", "synthetic", "--no-progress"]  # fmt: skip
    assert main(argv) == 0
    report = json.loads((tmp_path / "o" / "editing-smoke" / "report.json").read_text())
    validate_report(report)
    assert report["status"] == "partial"
    assert all(v is None for r in report["rows"] for v in r["metrics"].values())
    assert all("generator" in r["null_reasons"]["psnr"] for r in report["rows"])


@pytest.mark.blender
@pytest.mark.slow
@pytest.mark.skipif(not bpy_available(), reason="bpy not installed")
def test_smoke_run_end_to_end(tmp_path, capsys):
    from benchmark.leaderboard import merge_reports

    out = tmp_path / "o"
    argv = ["run", "editing", "--scale", "smoke", "--out", str(out), "--data", str(tmp_path / "d"),
            "--no-progress"]  # fmt: skip
    assert main(argv) == 0
    rdir = out / "editing-smoke"
    report = json.loads((rdir / "report.json").read_text())
    validate_report(report)
    assert report["status"] == "complete"
    rows = report["rows"]
    models = {(r["table"], r["model"], r["source"]) for r in rows}
    for table in ("editing: move one object", "editing: change background"):
        for name in ("sVORF", "sVORF (density-weighted)"):
            assert (table, name, "measured") in models
            assert (table, f"no edit ({name})", "baseline") in models
    for r in rows:
        assert r["n_scenes"] == 2
        assert r["metrics"]["psnr"] is not None and r["metrics"]["ari"] is not None
        if r["source"] == "measured":
            assert set(r["beats_no_edit"]) == {"psnr", "ssim", "lpips", "ari", "fg_ari"}
    assert len(report["figures"]) == 4 and all((rdir / f).is_file() for f in report["figures"])
    assert any("no-edit floor" in n for n in report["notes"])
    board = merge_reports(out)
    assert sum(e["protocol"] == "editing" for e in board["entries"]) == len(rows)
    # A rerun reuses the models and the cached evaluations.
    capsys.readouterr()
    assert main(argv) == 0
    again = json.loads((rdir / "report.json").read_text())
    assert [r["metrics"] for r in again["rows"]] == [r["metrics"] for r in rows]
