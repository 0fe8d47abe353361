"""The paper's orderings section: claims checked on measured rows."""

from __future__ import annotations

import pytest

from benchmark.orderings import Ordering, check_orderings, orderings_summary
from benchmark.paper_numbers import PAPER_TABLES
from benchmark.protocols import tables


def _row(source, table, model, dataset, **metrics):
    return {"source": source, "table": table, "model": model, "dataset": dataset,
            "metrics": metrics}  # fmt: skip


ROWS = [
    _row("paper", "tab:ablation", "full", "c", fg_ari=92.0),
    _row("paper", "tab:ablation", "wo", "c", fg_ari=31.2),
    _row("measured", "tab:ablation", "full", "c", fg_ari=70.0),
    _row("measured", "tab:ablation", "wo", "c", fg_ari=75.0),
    _row("measured", "tab:ablation", "near", "c", fg_ari=67.0),
    _row("measured", "tab:ablation", "gone", "c", fg_ari=None),
    _row("baseline", "tab:ablation", "blocks", "c", fg_ari=58.0),
    _row("baseline", "tab:ablation", "one slot", "c", fg_ari=0.0),
]


def test_above_close_baseline_and_missing():
    o = [
        Ordering("tab:ablation", "full above wo", "fg_ari", "full", "c", "wo", "c"),
        Ordering("tab:ablation", "near", "fg_ari", "near", "c", "full", "c", kind="close"),
        Ordering("tab:ablation", "chance", "fg_ari", "full", "c", "", "c", b_source="baseline"),
        Ordering("tab:ablation", "missing", "fg_ari", "full", "c", "gone", "c"),
        Ordering("tab:other", "not in this report", "fg_ari", "x", "c", "y", "c"),
    ]
    out = check_orderings(ROWS, o)
    assert len(out) == 4
    above, close, chance, missing = out
    assert above["paper_holds"] is True and above["measured_holds"] is False
    assert above["margin"] == pytest.approx(-5.0) and above["seed_spread"] is None
    assert close["measured_holds"] is True  # |67 - 70| <= 5
    assert chance["measured_holds"] is True and chance["b"]["measured"] == 58.0
    assert "blocks" in chance["b"]["model"] and chance["paper_holds"] is None
    assert missing["measured_holds"] is None and missing["why_null"]
    assert "keep 2 of 3" in orderings_summary(out) and "1 could not" in orderings_summary(out)


def test_seed_spread_from_other_seeds():
    seed1 = [
        _row("measured", "tab:ablation", "full", "c", fg_ari=80.0),
        _row("measured", "tab:ablation", "wo", "c", fg_ari=70.0),
    ]
    o = [Ordering("tab:ablation", "full above wo", "fg_ari", "full", "c", "wo", "c")]
    (res,) = check_orderings(ROWS, o, seed_rows={1: seed1}, seed=0)
    assert res["seed_spread"] == pytest.approx(15.0)  # margins -5 and +10
    assert res["seed_margins"] == {"0": pytest.approx(-5.0), "1": pytest.approx(10.0)}
    assert res["seed_mean"] == pytest.approx(2.5) and res["seed_mean_holds"] is True
    (alone,) = check_orderings(ROWS, o)
    assert alone["seed_margins"] is None and alone["seed_mean_holds"] is None


def test_a_close_claim_is_judged_on_the_mean_margin_with_its_tolerance():
    seed1 = [
        _row("measured", "tab:ablation", "full", "c", fg_ari=71.0),
        _row("measured", "tab:ablation", "wo", "c", fg_ari=70.0),
    ]
    o = [Ordering("tab:ablation", "c", "fg_ari", "full", "c", "wo", "c", "close", 4.0)]
    (res,) = check_orderings(ROWS, o, seed_rows={1: seed1}, seed=0)
    assert res["measured_holds"] is False  # seed 0 alone: |70 - 75| > 4
    assert res["seed_mean"] == pytest.approx(-2.0) and res["seed_mean_holds"] is True
    line = orderings_summary([res])
    assert "on the mean margin of 2 seeds 1 of 1 hold" in line


def test_declared_orderings_name_real_paper_rows():
    declared = tables.ABLATION_ORDERINGS + tables.GENERALIZATION_ORDERINGS
    for o in declared:
        models = {(r["model"], r["dataset"]) for r in PAPER_TABLES[o.table]["rows"]}
        assert (o.a_model, o.a_dataset) in models, o
        if o.b_source == "measured":
            assert (o.b_model, o.b_dataset) in models, o
    with pytest.raises(ValueError, match="kind"):
        Ordering("t", "c", "m", "a", "d", "b", "d", kind="below")
