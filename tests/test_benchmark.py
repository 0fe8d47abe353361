"""Tests of the benchmark package: schema, paper numbers, leaderboard, protocols, HTML.

Fast tier: schema/paper/leaderboard units, baselines, a tiny end-to-end table
protocol on ``svorf.synthetic`` data with resume, the stability protocol, and the
HTML page rendered in headless Chromium (skipped only if Chromium is absent).
Slow tier (``-m slow``): the speed protocol, and the full ``smoke`` ablation and
generalization protocols on the generator's presets.
"""

from __future__ import annotations

import copy
import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmark import adapter
from benchmark.cli import main as cli_main
from benchmark.html import chromium_binary, render_screenshot, write_index
from benchmark.leaderboard import format_leaderboard, merge_reports
from benchmark.paper_numbers import PAPER_TABLES, paper_rows
from benchmark.protocols.tables import PACKED_CONTROL
from benchmark.report import RowStore, new_report, write_report
from benchmark.runner import Context, MeasuredRow, ModelJob, run_table_protocol
from benchmark.schema import SchemaError, check_report, validate_report

TEX = Path("/work/shared/paper/svorf_neurips2023.tex")


# ---------------------------------------------------------------------- helpers


def _good_report(protocol: str = "ablation", created: str = "2025-01-01T00:00:00Z") -> dict:
    rep = new_report(protocol, "smoke", "cpu")
    rep["created_utc"] = created
    rep["rows"] = paper_rows("tab:ablation") + [
        {
            "id": "tab:ablation|sVORF (ours)|clevr567|measured",
            "table": "tab:ablation",
            "model": "sVORF (ours)",
            "dataset": "clevr567",
            "variant": "full",
            "source": "measured",
            "metrics": {"nv_ari": 12.5, "fg_ari": None},
            "null_reasons": {"fg_ari": "no_finite_value"},
            "n_scenes": 2,
        },
        {
            "id": "tab:ablation|chance|clevr567|baseline",
            "table": "tab:ablation",
            "model": "chance",
            "dataset": "clevr567",
            "source": "baseline",
            "metrics": {"nv_ari": 0.0, "fg_ari": 0.0},
            "null_reasons": {},
            "n_scenes": 2,
        },
    ]
    rep["datasets"] = [
        {
            "name": "clevr567/test",
            "preset": "clevr567",
            "split": "test",
            "path": "/x",
            "fingerprint": "ab" * 32,
            "n_scenes": 2,
            "n_views": 4,
            "resolution": 32,
            "source": "synthetic",
        }
    ]
    return rep


@pytest.fixture(scope="module")
def e2e(tmp_path_factory):
    """A tiny table protocol (2 ablation rows) on synthetic data, run once for several tests."""
    out = tmp_path_factory.mktemp("bench")
    ctx = _ctx(out)
    path = run_table_protocol(ctx, ["tab:ablation"], _tiny_rows(), _tiny_figures)
    return out, path, ctx


def _ctx(out: Path) -> Context:
    return Context(
        "ablation",
        "smoke",
        out / "reports",
        out / "data",
        data_source="synthetic",
        progress=False,
        train_steps=2,
    )


def _tiny_rows() -> list[MeasuredRow]:
    m = ("nv_ari", "fg_ari", "ari", "psnr")
    return [
        MeasuredRow("tab:ablation", "sVORF (ours)", "clevr567", ModelJob("full", "clevr567"), m),
        MeasuredRow("tab:ablation", "sVORF (w/o SA)", "clevr567", ModelJob("wo_sa", "clevr567"), m),
    ]


def _tiny_figures(ctx, rows, state):
    from benchmark.protocols.tables import _bars, _qualitative

    return [
        _bars(ctx, rows, ["tab:ablation"], ["nv_ari", "fg_ari"], "bars.png", "tiny")
    ] + _qualitative(ctx, state, [(ModelJob("full", "clevr567"), "clevr567", "full")])


# ---------------------------------------------------------------------- schema


def test_schema_accepts_a_good_report():
    validate_report(_good_report())


@pytest.mark.parametrize(
    "breakage, needle",
    [
        (lambda r: r.pop("hardware"), "report.hardware: missing"),
        (lambda r: r["rows"][0].pop("metrics"), "metrics: missing"),
        (lambda r: r["rows"][-1].update(source="guessed"), "source: expected one of"),
        (lambda r: r["rows"][-2]["metrics"].update(nv_ari=float("nan")), "nan is not allowed"),
        (lambda r: r["rows"][-2]["metrics"].update(nv_ari=float("inf")), "inf is not allowed"),
        (lambda r: r["rows"][-2]["null_reasons"].clear(), "null without a reason"),
        (
            lambda r: r["rows"][0]["metrics"].update(nv_ari=99.0),
            "differ from benchmark.paper_numbers",
        ),
        (lambda r: r["rows"][-2].pop("n_scenes"), "n_scenes"),
        (lambda r: r["rows"][-2].update(n_scenes=0), "is 0 but some metrics are not null"),
        (lambda r: r["rows"][-2]["metrics"].update(made_up=1.0), "unknown metric"),
        (lambda r: r.update(scale="huge"), "report.scale"),
        (lambda r: r.update(schema_version="0.1"), "schema_version"),
        (lambda r: r["datasets"][0].update(fingerprint="xyz"), "fingerprint"),
        (lambda r: r["rows"].append(copy.deepcopy(r["rows"][-1])), "duplicate"),
        (lambda r: r["wall_time_s"].update(total=-1.0), "wall_time_s.total"),
        (lambda r: r["hardware"].update(cpu_cores=True), "cpu_cores"),
    ],
)
def test_schema_rejects_bad_reports(breakage, needle):
    rep = _good_report()
    breakage(rep)
    problems = check_report(rep)
    assert any(needle in p for p in problems), problems
    with pytest.raises(SchemaError):
        validate_report(rep)


def test_write_report_refuses_invalid_and_writes_nothing(tmp_path):
    rep = _good_report()
    rep["rows"][-2]["metrics"]["nv_ari"] = float("nan")
    with pytest.raises(SchemaError):
        write_report(tmp_path / "report.json", rep)
    assert not (tmp_path / "report.json").exists()


# ---------------------------------------------------------------------- paper numbers


def test_paper_numbers_cover_every_row_of_the_protocol_tables():
    from benchmark.protocols import tables

    expected = {
        "tab:seg": ("Slot Attention", "uORF", "COLF", "sVORF"),
        "tab:nvs": ("uORF", "COLF", "sVORF"),
        "tab:ablation": (
            "sVORF (w/o NVS)",
            "sVORF (w/o CR)",
            "sVORF (density-weighted)",
            "sVORF (w/o SA)",
            "sVORF (ours)",
        ),
        "tab:supp_ablation": (
            "sVORF (w/o Hypernetwork)",
            "sVORF (w Slot-Attention)",
            "sVORF (w SM)",
            "sVORF (ours)",
        ),
        "tab:ab_apparance": ("Slot-Attention", "uORF", "sVORF", "sVORF(567)"),
        "tab:ab_num": ("Slot-Attention", "uORF", "sVORF"),
        "text:rgb_color": ("sVORF (grayscale test)", "sVORF (RGB test)"),
        "tab:time": ("sVORF", "uORF (coarse)", "uORF (fine)", "COLF (coarse)", "COLF (fine)"),
    }
    for table, models in expected.items():
        got = [r["model"] for r in PAPER_TABLES[table]["rows"]]
        assert set(got) == set(models), table
    for table in ("tab:seg", "tab:nvs"):
        assert {r["dataset"] for r in PAPER_TABLES[table]["rows"]} == set(tables.ROOM_AND_CLEVR)
    # Every ablation variant the paper lists is a model variant the adapter knows.
    for table in tables.ABLATION_TABLES:
        for r in PAPER_TABLES[table]["rows"]:
            assert r["variant"] in adapter.VARIANTS
    # Spot values (transcription).
    assert PAPER_TABLES["tab:seg"]["rows"][-3]["metrics"] == {
        "nv_ari": 81.5,
        "ari": 82.7,
        "fg_ari": 92.0,
    }
    assert PAPER_TABLES["tab:nvs"]["rows"][-1]["metrics"] == {
        "lpips": 0.1637,
        "ssim": 0.7825,
        "psnr": 29.41,
    }
    assert PAPER_TABLES["text:rgb_color"]["rows"][0]["metrics"]["fg_ari"] == 87.5


@pytest.mark.skipif(not TEX.is_file(), reason=f"paper source {TEX} not on this machine")
def test_paper_numbers_match_the_latex_tables():
    tex = TEX.read_text()
    number = re.compile(r"(?<![\d.])\d+\.\d+")
    for table, spec in PAPER_TABLES.items():
        if table.startswith("text:"):
            block = tex[tex.index("paragraph{RGB color}") :][:900]
        else:
            # The tabular nearest to the label (labels sit before or after theirs).
            at = tex.index(f"\\label{{{table}}}")
            spans = [
                (m.start(), tex.index("\\end{tabular}", m.start()))
                for m in re.finditer(r"\\begin\{tabular\}", tex)
            ]
            start, end = min(spans, key=lambda se: se[0] - at if se[0] > at else at - se[1])
            block = tex[start:end]
        # Every row's numbers must sit together on one line of the table (no row swaps).
        lines = [{float(x) for x in number.findall(line)} for line in block.splitlines()]
        for row in spec["rows"]:
            values = {v for m, v in row["metrics"].items() if v is not None and m != "epoch_time_s"}
            if not values or row.get("note"):
                continue
            assert any(values <= line for line in lines), (
                table,
                row["model"],
                row["dataset"],
                values,
            )


# ---------------------------------------------------------------------- leaderboard


def test_leaderboard_merges_keeps_newest_and_skips_invalid(tmp_path):
    old = _good_report(created="2025-01-01T00:00:00Z")
    new = _good_report(created="2025-02-01T00:00:00Z")
    new["rows"][-2]["metrics"]["nv_ari"] = 42.0
    write_report(tmp_path / "a" / "report.json", old)
    write_report(tmp_path / "b" / "report.json", new)
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "report.json").write_text('{"schema_version": "1.0"}')
    board = merge_reports(tmp_path)
    assert (tmp_path / "leaderboard.json").is_file()
    assert json.loads((tmp_path / "leaderboard.json").read_text())["entries"] == board["entries"]
    measured = [e for e in board["entries"] if e["source"] == "measured"]
    assert len(measured) == 1 and measured[0]["metrics"]["nv_ari"] == 42.0
    assert len([e for e in board["entries"] if e["source"] == "paper"]) == 5
    assert [s["report"] for s in board["skipped"]] == [str(Path("c") / "report.json")]
    text = format_leaderboard(board)
    assert (
        "sVORF (w/o NVS)" in text and "smoke seed 0" in text and "== Ablations (Table 5) ==" in text
    )
    # ARI family on the paper's 0-100 scale with one decimal (stored 42.0 -> "42.0").
    assert re.search(r"smoke seed 0\s+42\.0\s", text) and "42.00" not in text


def test_leaderboard_keeps_a_measured_row_over_a_newer_one_without_numbers(tmp_path):
    old = _good_report(created="2025-01-01T00:00:00Z")
    new = _good_report(created="2025-02-01T00:00:00Z")
    row = next(r for r in new["rows"] if r["source"] == "measured")
    row["metrics"] = {k: None for k in row["metrics"]}
    row["null_reasons"] = {k: "not_trained: --no-train" for k in row["metrics"]}
    new["status"] = "partial"
    write_report(tmp_path / "a" / "report.json", old)
    write_report(tmp_path / "b" / "report.json", new)
    measured = [e for e in merge_reports(tmp_path)["entries"] if e["source"] == "measured"]
    assert len(measured) == 1 and measured[0]["report"] == str(Path("a") / "report.json")
    assert any(v is not None for v in measured[0]["metrics"].values())


def test_leaderboard_keeps_rows_of_different_budgets_apart(tmp_path):
    short = _good_report(created="2025-01-01T00:00:00Z")
    long = _good_report(created="2025-02-01T00:00:00Z")
    long["scale_settings"]["train_minutes"] = 60.0
    write_report(tmp_path / "a" / "report.json", short)
    write_report(tmp_path / "b" / "report.json", long)
    board = merge_reports(tmp_path)
    budgets = sorted(str(e["budget"]) for e in board["entries"] if e["source"] == "measured")
    assert len(budgets) == 2 and "60 min" in budgets
    assert "smoke seed 0, 60 min" in format_leaderboard(board)


def test_leaderboard_keeps_baselines_on_other_scenes_apart(tmp_path):
    """A chance baseline is computed on the test scenes: one on the scenes of data seed 1 is
    another entry than one on seed 0's, not a newer value of it; on the same scenes the
    newest wins."""
    reports = {
        "s0_old": (0, "2025-01-01T00:00:00Z", 10.0),
        "s0_new": (0, "2025-02-01T00:00:00Z", 20.0),
        "s1": (1, "2025-03-01T00:00:00Z", 30.0),
    }
    for name, (data_seed, created, value) in reports.items():
        rep = _good_report(created=created)
        rep["seeds"] = {"data": data_seed, "train": data_seed, "eval": data_seed}
        next(r for r in rep["rows"] if r["source"] == "baseline")["metrics"]["fg_ari"] = value
        write_report(tmp_path / name / "report.json", rep)
    board = merge_reports(tmp_path)
    chance = [e for e in board["entries"] if e["source"] == "baseline"]
    assert [(e["data_seed"], e["metrics"]["fg_ari"]) for e in chance] == [(0, 20.0), (1, 30.0)]
    text = format_leaderboard(board)
    assert "smoke baseline, data 0" in text and "smoke baseline, data 1" in text
    # Measured rows are still one per training seed, paper rows one in all.
    assert len([e for e in board["entries"] if e["source"] == "measured"]) == 2
    assert len([e for e in board["entries"] if e["source"] == "paper"]) == 5


def _recipe_report(created: str, **train_changes) -> dict:
    """A cpu-scale report whose measured row's model has the cpu recipe's configs for
    CLEVR-567, with ``train_changes`` (a lever) applied to its train config."""
    from benchmark import adapter

    mcfg, tcfg = adapter.base_configs("cpu", "clevr567")
    rep = _good_report(created=created)
    rep["scale"] = "cpu"
    row = next(r for r in rep["rows"] if r["source"] == "measured")
    row["run_key"] = "ab" * 8
    train = json.loads(json.dumps(adapter.config_dict(tcfg)))
    train.update(seed=1, steps=1_000_000, **train_changes)
    rep["models"] = [
        {
            "run_key": "ab" * 8,
            "variant": "full",
            "train_dataset": "clevr567/train",
            "model_config": json.loads(json.dumps(adapter.config_dict(mcfg))),
            "train_config": train,
            "seed": 1,
            "reused": False,
            "train_wall_s": 1.0,
        }
    ]
    return rep


def test_leaderboard_prefers_the_current_recipe_over_a_newer_lever(tmp_path):
    from benchmark.leaderboard import current_recipe

    recipe = _recipe_report("2025-01-01T00:00:00Z")
    lever = _recipe_report("2025-02-01T00:00:00Z", ema_decay=0.9995)
    row = next(r for r in lever["rows"] if r["source"] == "measured")
    assert current_recipe(recipe, row) is True and current_recipe(lever, row) is False
    write_report(tmp_path / "lever" / "report.json", lever)
    alone = [e for e in merge_reports(tmp_path)["entries"] if e["source"] == "measured"]
    assert len(alone) == 1 and alone[0]["current_recipe"] is False
    assert "earlier recipe" in format_leaderboard(merge_reports(tmp_path))
    write_report(tmp_path / "recipe" / "report.json", recipe)
    board = merge_reports(tmp_path)
    measured = [e for e in board["entries"] if e["source"] == "measured"]
    assert len(measured) == 1 and measured[0]["report"] == str(Path("recipe") / "report.json")
    assert measured[0]["current_recipe"] is True
    assert "cpu seed 0, earlier recipe" not in format_leaderboard(board)


def test_leaderboard_prefers_the_recipe_speed_over_a_newer_run_on_a_slower_machine(tmp_path):
    # One recipe, seed and 60-minute budget: a machine at half the recipe's steps per minute
    # gives the same run key fewer steps, and its newer row does not replace the other.
    def budgeted(created: str, steps: int) -> dict:
        rep = _recipe_report(created)
        rep["scale_settings"]["train_minutes"] = 60.0
        rep["models"][0].update(
            config_source="svorf.train.run_configs (cpu recipe)",
            steps_done=steps,
            train_wall_s=3600.0,
            train_budget={"minutes": 60.0, "max_wall_s": 3600.0},
        )
        return rep

    write_report(tmp_path / "fast" / "report.json", budgeted("2025-01-01T00:00:00Z", 25_744))
    write_report(tmp_path / "slow" / "report.json", budgeted("2025-02-01T00:00:00Z", 13_068))
    board = merge_reports(tmp_path)
    (measured,) = [e for e in board["entries"] if e["source"] == "measured"]
    assert measured["report"] == str(Path("fast") / "report.json")
    assert "slow_machine" not in measured
    (tmp_path / "fast" / "report.json").unlink()  # alone, the slow row shows, marked
    (measured,) = [e for e in merge_reports(tmp_path)["entries"] if e["source"] == "measured"]
    assert measured["slow_machine"] is True
    assert "seed 0, 60 min, slow machine" in format_leaderboard(merge_reports(tmp_path))


# ---------------------------------------------------------------------- evaluation


def test_baselines_and_perfect_prediction(tmp_path, monkeypatch):
    from benchmark.evaluate import evaluate_baselines, evaluate_model

    root = adapter.write_synthetic_split(tmp_path / "test", n_scenes=2, resolution=32, seed=3)
    ds = adapter.open_dataset(root)
    res = evaluate_baselines(ds, num_slots=4)
    assert res["one_label"].metrics["ari"] == 0.0
    assert abs(res["random_slots"].metrics["ari"]) < 5.0
    assert res["median_colour"].metrics["psnr"] > 5.0
    assert set(res["median_colour"].metrics) >= {"psnr", "ssim", "lpips"}
    if res["median_colour"].metrics["lpips"] is None:
        assert res["median_colour"].null_reasons["lpips"] == "lpips_unavailable"

    def oracle(model, dataset, index, input_view=0, *, slots_scene=None, input_view_only=False):
        gt = adapter.ground_truth(dataset, index)
        keep = slice(input_view, input_view + 1) if input_view_only else slice(None)
        return adapter.Prediction(
            rgb=(gt.images * 0.98).clamp(0, 1)[keep],
            depth_z=gt.depth_z.nan_to_num(posinf=30.0)[keep],
            labels=(gt.instances * 3 + 1)[keep],
        )

    monkeypatch.setattr(adapter, "predict_scene", oracle)
    r = evaluate_model(object(), ds)
    for k in ("ari", "fg_ari", "nv_ari", "ari_all", "fg_ari_all"):
        assert r.metrics[k] == pytest.approx(100.0), k
    assert r.metrics["psnr"] > 30 and r.metrics["ssim"] > 0.95
    assert r.n_scenes == 2 and r.sample is not None


# ---------------------------------------------------------------------- end to end


def test_tiny_protocol_end_to_end_writes_json_figures_html(e2e):
    out, path, _ = e2e
    report = json.loads(path.read_text())
    validate_report(report)
    assert report["status"] == "complete"
    sources = {r["source"] for r in report["rows"]}
    assert sources == {"paper", "measured", "baseline"}
    paper = [r for r in report["rows"] if r["source"] == "paper"]
    assert len(paper) == len(PAPER_TABLES["tab:ablation"]["rows"])
    measured = [r for r in report["rows"] if r["source"] == "measured"]
    assert {r["model"] for r in measured} == {"sVORF (ours)", "sVORF (w/o SA)"}
    control = {"ari_shuffled", "fg_ari_shuffled", "fg_ari_gain"}
    for r in measured:
        assert (
            r["n_scenes"] == 2
            and r["run_key"]
            and set(r["metrics"]) == {"nv_ari", "fg_ari", "ari", "psnr"} | control
        )
        m = r["metrics"]
        if m["fg_ari"] is not None and m["fg_ari_shuffled"] is not None:
            assert m["fg_ari_gain"] == pytest.approx(m["fg_ari"] - m["fg_ari_shuffled"])
        for k in control:  # computed, or null for a stated reason (no foreground)
            assert m[k] is not None or r["null_reasons"][k]
    assert not any(control & set(r["metrics"]) for r in report["rows"] if r["source"] != "measured")
    assert all("fg_ari_shuffled" in v for v in report["verdicts"] if v["decomposes"] is not None)
    assert len(report["models"]) == 2 and all(
        m["model_config"] and m["train_config"] for m in report["models"]
    )
    assert report["verdicts"] and all("decompose" in v["message"] for v in report["verdicts"])
    assert report["hardware"]["torch_version"] == torch.__version__
    assert set(report["wall_time_s"]) == {"data", "training", "evaluation", "total"}
    folder = path.parent
    for f in report["figures"]:
        assert (folder / f).stat().st_size > 1000
    assert len(report["figures"]) == 2
    page = (folder / "index.html").read_text()
    assert "Ablations (Table 5)" in page and "bars.png" in page and "decompose" in page
    assert ">FG-ARI shuffled</th>" in page and ">FG-ARI gain</th>" in page
    assert "<h2>tab:ablation</h2>" not in page  # the id only as a reference, not a title
    assert len(list((out / "reports" / "runs").iterdir())) == 2


def test_resume_skips_finished_rows_and_reuses_models(e2e, monkeypatch):
    out, path, _ = e2e
    before = {r["id"]: r for r in json.loads(path.read_text())["rows"]}

    def no_training(*a, **k):
        raise AssertionError("a finished row or cached model must not be trained again")

    monkeypatch.setattr(adapter, "train", no_training)
    monkeypatch.setattr(adapter, "predict_scene", no_training)
    path2 = run_table_protocol(_ctx(out), ["tab:ablation"], _tiny_rows(), _tiny_figures)
    after = json.loads(path2.read_text())
    assert {r["id"]: r["metrics"] for r in after["rows"]} == {
        k: r["metrics"] for k, r in before.items()
    }
    assert any("reused" in n for n in after["notes"])
    assert all(m["reused"] for m in after["models"])


def test_interrupted_run_resumes_without_redoing_finished_rows(tmp_path, monkeypatch):
    real_train = adapter.train
    calls = []

    def flaky(data_dir, run_dir, mcfg, tcfg, **kw):
        calls.append(mcfg.self_attention)
        if len(calls) == 2:
            raise KeyboardInterrupt  # killed while training the second model
        return real_train(data_dir, run_dir, mcfg, tcfg, **kw)

    monkeypatch.setattr(adapter, "train", flaky)
    with pytest.raises(KeyboardInterrupt):
        run_table_protocol(_ctx(tmp_path), ["tab:ablation"], _tiny_rows(), None)
    rows_dir = tmp_path / "reports" / "ablation-smoke" / "rows"
    assert len(list(rows_dir.glob("*.json"))) == 1  # the first row was kept
    calls.clear()
    path = run_table_protocol(_ctx(tmp_path), ["tab:ablation"], _tiny_rows(), None)
    assert calls == [False]  # only the w/o-SA model was trained on the rerun
    validate_report(json.loads(path.read_text()))


def test_a_failing_row_keeps_the_others_and_is_marked_failed(tmp_path, monkeypatch):
    real_train = adapter.train

    def broken_for_wo_sa(data_dir, run_dir, mcfg, tcfg, **kw):
        if not mcfg.self_attention:
            raise ValueError("ModelConfig refuses this combination")
        return real_train(data_dir, run_dir, mcfg, tcfg, **kw)

    monkeypatch.setattr(adapter, "train", broken_for_wo_sa)
    path = run_table_protocol(_ctx(tmp_path), ["tab:ablation"], _tiny_rows(), None)
    report = json.loads(path.read_text())
    validate_report(report)
    assert report["status"] == "partial"
    measured = {r["model"]: r for r in report["rows"] if r["source"] == "measured"}
    ok, bad = measured["sVORF (ours)"], measured["sVORF (w/o SA)"]
    assert ok["metrics"]["fg_ari"] is not None and "failed" not in ok
    assert bad["failed"].startswith("ValueError: ModelConfig refuses")
    assert all(v is None for v in bad["metrics"].values())
    assert all(r.startswith("failed: ValueError") for r in bad["null_reasons"].values())
    assert any("FAILED" in n for n in report["notes"])


def test_room_diverse_model_starts_from_the_clevr567_model(tmp_path):
    m = ("ari", "fg_ari")
    rows = [MeasuredRow("tab:seg", "sVORF", "room-diverse", ModelJob("full", "room-diverse"), m)]
    path = run_table_protocol(_ctx(tmp_path), ["tab:seg"], rows, None)
    report = json.loads(path.read_text())
    validate_report(report)
    models = {m["train_dataset"]: m for m in report["models"]}
    room = models["room-diverse/train"]
    init = room["init_from"]
    assert init is not None and init["loaded"] > 0
    clevr_run = next(
        p for p in (tmp_path / "reports" / "runs").iterdir() if p.name != room["run_key"]
    )
    assert init["path"] == str((clevr_run / "checkpoint.pt").resolve())


def test_no_train_scores_only_cached_models(tmp_path):
    rows = _tiny_rows()
    first = Context(
        "ablation", "smoke", tmp_path / "reports", tmp_path / "data",
        data_source="synthetic", progress=False, train_steps=2, no_train=True,
    )  # fmt: skip
    report = json.loads(run_table_protocol(first, ["tab:ablation"], rows, None).read_text())
    validate_report(report)
    measured = [r for r in report["rows"] if r["source"] == "measured"]
    assert report["status"] == "partial" and not (tmp_path / "reports" / "runs").exists()
    assert all(v.startswith("not_trained: --no-train") for r in measured
               for v in r["null_reasons"].values())  # fmt: skip
    run_table_protocol(_ctx(tmp_path), ["tab:ablation"], rows[:1], None)  # trains one model
    again = Context(
        "ablation", "smoke", tmp_path / "reports", tmp_path / "data",
        data_source="synthetic", progress=False, train_steps=2, no_train=True,
    )  # fmt: skip
    report = json.loads(run_table_protocol(again, ["tab:ablation"], rows, None).read_text())
    by_model = {r["model"]: r for r in report["rows"] if r["source"] == "measured"}
    assert by_model["sVORF (ours)"]["metrics"]["fg_ari"] is not None
    assert by_model["sVORF (w/o SA)"]["metrics"]["fg_ari"] is None


def test_a_model_that_may_not_train_needs_no_training_split_without_a_run(tmp_path):
    m = ("fg_ari", "ari")
    rows = [
        MeasuredRow(
            "tab:ab_apparance", "sVORF", "clevr567-heldout", ModelJob("full", "clevr567-heldout"), m
        )
    ]
    train_split = tmp_path / "data" / "smoke" / "clevr567-heldout" / "train"

    def ctx(**kw):
        return Context(
            "generalization", "smoke", tmp_path / "reports", tmp_path / "data",
            data_source="synthetic", progress=False, train_steps=2, **kw,
        )  # fmt: skip

    report = json.loads(
        run_table_protocol(ctx(no_train=True), ["tab:ab_apparance"], rows, None).read_text()
    )
    (row,) = [r for r in report["rows"] if r["source"] == "measured"]
    assert row["metrics"]["fg_ari"] is None
    assert row["null_reasons"]["fg_ari"].startswith("not_trained: --no-train")
    assert not train_split.exists()  # nothing to hash: no run could be this model
    run_table_protocol(ctx(), ["tab:ab_apparance"], rows, None)  # trains it
    shutil.rmtree(train_split)
    # A finished run of the same model: its split is made again to confirm the key.
    report = json.loads(
        run_table_protocol(ctx(no_train=True), ["tab:ab_apparance"], rows, None).read_text()
    )
    (row,) = [r for r in report["rows"] if r["source"] == "measured"]
    assert row["metrics"]["fg_ari"] is not None and train_split.is_dir()


def test_train_only_trains_the_named_variants_and_scores_cached_others(tmp_path):
    rows = _tiny_rows()

    def ctx(**kw):
        return Context(
            "ablation", "smoke", tmp_path / "reports", tmp_path / "data",
            data_source="synthetic", progress=False, train_steps=2, **kw,
        )  # fmt: skip

    report = json.loads(
        run_table_protocol(ctx(train_only=["wo_sa"]), ["tab:ablation"], rows, None).read_text()
    )
    validate_report(report)
    assert report["scale_settings"]["train_only"] == ["wo_sa"]
    by_model = {r["model"]: r for r in report["rows"] if r["source"] == "measured"}
    assert by_model["sVORF (w/o SA)"]["metrics"]["fg_ari"] is not None
    full = by_model["sVORF (ours)"]
    assert all(v is None for v in full["metrics"].values())
    assert all(
        v.startswith("not_trained: --train-only wo_sa") for v in full["null_reasons"].values()
    )
    assert (
        report["status"] == "partial" and len(list((tmp_path / "reports" / "runs").iterdir())) == 1
    )
    # A second run that trains the other variant scores both (the first from the cache).
    report = json.loads(
        run_table_protocol(ctx(train_only=["full"]), ["tab:ablation"], rows, None).read_text()
    )
    assert report["status"] == "complete"
    assert all(
        r["metrics"]["fg_ari"] is not None for r in report["rows"] if r["source"] == "measured"
    )


@pytest.mark.parametrize(
    "kw, needle",
    [
        ({"train_only": ["wo_nvv"]}, "no model variant 'wo_nvv'; did you mean 'wo_nvs'?"),
        ({"train_only": [" "]}, "no model variant given"),
        ({"train_only": ["full"], "no_train": True}, "pass one of them, not both"),
    ],
)
def test_train_only_refuses_bad_names(tmp_path, kw, needle):
    with pytest.raises(ValueError, match=re.escape(needle)):
        Context("ablation", "smoke", tmp_path / "r", tmp_path / "d", **kw)


def test_row_store_ignores_rows_of_another_context(tmp_path):
    a = RowStore(tmp_path, {"scale": "smoke"})
    a.put({"id": "x|y", "v": 1})
    assert a.get("x|y") == {"id": "x|y", "v": 1}
    assert RowStore(tmp_path, {"scale": "cpu"}).get("x|y") is None


def _fake_generator(monkeypatch, calls):
    """Install a stand-in ``generators.pipeline`` with the expected generate_dataset(cfg)."""
    import dataclasses
    import sys
    import types

    @dataclasses.dataclass(frozen=True)
    class GenerateConfig:
        preset: str
        split: str
        n: int
        out: Path
        resolution: int = 128
        samples: int = 16
        denoise: bool = True
        seed: int = 0
        progress: bool = True
        workers: int | None = None

    def generate_dataset(cfg: GenerateConfig) -> Path:
        calls.append(cfg)
        root = adapter.write_synthetic_split(
            cfg.out,
            n_scenes=cfg.n,
            resolution=cfg.resolution,
            seed=cfg.seed,
            preset=cfg.preset,
            split=cfg.split,
        )
        manifest = json.loads((root / "manifest.json").read_text())
        manifest["generator"] = "generators (test stand-in)"
        (root / "manifest.json").write_text(json.dumps(manifest))
        return root

    mod = types.ModuleType("generators.pipeline")
    mod.GenerateConfig = GenerateConfig
    mod.generate_dataset = generate_dataset
    monkeypatch.setitem(sys.modules, "generators.pipeline", mod)


def test_generator_bridge_fills_the_config_and_unknown_presets_become_null_rows(
    tmp_path, monkeypatch
):
    from benchmark.datasets import ensure_dataset
    from benchmark.scales import get_scale

    calls = []
    _fake_generator(monkeypatch, calls)
    info = ensure_dataset(tmp_path, get_scale("smoke"), "clevr567", "test", source="generator")
    assert calls and calls[0].n == 2 and calls[0].resolution == 32 and calls[0].samples == 1
    assert info.source == "generator" and info.n_scenes == 2 and len(info.fingerprint) == 64
    ensure_dataset(tmp_path, get_scale("smoke"), "clevr567", "test", source="generator")
    assert len(calls) == 1  # complete on disk: not generated again
    # A preset the generator does not know gives null rows with the reason, not a crash.
    ctx = Context(
        "ablation", "smoke", tmp_path / "reports", tmp_path / "data", progress=False, train_steps=1
    )
    row = MeasuredRow(
        "tab:ablation",
        "sVORF (ours)",
        "no-such-preset",
        ModelJob("full", "no-such-preset"),
        ("nv_ari", "fg_ari"),
    )
    report = json.loads(run_table_protocol(ctx, ["tab:ablation"], [row], None).read_text())
    assert report["status"] == "partial"
    (measured,) = [r for r in report["rows"] if r["source"] == "measured"]
    from benchmark.evaluate import CONTROL_KEYS

    # The segmentation row carries its scene-shuffle control columns, null as well.
    nulls = {"nv_ari": None, "fg_ari": None, **dict.fromkeys(CONTROL_KEYS)}
    assert measured["metrics"] == nulls and measured["n_scenes"] == 0
    assert measured["null_reasons"]["fg_ari"].startswith("dataset_unavailable")


def test_stability_protocol_all_cases_pass(tmp_path):
    from benchmark.protocols.stability import CASES, run_stability
    from benchmark.protocols.stability import cases as sc

    ctx = Context("stability", "smoke", tmp_path, tmp_path / "data", progress=False)
    report = json.loads(run_stability(ctx).read_text())
    tables = {}
    for r in report["rows"]:
        tables[r["table"]] = tables.get(r["table"], 0) + 1
    assert tables == {
        "stability": len(CASES),
        "stability_compose": len(sc.COMPOSE_CASES),
        "stability_loss": len(sc.LOSS_CASES),
        "stability_metrics": len(sc.METRIC_CASES),
        "stability_training": 1,
    }
    bad = [(r["model"], r["metrics"]) for r in report["rows"] if not r["pass"]]
    assert not bad
    assert all(r["metrics"].get("nonfinite_count", 0) == 0 for r in report["rows"])
    guard = next(r for r in report["rows"] if r["table"] == "stability_training")
    assert guard["metrics"]["checkpoint_step"] == guard["metrics"]["diverged_at_step"] - 1
    assert "keeps the last good state" in guard["guard_message"]
    empty_fg = next(r for r in report["rows"] if "empty foreground" in r["model"])
    assert empty_fg["metrics"]["value"] is None and empty_fg["metrics"]["reference_value"] == 1.0
    assert "no foreground" in empty_fg["null_reasons"]["value"]
    assert (tmp_path / "stability-smoke" / "stability.png").is_file()


def test_stability_oracles_catch_a_finite_stand_in_for_masked_logits(monkeypatch):
    """The code before 2026-11-24 filled masked logits with -1e4: rows whose valid logits
    all lay below that gave every point's mass to masked slots (zeroed: m = 0)."""
    import svorf.compose
    from benchmark.protocols.stability import cases as sc

    def finite_stand_in(logits, valid, dim=-1):
        if valid is None:
            return torch.softmax(logits.float(), dim=dim)
        p = torch.softmax(logits.float().masked_fill(~valid, -1e4), dim=dim)
        return p.masked_fill(~valid, 0.0)

    monkeypatch.setattr(svorf.compose, "masked_softmax", finite_stand_in)
    failed = {r["model"] for r in sc.compose_rows(0) if not r["pass"]}
    assert "valid logits below -1e4, masked ones at 0" in failed
    assert "moderate logits and densities" not in failed


def test_stability_training_row_fails_when_the_guard_does_not_fire(monkeypatch):
    from benchmark import adapter
    from benchmark.protocols.stability import cases as sc

    quiet = {"diverged": False, "diverged_at_step": None, "message": None,
             "checkpoint_loads": True, "checkpoint_step": 30, "nonfinite_params": 0,
             "temp_files": 0}  # fmt: skip
    monkeypatch.setattr(adapter, "diverging_run", lambda *a, **k: quiet)
    row = sc.training_row("smoke", 0)
    assert row["pass"] is False and row["metrics"]["diverged_at_step"] is None
    assert "did not fire" in row["null_reasons"]["diverged_at_step"]


def test_stability_connectivity_oracle_closed_form():
    from benchmark.protocols.stability.cases import reference_connectivity

    # One slot, one ray, a single interval [0, 1] (near 0, far 1) of weight w: the
    # distortion is w^2 / 3 (no pairs), w = 1 - exp(-sigma).
    sigma = torch.tensor([[[[2.0]]]])
    got = reference_connectivity(sigma, torch.zeros(1, 1, 1), torch.ones(1, 1), 0.0, 1.0, None)
    w = 1 - math.exp(-2.0)
    assert got == pytest.approx(w * w / 3)
    mask = torch.zeros(1, 1, dtype=torch.bool)
    assert (
        reference_connectivity(sigma, torch.zeros(1, 1, 1), torch.ones(1, 1), 0.0, 1.0, mask) == 0.0
    )


def test_stability_reference_closed_form():
    from benchmark.protocols.stability import reference_render

    # One ray, constant density s over [0, L] in two samples: acc = 1 - exp(-s * L_total).
    sigma = torch.tensor([[2.0, 2.0]])
    t = torch.tensor([[0.0, 0.5]])
    ref = reference_render(sigma, torch.ones(1, 2, 3), t, last_delta=0.5)
    assert float(ref["acc"][0]) == pytest.approx(1 - math.exp(-2.0))
    inf_first = reference_render(torch.tensor([[math.inf, 1.0]]), torch.rand(1, 2, 3), t, 1.0)
    assert float(inf_first["weights"][0, 0]) == 1.0 and float(inf_first["depth"][0]) == 0.0


def test_cli_list_and_one_line_errors(capsys):
    assert cli_main(["list"]) == 0
    assert "generalization" in capsys.readouterr().out
    assert cli_main(["run", "nope", "--scale", "smoke"]) == 2
    assert "unknown protocol 'nope'" in capsys.readouterr().err
    from benchmark.protocols import get_protocol

    assert get_protocol("tradeoff").__name__ == "run_tradeoff"  # tests/test_tradeoff.py runs it


@pytest.mark.skipif(
    chromium_binary() is None, reason="chromium is not installed (apt-get install -y chromium)"
)
def test_html_page_renders_in_headless_chromium(e2e):
    from PIL import Image

    _, path, _ = e2e
    report = json.loads(path.read_text())
    index = write_index(path.parent, report)
    png = render_screenshot(index, path.parent / "screenshot.png", size=(1200, 1600))
    with Image.open(png) as im:
        arr = np.asarray(im.convert("L"), dtype=np.float64)
    assert arr.shape == (1600, 1200)
    assert arr.std() > 10  # not a blank page


# ---------------------------------------------------------------------- slow tier


@pytest.mark.slow
def test_speed_protocol_on_synthetic_data(tmp_path):
    from benchmark.protocols.speed import run_speed

    ctx = Context(
        "speed",
        "smoke",
        tmp_path / "reports",
        tmp_path / "data",
        data_source="synthetic",
        progress=False,
    )
    report = json.loads(run_speed(ctx).read_text())
    rows = report["rows"]
    m = [r for r in rows if r["source"] == "measured" and r["table"] in ("tab:time", "speed")]
    assert len(m) == 2 and all(r["metrics"]["steps_per_s"] > 0 for r in m)
    assert m[0]["metrics"]["memory_gb"] > 0 and m[0]["metrics"]["render_s_per_view"] > 0
    # sVORF vs the uORF-style configuration, measured side by side in this run
    # at batch 1 (Table 8's setting) and at the scale's training batch (2 at smoke)
    vs = [r for r in rows if r["table"] == "speed_vs_uorf"]
    assert [r.get("batch_scenes") for r in vs] == [1, 1, 1, 2, 2, 2]
    assert len({r["id"] for r in vs}) == 6 and vs[3]["model"].endswith(", batch 2")
    for cmp in ({r["variant"]: r for r in vs[:3]}, {r["variant"]: r for r in vs[3:]}):
        assert set(cmp) == {"full", "uorf_style", "ratio"}
        assert cmp["full"]["rays_per_scene"] < cmp["uorf_style"]["rays_per_scene"] == 32 * 32
        assert cmp["full"]["batch_scenes"] == cmp["uorf_style"]["batch_scenes"]
        ratio = cmp["ratio"]
        assert ratio["metrics"]["step_time_ratio"] > 0 and ratio["metrics"]["memory_ratio"] > 0
        assert set(ratio["target_met"]) == {
            "step_time_ratio",
            "memory_ratio",
            "tensor_memory_ratio",
        }
        # tensor memory (the GPU figure's measure) measured on both sides, the process holds it
        for side in (cmp["full"], cmp["uorf_style"]):
            assert 0 < side["metrics"]["tensor_peak_mb"] < side["metrics"]["peak_memory_mb"]
        assert ratio["metrics"]["tensor_memory_ratio"] > 0
    assert sum("sVORF vs uORF-style at batch" in n for n in report["notes"]) == 2
    # inference images/s; the generator is null with a reason on synthetic data
    inf = [r for r in rows if r["table"] == "speed_inference"]
    assert len(inf) == 2 and all(r["metrics"]["images_per_s"] > 0 for r in inf)
    gen = [r for r in rows if r["table"] == "speed_generator"]
    assert gen and gen[0]["metrics"]["overhead_ratio"] is None
    assert "synthetic" in gen[0]["null_reasons"]["overhead_ratio"]
    assert report["figures"] == ["speed.png", "speed_vs_uorf.png"]


def _generator_ready() -> bool:
    try:
        from benchmark.generator_bridge import entry_point

        entry_point()
    except Exception:  # noqa: BLE001 - any failure means "not ready here"
        return False
    # find_spec, not import: importing bpy here would break the generator's own import
    # in this process ("No module named '_bpy'").
    import importlib.util

    return importlib.util.find_spec("bpy") is not None


@pytest.mark.slow
@pytest.mark.skipif(
    not _generator_ready(), reason="generators.generate_dataset or bpy not available"
)
@pytest.mark.parametrize("protocol", ["ablation", "generalization"])
def test_smoke_protocol_with_generator_presets(tmp_path, protocol):
    rc = cli_main(
        [
            "run",
            protocol,
            "--scale",
            "smoke",
            "--out",
            str(tmp_path / "reports"),
            "--data",
            str(tmp_path / "data"),
            "--no-progress",
        ]
    )
    assert rc == 0
    folder = tmp_path / "reports" / f"{protocol}-smoke"
    report = json.loads((folder / "report.json").read_text())
    validate_report(report)
    tables = {
        "ablation": ["tab:ablation", "tab:supp_ablation"],
        "generalization": ["tab:ab_apparance", "tab:ab_num", "text:rgb_color"],
    }[protocol]
    for t in tables:
        for prow in PAPER_TABLES[t]["rows"]:
            sources = {
                r["source"]
                for r in report["rows"]
                if r["table"] == t
                and r["model"] == prow["model"]
                and r["dataset"] == prow["dataset"]
            }
            assert "paper" in sources
            if prow["variant"] is not None:
                assert "measured" in sources, (t, prow["model"])
    assert report["status"] == "complete"
    assert all(r["n_scenes"] >= 1 for r in report["rows"] if r["source"] != "paper")
    if protocol == "generalization":
        # The control not in the paper: the CLEVR-567 model on the packed scenes, measured
        # with a verdict of its own and no paper row beside it.
        control = [r for r in report["rows"] if r["model"] == PACKED_CONTROL]
        assert [(r["source"], r["dataset"], r["variant"]) for r in control] == [
            ("measured", "packed-clevr11", "full")
        ]
        assert (
            control[0]["metrics"]["fg_ari"] is not None and "not in the paper" in control[0]["note"]
        )
        assert any(v["model"] == PACKED_CONTROL for v in report["verdicts"])
    assert report["datasets"] and all(d["source"] == "generator" for d in report["datasets"])
    assert (folder / "index.html").is_file() and report["figures"]
