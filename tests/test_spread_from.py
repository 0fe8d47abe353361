"""Tests of ``benchmark run NAME --spread-from REPORT``: the paper's orderings judged with
the seed-to-seed spread of each margin, from reports of the same table at other seeds.

Tiny ``smoke``-scale synthetic data, 2 training steps; about 20 s in all.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmark import adapter
from benchmark.cli import main as cli_main
from benchmark.orderings import Ordering, check_orderings, orderings_summary, other_seed_rows
from benchmark.schema import validate_report


def _run(tmp: Path, out: str, seed: int, *extra: str) -> int:
    return cli_main(
        [
            "run",
            "segmentation",
            "--scale",
            "smoke",
            "--out",
            str(tmp / out),
            "--data",
            str(tmp / f"data{seed}"),
            "--data-source",
            "synthetic",
            "--no-progress",
            "--datasets",
            "clevr567",
            "--steps",
            "2",
            "--seed",
            str(seed),
            *extra,
        ]
    )


def _report(tmp: Path, out: str) -> dict:
    report = json.loads((tmp / out / "segmentation-smoke" / "report.json").read_text())
    validate_report(report)
    return report


def test_orderings_carry_the_spread_of_their_margin_over_the_seeds(tmp_path):
    assert _run(tmp_path, "s1", 1) == 0
    one = _report(tmp_path, "s1")
    assert all(o["seed_spread"] is None for o in one["orderings"])
    spread_from = str(tmp_path / "s1" / "segmentation-smoke")
    assert _run(tmp_path, "s0", 0, "--spread-from", spread_from) == 0
    zero = _report(tmp_path, "s0")
    assert zero["orderings"], "the segmentation table judges sVORF against chance"
    for o0, o1 in zip(zero["orderings"], one["orderings"], strict=True):
        if o0["margin"] is None or o1["margin"] is None:
            assert o0["seed_spread"] is None
            continue
        assert o0["seed_spread"] == pytest.approx(abs(o0["margin"] - o1["margin"]))
        assert o0["seed_spread_reason"] is None
        assert o0["seed_margins"] == {
            "0": pytest.approx(o0["margin"]),
            "1": pytest.approx(o1["margin"]),
        }
        assert o0["seed_mean"] == pytest.approx((o0["margin"] + o1["margin"]) / 2)
    assert any(o["seed_spread"] is not None for o in zero["orderings"])
    note = next(n for n in zero["notes"] if n.startswith("Seed-to-seed spread"))
    assert "seed 0 (this run) and seed(s) 1" in note and "segmentation-smoke" in note
    html = (tmp_path / "s0" / "segmentation-smoke" / "index.html").read_text()
    assert "mean over seeds" in html and "on the mean" in html
    # The rows and verdicts stay this seed's own.
    m0 = [r["metrics"] for r in zero["rows"] if r["source"] == "measured"]
    m1 = [r["metrics"] for r in one["rows"] if r["source"] == "measured"]
    assert m0 != m1


def _rep(protocol="ablation", scale="cpu", seed=1, steps=25000, minutes=None, refine=0):
    return {
        "kind": "svorf-benchmark-report",
        "protocol": protocol,
        "scale": scale,
        "seeds": {"data": seed, "train": seed, "eval": seed},
        "scale_settings": {
            "train_steps_override": steps,
            "train_minutes": minutes,
            "refine_slots": refine,
        },
        "rows": [
            {"source": "paper", "table": "t", "model": "a", "dataset": "c", "metrics": {}},
            {"source": "measured", "table": "t", "model": "a", "dataset": "c", "metrics": {}},
            {"source": "baseline", "table": "t", "model": "b", "dataset": "c", "metrics": {}},
        ],
    }


MINE = {"train_steps_override": 25000, "train_minutes": None, "refine_slots": 0, "refine_lr": None}


def _other(*reports):
    pairs = [(f"r{i}.json", r) for i, r in enumerate(reports)]
    return other_seed_rows(pairs, protocol="ablation", scale="cpu", seed=0, settings=MINE)


def test_other_seed_rows_keeps_measured_and_baseline_rows_by_seed():
    out = _other(_rep(seed=1), _rep(seed=2))
    assert sorted(out) == [1, 2]
    assert [r["source"] for r in out[1]] == ["measured", "baseline"]
    # A report without refine_slots (written before it existed) counts as 0.
    old = _rep()
    del old["scale_settings"]["refine_slots"]
    assert list(_other(old)) == [1]


def test_a_refined_report_without_a_rate_refined_at_the_rate_of_its_day():
    refined = {**MINE, "refine_slots": 50, "refine_lr": adapter.REFINE_LR_UNRECORDED}
    pairs = [("r0.json", _rep(refine=50))]
    kw = {"protocol": "ablation", "scale": "cpu", "seed": 0}
    assert list(other_seed_rows(pairs, settings=refined, **kw)) == [1]
    with pytest.raises(ValueError, match="refine_lr 0.003 where this run has 0.02"):
        other_seed_rows(pairs, settings={**refined, "refine_lr": 0.02}, **kw)


@pytest.mark.parametrize(
    "report, needle",
    [
        (_rep(seed=0), "the seed of this run"),
        (_rep(protocol="generalization"), "give a 'ablation' report at scale 'cpu'"),
        (_rep(scale="smoke"), "at scale 'smoke'"),
        (_rep(steps=50000), "train_steps_override 50000 where this run has 25000"),
        (_rep(minutes=60.0), "train_minutes 60.0"),
        (_rep(refine=50), "refine_slots 50"),
    ],
)
def test_a_report_that_is_not_another_seed_of_this_table_is_refused(report, needle):
    with pytest.raises(ValueError, match="--spread-from r0.json") as err:
        _other(report)
    assert needle in str(err.value) and "\n" not in str(err.value)


def test_a_report_without_a_training_seed_is_refused():
    report = _rep()
    del report["seeds"]
    with pytest.raises(ValueError, match="names no training seed"):
        _other(report)


def test_two_reports_of_one_seed_are_refused():
    with pytest.raises(ValueError, match="a second report of seed 1"):
        _other(_rep(seed=1), _rep(seed=1))


def test_a_bad_spread_from_is_a_one_line_error_before_any_work(tmp_path, capsys):
    assert _run(tmp_path, "s0", 0, "--spread-from", str(tmp_path / "nowhere")) == 2
    err = capsys.readouterr().err
    assert "--spread-from" in err and "no such file" in err and err.count("\n") == 1
    assert not (tmp_path / "data0").exists()


def test_spread_from_is_refused_for_protocols_without_tables(tmp_path, capsys):
    argv = ["run", "stability", "--out", str(tmp_path), "--spread-from", str(tmp_path)]
    assert cli_main(argv) == 2
    assert "applies to the table protocols" in capsys.readouterr().err


def test_summary_counts_orderings_kept_by_less_than_their_spread():
    def row(model, v, source="measured"):
        return {"source": source, "table": "t", "model": model, "dataset": "c",
                "metrics": {"fg_ari": v}}  # fmt: skip

    rows = [row("full", 80.0), row("wo", 79.0), row("two", 60.0)]
    seed1 = [row("full", 78.0), row("wo", 80.0), row("two", 59.0)]
    o = [
        Ordering("t", "full above wo", "fg_ari", "full", "c", "wo", "c"),
        Ordering("t", "full above two", "fg_ari", "full", "c", "two", "c"),
    ]
    out = check_orderings(rows, o, seed_rows={1: seed1})
    assert [x["seed_spread"] for x in out] == [pytest.approx(3.0), pytest.approx(1.0)]
    line = orderings_summary(out)
    assert "keep 2 of 2" in line and "1 of those kept by a margin smaller than" in line
    assert "smaller than" not in orderings_summary(check_orderings(rows, o))
