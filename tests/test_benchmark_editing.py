"""``benchmark run editing``: registration, a run without generator data, the run options
it shares with the table protocols (``--datasets``, ``--train-minutes``, ``--no-train``) and
its reuse of their trained models, and a Blender smoke run.

The reuse tests need no Blender: their ``--data`` folder holds ray-cast smoke-scale splits
(``generators.testing``, the generator's file contract with flat-shaded images), which the
benchmark takes as generator splits found complete on disk; a segmentation run trains sVORF
for 2 steps there, then editing runs into the same ``--out``.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from benchmark.cli import main
from benchmark.protocols import PROTOCOLS
from benchmark.schema import PROTOCOLS as SCHEMA_PROTOCOLS
from benchmark.schema import validate_report
from generators.blender_backend import bpy_available
from generators.testing import write_raycast_manip_split, write_raycast_split
from scenefmt import MANIP_SPLIT

#: The flags a segmentation run and an editing run share so that they name the same model.
_SHARED = ("--scale", "smoke", "--datasets", "clevr567", "--steps", "2", "--train-minutes", "5",
           "--seed", "0", "--no-progress")  # fmt: skip
_TABLES = ("editing: move one object", "editing: change background")


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


# ------------------------------------------------------------------ reuse of the table models


@pytest.fixture(scope="module")
def segmented(tmp_path_factory) -> tuple[Path, Path, str]:
    """``(data, out, run key)``: ray-cast smoke splits of clevr567 (train 4, test 2, manip
    2 scenes at 32x32, the smoke scale's counts) and an --out where ``benchmark run
    segmentation`` trained sVORF on them."""
    base = tmp_path_factory.mktemp("editing-reuse")
    data = base / "data" / "smoke" / "clevr567"
    write_raycast_split(data / "train", "clevr567", "train", n=4, resolution=32)
    write_raycast_split(data / "test", "clevr567", "test", n=2, resolution=32)
    write_raycast_manip_split(data / MANIP_SPLIT, "clevr567", n=2, resolution=32)
    out = base / "out"
    argv = ["run", "segmentation", *_SHARED, "--out", str(out), "--data", str(base / "data")]
    assert main(argv) == 0
    report = json.loads((out / "segmentation-smoke" / "report.json").read_text())
    (model,) = report["models"]
    assert model["variant"] == "full" and not model["reused"]
    return base / "data", out, model["run_key"]


def _edit(segmented, tmp_path: Path, *extra: str) -> tuple[dict, Path, str]:
    """Run ``benchmark run editing`` into a copy of the segmentation run's --out."""
    data, seg_out, key = segmented
    out = tmp_path / "out"
    shutil.copytree(seg_out, out)
    assert sorted(p.name for p in (out / "runs").iterdir()) == [key]
    argv = ["run", "editing", *_SHARED, "--out", str(out), "--data", str(data), *extra]
    assert main(argv) == 0
    report = json.loads((out / "editing-smoke" / "report.json").read_text())
    validate_report(report)
    return report, out, key


def test_editing_reuses_the_model_segmentation_trained(segmented, tmp_path):
    ckpt = tmp_path / "out" / "runs" / segmented[2] / "checkpoint.pt"
    before = (segmented[1] / "runs" / segmented[2] / "checkpoint.pt").stat().st_size
    report, out, key = _edit(segmented, tmp_path)
    models = {m["variant"]: m for m in report["models"]}
    # sVORF: the segmentation run's model, found by its key and not trained again
    assert models["full"]["run_key"] == key and models["full"]["reused"]
    assert ckpt.stat().st_size == before
    # the ablation is the only model trained, in the only new run folder
    assert not models["density_weighted"]["reused"]
    new = {p.name for p in (out / "runs").iterdir()} - {key}
    assert new == {models["density_weighted"]["run_key"]}
    assert models["full"]["train_budget"]["max_wall_s"] == pytest.approx(300.0)
    measured = [r for r in report["rows"] if r["model"] == "sVORF"]
    assert len(measured) == 2 and all(r["run_key"] == key for r in measured)
    assert all(r["metrics"]["psnr"] is not None for r in measured)
    assert {r["dataset"] for r in report["rows"]} == {"clevr567"}
    assert report["scale_settings"]["only_datasets"] == ["clevr567"]
    assert report["scale_settings"]["train_minutes"] == 5.0
    assert any(n.startswith("Models:") and f"(run {key}): reused" in n for n in report["notes"])
    # what the run generated or found is listed: the training and manipulation splits
    names = {d["name"]: d for d in report["datasets"]}
    assert set(names) == {"clevr567/train", f"clevr567/{MANIP_SPLIT}"}
    assert names[f"clevr567/{MANIP_SPLIT}"]["n_scenes"] == 2


def test_no_train_scores_the_cached_model_and_leaves_the_others_not_trained(
    segmented, tmp_path, capsys
):
    report, out, key = _edit(segmented, tmp_path, "--no-train")
    assert sorted(p.name for p in (out / "runs").iterdir()) == [key]  # nothing trained
    assert report["status"] == "partial"
    assert [m["run_key"] for m in report["models"]] == [key]
    rows = {(r["table"], r["model"]): r for r in report["rows"]}
    for table in _TABLES:
        assert rows[(table, "sVORF")]["metrics"]["psnr"] is not None
        assert rows[(table, "no edit (sVORF)")]["metrics"]["psnr"] is not None
        ablation = rows[(table, "sVORF (density-weighted)")]
        assert all(v is None for v in ablation["metrics"].values())
        assert all(
            v.startswith("not_trained: --no-train") for v in ablation["null_reasons"].values()
        )
        assert "failed" not in ablation
    assert any("not trained in this run" in n and "density-weighted" in n for n in report["notes"])
    assert "report: " in capsys.readouterr().out


@pytest.mark.parametrize(
    "args, needle",
    [
        (("editing", "--datasets", "room-chair"), "has no test dataset 'room-chair'"),
        (("editing", "--datasets", ","), "(none given)"),
        (("editing", "--backend", "ray"), "--backend applies to the table protocols"),
        (("stability", "--no-train"), "--no-train applies to the protocols that train models"),
        (("stability", "--train-only", "full"), "--train-only applies to the protocols that"),
        (
            ("editing", "--train-only", "wo_nvv"),
            "no model variant 'wo_nvv'; did you mean 'wo_nvs'?",
        ),
    ],
)
def test_bad_run_options_are_one_line_errors_before_any_work(tmp_path, capsys, args, needle):
    name, *extra = args
    argv = ["run", name, "--scale", "smoke", "--out", str(tmp_path / "o"),
            "--data", str(tmp_path / "d"), "--no-progress", *extra]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert needle in err and err.count("\n") == 1 and err.startswith("benchmark: error:")
    assert not (tmp_path / "d").exists()
