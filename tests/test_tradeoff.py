"""The ``tradeoff`` benchmark protocol (DESIGN 8: every speed knob has a measured
time-vs-error curve) at smoke scale: report schema, curves, exact points, figure, page.

No timing assertions (shared machines are noisy): only what holds by construction.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from benchmark.cli import main as cli_main
from benchmark.protocols import tradeoff
from benchmark.runner import Context, ModelJob
from benchmark.schema import validate_report

ERRORS = ("rgb_max_err", "rgb_mean_err", "depth_mean_err", "slot_probs_max_err")
KNOBS_INIT = {"bf16_autocast", "slot_keep_mass", "slot_topk", "fg_box", "samples_per_ray"}


@pytest.fixture(scope="module")
def smoke(tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("tradeoff")
    threads = torch.get_num_threads()
    rc = cli_main(
        [
            "run",
            "tradeoff",
            "--scale",
            "smoke",
            "--out",
            str(out / "reports"),
            "--data",
            str(out / "data"),
            "--no-progress",
        ]
    )
    assert rc == 0
    assert torch.get_num_threads() == threads  # the protocol restores the thread count
    path = out / "reports" / "tradeoff-smoke" / "report.json"
    return path, json.loads(path.read_text())


def _curves(rows: list[dict]) -> dict[tuple[str, str], list[dict]]:
    out: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        if not r["reference"]:
            out.setdefault((r["weights"], r["knob"]), []).append(r)
    return out


def test_report_is_schema_valid_and_measured(smoke):
    _, rep = smoke
    validate_report(rep)
    assert rep["protocol"] == "tradeoff" and rep["scale"] == "smoke"
    assert rep["status"] == "complete"
    assert all(r["source"] == "measured" for r in rep["rows"])
    assert len({r["id"] for r in rep["rows"]}) == len(rep["rows"])
    settings = rep["scale_settings"]["tradeoff"]
    assert settings["tolerance"] == tradeoff.TOLERANCE
    assert [w["name"] for w in settings["weight_sets"]] == ["init", "sharp-m"]
    # honest labelling: which weights, and that no trained run was used
    text = " ".join(rep["notes"])
    assert "initialisation" in text and "x8" in text
    assert "so no curve uses trained weights" in text


def test_every_knob_has_a_curve(smoke):
    _, rep = smoke
    curves = _curves(rep["rows"])
    for knob in KNOBS_INIT | {"combined"}:
        assert len(curves[("init", knob)]) >= 2, knob
    for knob in ("slot_keep_mass", "slot_topk", "combined"):
        assert len(curves[("sharp-m", knob)]) >= 2, knob
    keep = [r["setting"] for r in curves[("init", "slot_keep_mass")]]
    assert keep == ["1.0", "0.999", "0.99", "0.95", "0.9"]
    topk = [r["setting"] for r in curves[("init", "slot_topk")]]
    assert topk == ["0 (all)", "8 (=K)", "4", "3", "2"]
    for pts in curves.values():
        assert pts[0]["overrides"] == {}  # each curve starts at its own off instance


def test_metrics_finite_and_tolerance_flag_consistent(smoke):
    _, rep = smoke
    for r in rep["rows"]:
        m = r["metrics"]
        assert not r["null_reasons"]
        assert all(v is not None and math.isfinite(v) for v in m.values()), r["id"]
        assert m["step_time_s"] > 0 and m["speedup"] > 0
        assert 0 < m["kept_pairs"] <= 1
        assert all(m[k] >= 0 for k in ERRORS)
        tol = r["tolerance"]
        assert r["within_tolerance"] == all(m[k] <= t for k, t in tol.items())
        assert r["n_cases"] == tradeoff.SETTINGS["smoke"].repeats == len(r["step_times_s"])
        want = tradeoff.TOLERANCE_COMBINED if r["knob"] == "combined" else tradeoff.TOLERANCE
        assert tol == want


def test_baseline_and_exact_points(smoke):
    _, rep = smoke
    refs = [r for r in rep["rows"] if r["reference"]]
    assert {r["weights"] for r in refs} == {"init", "sharp-m"}
    for r in refs:  # the reference against itself: by definition
        assert r["metrics"]["speedup"] == 1.0
        assert all(r["metrics"][k] == 0.0 for k in ERRORS)
        assert r["within_tolerance"] and r["metrics"]["kept_pairs"] == 1.0
    for r in rep["rows"]:
        if not r["overrides"]:
            # the off setting is the baseline's config and weights: bit-identical render
            assert all(r["metrics"][k] == 0.0 for k in ERRORS), r["id"]
        if r["exact_by_construction"]:
            # topk = K, fg_box around the whole sampled box: nothing is left out
            assert all(r["metrics"][k] <= 1e-6 for k in ERRORS), r["id"]
            assert r["metrics"]["kept_pairs"] == 1.0, r["id"]
    curves = _curves(rep["rows"])
    for w in ("init", "sharp-m"):
        for r in curves[(w, "slot_topk")]:
            t = r["overrides"].get("slot_topk", 0)
            if 0 < t < 8:  # at most t of the K = 8 slots per point are evaluated
                assert r["metrics"]["kept_pairs"] <= t / 8 + 1e-3, r["id"]
                assert r["metrics"]["rgb_max_err"] > 0
    bf16 = next(r for r in curves[("init", "bf16_autocast")] if r["overrides"])
    assert 0 < bf16["metrics"]["rgb_max_err"] <= 1e-2  # the stated bf16 tolerance holds
    assert bf16["within_tolerance"]


def test_figure_and_page(smoke):
    path, rep = smoke
    assert rep["figures"] == ["tradeoff.png"]
    png = path.parent / "tradeoff.png"
    assert png.is_file() and png.stat().st_size > 10_000
    from PIL import Image

    with Image.open(png) as im:
        assert im.size[0] > 500 and im.size[1] > 400
    page = (path.parent / "index.html").read_text()
    assert "tradeoff: init weights" in page and "tradeoff: sharp-m x8 weights" in page
    assert "tradeoff.png" in page and "beyond tolerance" in page and "within tolerance" in page


def test_knob_points_follow_the_model(tmp_path):
    """fg_box that is part of a model is not swept; top-k settings stay below K."""
    from benchmark import adapter

    base = adapter.model_config("smoke", "clevr567", "full").replace(
        num_slots=4, fg_box=3.0, bf16_autocast=True
    )
    ws = tradeoff.WeightSet(
        "x", "t", tradeoff._knobs_off(base), {}, 1.0, tuple(KNOBS_INIT) + ("combined",), ""
    )
    assert ws.base.fg_box == 3.0 and not ws.base.bf16_autocast
    pts = tradeoff.knob_points(ws, "smoke")
    assert not any(p.knob == "fg_box" for p in pts)
    assert not any("fg_box" in p.overrides for p in pts)
    assert [p.setting for p in pts if p.knob == "slot_topk"] == ["0 (all)", "4 (=K)", "3", "2"]
    assert sum(p.reference for p in pts) == 1


def test_uses_a_cached_trained_run(tmp_path, monkeypatch):
    """A finished benchmark run of the same model in <out>/runs gives a 'trained' table."""
    out, data = tmp_path / "reports", tmp_path / "data"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # 2 shared cores
    try:
        _trained_run_case(out, data, monkeypatch)
    finally:
        torch.set_num_threads(threads)


def _trained_run_case(out: Path, data: Path, monkeypatch) -> None:
    trainer = Context(
        "segmentation",
        "smoke",
        out,
        data,
        data_source="synthetic",
        progress=False,
        train_steps=2,
    )
    rec = trainer.model(ModelJob("full", "clevr567"))
    monkeypatch.setitem(
        tradeoff.SETTINGS,
        "smoke",
        tradeoff.TradeoffSettings(repeats=1, warmup=0, threads=1, sharp=False),
    )
    ctx = Context("tradeoff", "smoke", out, data, progress=False)
    rep = json.loads(tradeoff.run_tradeoff(ctx).read_text())
    validate_report(rep)
    trained = [r for r in rep["rows"] if r["weights"] == "trained"]
    assert trained and all(r["run_key"] == rec.key for r in trained)
    assert {r["knob"] for r in trained} >= KNOBS_INIT
    ref = next(r for r in trained if r["reference"])
    assert all(ref["metrics"][k] == 0.0 for k in ERRORS)
    assert any(rec.key in n for n in rep["notes"])
    assert not any("sharp-m" == r["weights"] for r in rep["rows"])
