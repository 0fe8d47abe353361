"""Tests of ``benchmark run NAME --rows-from REPORT``: a table built from rows measured by
an earlier run elsewhere (another ``--out``, another machine), taken only where they are
the numbers this run would compute.

Tiny ``smoke``-scale synthetic data, 2 training steps; about 20 s in all.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmark import adapter
from benchmark.cli import main as cli_main
from benchmark.schema import validate_report


def _run(tmp: Path, out: str, protocol: str, *extra: str) -> int:
    return cli_main(
        [
            "run",
            protocol,
            "--scale",
            "smoke",
            "--out",
            str(tmp / out),
            "--data",
            str(tmp / "data"),
            "--data-source",
            "synthetic",
            "--no-progress",
            "--datasets",
            "clevr567",
            "--steps",
            "2",
            *extra,
        ]
    )


def _report(tmp: Path, out: str, protocol: str) -> dict:
    report = json.loads((tmp / out / f"{protocol}-smoke" / "report.json").read_text())
    validate_report(report)
    return report


def _measured(report: dict) -> dict[str, dict]:
    return {r["model"]: r for r in report["rows"] if r["source"] == "measured"}


@pytest.fixture
def first(tmp_path):
    """A segmentation report measured in ``tmp_path/first`` (the earlier machine)."""
    assert _run(tmp_path, "first", "segmentation") == 0
    return _report(tmp_path, "first", "segmentation")


def _no_training(monkeypatch):
    def refuse(*a, **k):
        raise AssertionError("a row taken from an earlier report must not train its model")

    monkeypatch.setattr(adapter, "train", refuse)


def test_a_row_is_taken_from_an_earlier_report_with_its_provenance(tmp_path, first, monkeypatch):
    assert isinstance(first["row_context"], str)
    src = tmp_path / "first" / "segmentation-smoke"
    _no_training(monkeypatch)
    # Another --out: no cached model, no cached evaluation, no stored row.
    assert _run(tmp_path, "second", "segmentation", "--rows-from", str(src)) == 0
    report = _report(tmp_path, "second", "segmentation")
    row, was = _measured(report)["sVORF"], _measured(first)["sVORF"]
    assert row["metrics"] == was["metrics"] and row["run_key"] == was["run_key"]
    assert row["imported_from"] == {
        "report": str(src / "report.json"),
        "created_utc": first["created_utc"],
        "commit": first["git"]["commit"],
    }
    (model,) = report["models"]
    assert model["run_key"] == was["run_key"] and model["imported_from"]["report"].endswith(
        "report.json"
    )
    assert model["steps_done"] == 2
    assert any("taken from earlier reports (--rows-from" in n for n in report["notes"])
    assert report["verdicts"] and report["verdicts"][0]["model"] == "sVORF"
    page = (tmp_path / "second" / "segmentation-smoke" / "index.html").read_text()
    # the row's notes, the models table and the report's notes name the source
    assert page.count(f"from {src / 'report.json'}") == 3
    assert f"taken from {src / 'report.json'}" in page
    # A rerun with the same --out keeps the taken row without --rows-from.
    assert _run(tmp_path, "second", "segmentation") == 0
    again = _measured(_report(tmp_path, "second", "segmentation"))["sVORF"]
    assert again["metrics"] == was["metrics"] and again["imported_from"] == row["imported_from"]


def test_another_tables_row_of_the_same_model_and_test_data_serves(tmp_path, first, monkeypatch):
    # The ablation's full model is the segmentation table's model: one evaluation
    # computes every metric, so its row comes from the segmentation report.
    _no_training(monkeypatch)
    src = str(tmp_path / "first" / "segmentation-smoke" / "report.json")
    assert _run(tmp_path, "second", "ablation", "--no-train", "--rows-from", src) == 0
    rows = _measured(_report(tmp_path, "second", "ablation"))
    full = rows["sVORF (ours)"]
    seg = _measured(first)["sVORF"]
    assert full["imported_from"]["report"] == src
    assert all(full["metrics"][m] == seg["metrics"][m] for m in full["metrics"])
    # The other variants were trained nowhere: not taken, not trained.
    others = [r for name, r in rows.items() if name != "sVORF (ours)"]
    assert others and all(r["n_scenes"] == 0 and "imported_from" not in r for r in others)


def test_a_report_of_other_settings_gives_no_rows_and_says_why(tmp_path, first, monkeypatch):
    _no_training(monkeypatch)
    src = str(tmp_path / "first" / "segmentation-smoke")
    assert (
        _run(tmp_path, "second", "segmentation", "--seed", "1", "--no-train", "--rows-from", src)
        == 0
    )
    report = _report(tmp_path, "second", "segmentation")
    row = _measured(report)["sVORF"]
    assert row["n_scenes"] == 0 and "imported_from" not in row
    (note,) = [n for n in report["notes"] if n.startswith("--rows-from:")]
    assert "none of its rows taken" in note and "row context" in note
    assert "that report is of seeds {'data': 0" in note  # the difference, named


def test_a_report_without_row_context_gives_no_rows(tmp_path, first, monkeypatch):
    old = dict(first)
    del old["row_context"]
    path = tmp_path / "old.json"
    path.write_text(json.dumps(old))
    _no_training(monkeypatch)
    assert _run(tmp_path, "second", "segmentation", "--no-train", "--rows-from", str(path)) == 0
    report = _report(tmp_path, "second", "segmentation")
    assert _measured(report)["sVORF"]["n_scenes"] == 0
    assert any("written before reports recorded their row context" in n for n in report["notes"])


@pytest.mark.parametrize(
    "content, needle",
    [
        (None, "no such file"),
        ("{not json", "not a readable JSON report"),
        ('{"kind": "something else"}', "not a benchmark report"),
    ],
)
def test_a_bad_rows_from_file_is_a_one_line_error_before_any_work(
    tmp_path, capsys, content, needle
):
    path = tmp_path / "r.json"
    if content is not None:
        path.write_text(content)
    assert _run(tmp_path, "second", "segmentation", "--rows-from", str(path)) == 2
    err = capsys.readouterr().err
    assert needle in err and err.count("\n") == 1 and err.startswith("benchmark: error:")
    assert not (tmp_path / "data").exists()


def test_rows_from_is_refused_for_protocols_without_tables(tmp_path, capsys):
    assert cli_main(["run", "stability", "--out", str(tmp_path), "--rows-from", str(tmp_path)]) == 2
    assert "applies to the table protocols" in capsys.readouterr().err


def _report_with(rows: list[dict], context: str = "ctx", path_models: tuple = ()) -> dict:
    return {
        "kind": "svorf-benchmark-report",
        "row_context": context,
        "created_utc": "2026-11-26T00:00:00Z",
        "git": {"commit": None},
        "rows": rows,
        "models": [{"run_key": k, "steps_done": s} for k, s in path_models],
    }


def _mrow(table: str, metrics: dict, key: str = "k1", fp: str = "fp1") -> dict:
    return {
        "source": "measured",
        "table": table,
        "n_scenes": 50,
        "run_key": key,
        "test_fingerprint": fp,
        "train_dataset": "clevr567/train",
        "metrics": metrics,
        "null_reasons": {m: "lpips_unavailable" for m, v in metrics.items() if v is None},
    }


def test_imported_scores_merge_within_a_report_and_the_first_report_wins():
    from benchmark.datasets import DatasetInfo
    from benchmark.jobs import ModelJob
    from benchmark.row_import import ImportedRows
    from benchmark.rows import MeasuredRow

    test = DatasetInfo(
        "clevr567/test", "clevr567", "test", Path("x"), "fp1", 50, 4, 64, "generator", False, 0.0
    )
    job = ModelJob("full", "clevr567")
    control = {"ari_shuffled": 5.0, "fg_ari_shuffled": 15.0, "fg_ari_gain": 70.0}
    seg = _mrow("tab:seg", {"ari": 70.0, "fg_ari": 85.0, "nv_ari": 68.0, **control})
    nvs = _mrow("tab:nvs", {"psnr": 30.0, "ssim": 0.9, "lpips": None})
    later = _mrow("tab:seg", {"ari": 1.0, "fg_ari": 1.0, "nv_ari": 1.0, "psnr": 1.0, **control})
    other = _report_with([seg], context="another")
    imported = ImportedRows(
        [
            ("other.json", other),
            ("a.json", _report_with([seg, nvs], path_models=(("k1", 100),))),
            ("b.json", _report_with([later], path_models=(("k1", 7),))),
        ],
        "ctx",
    )
    (refused,) = imported.refused
    assert refused.startswith("other.json: none of its rows taken (row context another")
    assert imported.models["k1"]["steps_done"] == 100  # the first report's model
    # One row that needs columns of both of a.json's rows (b.json's scores never mix in).
    spec = MeasuredRow("tab:nvs", "sVORF", "clevr567", job, ("psnr", "lpips", "fg_ari"))
    row = imported.row(spec, "k1", test)
    assert row["metrics"]["psnr"] == 30.0 and row["metrics"]["fg_ari"] == 85.0
    assert row["metrics"]["fg_ari_shuffled"] == 15.0  # the control comes with FG-ARI
    assert row["metrics"]["lpips"] is None and row["null_reasons"]["lpips"] == "lpips_unavailable"
    assert row["imported_from"]["report"] == "a.json"
    # A column no report scored, another model key or other test data: nothing taken.
    assert (
        imported.row(MeasuredRow("tab:nvs", "sVORF", "clevr567", job, ("depth",)), "k1", test)
        is None
    )
    assert imported.row(spec, "k2", test) is None


def test_a_refusal_names_lpips_availability_when_that_is_the_difference():
    from benchmark.report import stable_hash
    from benchmark.row_import import ImportedRows

    here = {"scale": "cpu", "seeds": {"data": 0, "train": 0, "eval": 0}, "lpips": False}
    for lpips_there, says in ((True, "run `benchmark lpips-weights`"), (False, "has them")):
        ctx = {**here, "lpips": not lpips_there}
        there = _report_with([], context=stable_hash({**ctx, "lpips": lpips_there}))
        (refused,) = ImportedRows([("r.json", there)], stable_hash(ctx), ctx).refused
        assert says in refused
    other = _report_with([], context=stable_hash({**here, "scale": "paper"}))
    (refused,) = ImportedRows([("r.json", other)], stable_hash(here), here).refused
    assert "other scale settings" in refused  # not one of the differences it can name


def test_step_rate_note_names_the_slowest_and_fastest_models_only_past_the_spread():
    from benchmark.row_import import step_rate_note

    here = {"variant": "full", "train_dataset": "clevr567", "steps_done": 36000}
    there = {
        "variant": "wo_cr",
        "train_dataset": "clevr567",
        "steps_done": 18000,
        "imported_from": {"report": "results/cpu/ablation-60min/report.json"},
    }
    note = step_rate_note([{**here, "train_wall_s": 3600.0}, {**there, "train_wall_s": 3600.0}])
    assert note is not None and "differ by 2.0x" in note
    assert "300 steps per minute (wo_cr on clevr567, from results/cpu/ablation-60min" in note
    assert "to 600 (full on clevr567, trained into this --out)" in note
    # Within the spread, or fewer than two known rates: no note.
    close = {**there, "steps_done": 32000, "train_wall_s": 3600.0}
    assert step_rate_note([{**here, "train_wall_s": 3600.0}, close]) is None
    unknown = {**there, "steps_done": None, "train_wall_s": 3600.0}
    assert step_rate_note([{**here, "train_wall_s": 3600.0}, unknown]) is None
    assert step_rate_note([{**here, "train_wall_s": 0.0}, {**there, "train_wall_s": 60.0}]) is None


def test_recipe_rate_note_flags_a_full_recipe_model_trained_on_a_slow_machine():
    from benchmark.row_import import RECIPE_STEPS_PER_MINUTE, recipe_rate_note

    lo = RECIPE_STEPS_PER_MINUTE[0]
    slow = {
        "variant": "full",
        "train_dataset": "clevr567/train",
        "config_source": "svorf.train.run_configs (cpu recipe)",
        "train_budget": {"minutes": 60.0},
        "steps_done": 18751,
        "train_wall_s": 3600.0,
    }
    note = recipe_rate_note([slow])
    assert note is not None and "clevr567/train at 313 steps per minute" in note
    assert f"60 minutes there are about {60 * lo / 312.5:.0f} here" in note
    # At the measured rates, another variant, no recipe, or no wall-clock budget: no note.
    assert recipe_rate_note([{**slow, "steps_done": int(0.9 * lo * 60)}]) is None
    assert recipe_rate_note([{**slow, "variant": "slot_mixer"}]) is None
    assert recipe_rate_note([{**slow, "config_source": "svorf.train.run_configs"}]) is None
    assert recipe_rate_note([{**slow, "train_budget": {"minutes": None}}]) is None
    assert recipe_rate_note([{**slow, "train_budget": None}]) is None
