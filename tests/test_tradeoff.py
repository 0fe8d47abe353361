"""The ``tradeoff`` benchmark protocol (every speed knob has a measured
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
from generators.blender_backend import bpy_available

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


def _step(rows: list[dict]) -> list[dict]:
    return [r for r in rows if r["curve"] == "step"]


def _render(rows: list[dict]) -> list[dict]:
    return [r for r in rows if r["curve"] == "render"]


def _curves(rows: list[dict]) -> dict[tuple[str, str], list[dict]]:
    out: dict[tuple[str, str], list[dict]] = {}
    for r in _step(rows):
        if not r["reference"]:
            out.setdefault((r["weights"], r["knob"]), []).append(r)
    return out


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
def test_metrics_finite_and_tolerance_flag_consistent(smoke):
    _, rep = smoke
    for r in _step(rep["rows"]):
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


@pytest.mark.slow
def test_baseline_and_exact_points(smoke):
    _, rep = smoke
    refs = [r for r in _step(rep["rows"]) if r["reference"]]
    assert {r["weights"] for r in refs} == {"init", "sharp-m"}
    for r in refs:  # the reference against itself: by definition
        assert r["metrics"]["speedup"] == 1.0
        assert all(r["metrics"][k] == 0.0 for k in ERRORS)
        assert r["within_tolerance"] and r["metrics"]["kept_pairs"] == 1.0
    for r in _step(rep["rows"]):
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


@pytest.mark.slow
def test_figure_and_page(smoke):
    path, rep = smoke
    # no trained run: no training curve, so no training figure
    gen = ["tradeoff_generator.png"] if bpy_available() else []
    assert rep["figures"] == ["tradeoff.png", "tradeoff_render.png", *gen]
    from PIL import Image

    for name in rep["figures"]:
        png = path.parent / name
        assert png.is_file() and png.stat().st_size > 10_000
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
        "x", "t", tradeoff.knobs_off(base), {}, 1.0, tuple(KNOBS_INIT) + ("combined",), ""
    )
    assert ws.base.fg_box == 3.0 and not ws.base.bf16_autocast
    pts = tradeoff.knob_points(ws, "smoke")
    assert not any(p.knob == "fg_box" for p in pts)
    assert not any("fg_box" in p.overrides for p in pts)
    assert [p.setting for p in pts if p.knob == "slot_topk"] == ["0 (all)", "4 (=K)", "3", "2"]
    assert sum(p.reference for p in pts) == 1


@pytest.mark.slow
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
    trainer.dataset("clevr567", "test")  # the render curve scores against its ground truth
    monkeypatch.setitem(
        tradeoff.SETTINGS,
        "smoke",
        tradeoff.TradeoffSettings(repeats=1, warmup=0, threads=1, sharp=False, generator=False),
    )
    ctx = Context("tradeoff", "smoke", out, data, progress=False)
    rep = json.loads(tradeoff.run_tradeoff(ctx).read_text())
    validate_report(rep)
    trained = [r for r in _step(rep["rows"]) if r["weights"] == "trained"]
    assert trained and all(r["run_key"] == rec.key for r in trained)
    assert {r["knob"] for r in trained} >= KNOBS_INIT
    ref = next(r for r in trained if r["reference"])
    assert all(ref["metrics"][k] == 0.0 for k in ERRORS)
    assert any(rec.key in n for n in rep["notes"])
    assert not any("sharp-m" == r.get("weights") for r in rep["rows"])
    # render curve: the trained weights against the test split's ground truth
    render = _render(rep["rows"])
    assert render and all(r["weights"] == "trained" and r["ground_truth"] for r in render)
    assert all(r["run_key"] == rec.key for r in render)
    for r in render:
        assert r["metrics"]["psnr"] is not None and r["metrics"]["psnr"] > 0
        assert r["metrics"]["nv_ari"] is not None
    # Trained weights scored against the truth: test-time refinement is a point too, and it
    # changes the render (init weights on analytic scenes have no such point: below).
    refined = [r for r in render if r["knob"] == "refine_slots"]
    assert [r["refine_steps"] for r in refined] == [20, 50]
    assert all(r["metrics"]["rgb_mean_err"] > 0 for r in refined)
    assert rep["scale_settings"]["tradeoff"]["render"]["ground_truth"]
    assert {"render: trained weights, psnr", "render: trained weights, nv_ari"} <= set(
        rep["curves"]
    )
    assert any(d["split"] == "test" for d in rep["datasets"])
    assert "generator=False" in rep["curves"]["generator"]["absent"]
    train = rep["curves"]["training"]
    assert train.get("points") or "no usable log" in train["absent"]


# ----------------------------------------------------------------------------- render curve


@pytest.mark.slow
def test_render_curve_without_a_trained_run(smoke):
    """No trained run: init weights on analytic scenes, differences against the default
    render only, PSNR / NV-ARI null with the reason."""
    _, rep = smoke
    rows = _render(rep["rows"])
    assert {r["knob"] for r in rows} == {
        "default",
        "samples_per_ray",
        "clip_to_box",
        "eval_early_stop",
        "eval_fine_min_weight",
        "combined",
    }
    assert all(r["weights"] == "init" and not r["ground_truth"] for r in rows)
    for r in rows:
        m = r["metrics"]
        assert m["render_s_per_view"] > 0 and m["speedup"] > 0
        for k in ("psnr", "nv_ari"):
            assert m[k] is None and "no ground truth used" in r["null_reasons"][k]
        assert all(m[k] is not None and m[k] >= 0 for k in ("rgb_max_err", "labels_changed"))
        if r["reference"] or r["exact_by_construction"]:
            assert m["rgb_max_err"] == 0.0 and m["labels_changed"] == 0.0
    stop = {
        r["setting"]: r["metrics"]["rgb_max_err"] for r in rows if r["knob"] == "eval_early_stop"
    }
    assert stop["0.001"] <= 2e-2 and stop["0.001"] <= stop["0.2"]
    info = rep["scale_settings"]["tradeoff"]["render"]
    assert info["weights"] == "init" and not info["ground_truth"]
    assert "init weights" in info["why_no_ground_truth"]


@pytest.mark.slow
def test_fronts_knees_and_shipped_defaults(smoke):
    _, rep = smoke
    curves = rep["curves"]
    assert set(curves) == {
        "step: init weights",
        "step: sharp-m weights",
        "render: init weights, rgb_mean_err",
        "render: init weights, labels_changed",
        "training",
        "generator",
    }
    assert "no finished benchmark run" in curves["training"]["absent"]
    by_id = {r["id"]: r for r in rep["rows"]}
    for name, c in curves.items():
        if name == "training" or "absent" in c:
            continue
        assert c["front"] and set(c["front"]) <= set(c["points"])
        assert c["knee"] is None or c["knee"] in c["front"]
        d = c["shipped_default"]
        assert d["id"] in c["points"] and d["on_front"] == (d["id"] in c["front"])
        assert d["on_front"] == (not d["dominated_by"])
        sign = -1.0 if c["y_better"] == "higher" else 1.0
        pts = [
            (i, by_id[i]["metrics"][c["x"]], sign * by_id[i]["metrics"][c["y"]])
            for i in c["points"]
        ]
        assert tradeoff.pareto_front(pts, c["timing_noise"], c["metric_eps"]) == c["front"]
        for i in c["points"]:
            assert (name in by_id[i]["on_front"]) == (i in c["front"])
    # smoke ships no speed knob: the step curves' default is the knob-free reference
    assert by_id[curves["step: init weights"]["shipped_default"]["id"]]["reference"]
    text = " ".join(rep["notes"])
    assert "Curve 'render: init weights, rgb_mean_err'" in text and "shipped default is" in text


def test_pareto_front_and_knee():
    pts = [("a", 1.0, 5.0), ("b", 2.0, 2.0), ("c", 4.0, 1.0), ("d", 3.0, 3.0), ("e", 8.0, 1.0)]
    front = tradeoff.pareto_front(pts)
    assert front == ["a", "b", "c"]  # d is dominated by b, e by c (same error, slower)
    assert tradeoff.knee_point(pts, front) == "b"
    # equal-error points within the timing noise do not dominate each other
    assert tradeoff.pareto_front([("x", 1.0, 0.0), ("y", 1.04, 0.0)], noise=0.05) == ["x", "y"]
    assert tradeoff.pareto_front([("x", 1.0, 0.0), ("y", 1.04, 0.0)]) == ["x"]
    # nor do points whose errors differ by less than eps
    assert tradeoff.pareto_front([("x", 1.0, 0.01), ("y", 1.0, 0.0)], eps=0.02) == ["y", "x"]
    assert tradeoff.knee_point([], []) is None
    line = [("a", 1.0, 3.0), ("b", 2.0, 2.5), ("c", 4.0, 1.0)]  # b above the chord: no knee
    assert tradeoff.knee_point(line, tradeoff.pareto_front(line)) is None
    c = tradeoff.curve_summary(
        [
            {"id": "p", "metrics": {"t": 1.0, "q": 20.0}},
            {"id": "q", "metrics": {"t": 2.0, "q": 30.0}},
            {"id": "r", "metrics": {"t": 3.0, "q": 25.0}},
            {"id": "s", "metrics": {"t": 0.5, "q": None}},
        ],
        "t",
        "q",
        True,
        "r",
        "",
    )
    assert c["front"] == ["p", "q"] and c["points"] == ["p", "q", "r"]
    assert c["shipped_default"] == {
        "id": "r",
        "on_front": False,
        "is_knee": False,
        "dominated_by": ["q"],
    }


def test_training_curve_from_a_run_log(tmp_path):
    """The training curve reads svorf's log.jsonl / eval.jsonl: running-best front, knee
    within 0.5 dB of the end, the budget's end as the shipped default, a figure."""
    run = tmp_path / "run"
    run.mkdir()
    lines = []
    for i in range(1, 41):
        p = 30.0 - 10.0 * math.exp(-i / 6.0) + (0.3 if i % 2 else -0.3)
        lines.append(
            json.dumps(
                {"step": 25 * i, "wall_s": 10.0 * i, "loss": 10 ** (-p / 10), "parts": {"psnr": p}}
            )
        )
    (run / "log.jsonl").write_text("\n".join(lines) + "\n{truncated")
    (run / "eval.jsonl").write_text(json.dumps({"step": 500, "wall_s": 200.0, "nv_ari": 0.5}))
    c = tradeoff.training_curve(run, "key")
    assert len(c["points"]) == 40 and c["shipped_default"]["id"] == "step 1000"
    sm = {p["id"]: p["train_psnr_smoothed"] for p in c["points"]}
    assert all(sm[a] < sm[b] for a, b in zip(c["front"], c["front"][1:]))
    end = c["points"][-1]["train_psnr_smoothed"]
    ids = [p["id"] for p in c["points"]]
    after = ids[ids.index(c["knee"]) :]
    assert all(sm[i] >= end - tradeoff.TRAIN_KNEE_DB for i in after)
    assert sm[ids[ids.index(c["knee"]) - 1]] < end - tradeoff.TRAIN_KNEE_DB
    assert c["points"][0]["wall_s"] < next(p["wall_s"] for p in c["points"] if p["id"] == c["knee"])
    assert c["held_out"] == [{"step": 500.0, "wall_s": 200.0, "nv_ari": 0.5}]
    from benchmark.figures import training_chart

    assert training_chart(tmp_path / "t.png", c) == "t.png"
    assert (tmp_path / "t.png").stat().st_size > 10_000
    assert tradeoff.training_curve(tmp_path, None) is None  # no log


def test_training_curve_names_what_beats_a_budget_end_off_the_front(tmp_path):
    """A run whose PSNR peaks before its budget ends: the last point is off the front, and
    dominated_by names the first earlier point with at least its smoothed PSNR."""
    run = tmp_path / "run"
    run.mkdir()
    psnr = [20.0 + i for i in range(20)] + [39.0 - 0.5 * i for i in range(1, 21)]
    (run / "log.jsonl").write_text(
        "\n".join(
            json.dumps({"step": i + 1, "wall_s": float(i + 1), "loss": 0.01, "parts": {"psnr": p}})
            for i, p in enumerate(psnr)
        )
    )
    c = tradeoff.training_curve(run, None)
    sd = c["shipped_default"]
    assert sd["on_front"] is False and len(sd["dominated_by"]) == 1
    sm = {p["id"]: p["train_psnr_smoothed"] for p in c["points"]}
    beat = sd["dominated_by"][0]
    assert sm[beat] >= sm[sd["id"]]
    assert all(
        sm[p["id"]] < sm[sd["id"]]
        for p in c["points"][: [q["id"] for q in c["points"]].index(beat)]
    )


def test_cached_run_steps_are_the_steps_done_not_the_limit():
    marker = {"key_source": {"train": {"steps": 1_000_000}}, "summary": {"steps": 16920}}
    assert tradeoff.steps_done(marker) == 16920
    assert tradeoff.steps_done({"key_source": {"train": {"steps": 500}}}) == 500
    assert tradeoff.steps_done({}) == 0


# ----------------------------------------------------------------------------- generator curve


@pytest.mark.slow
def test_generator_curve(smoke):
    """Seconds per view against PSNR vs a high-sample render over samples, denoiser and
    bounces (benchmark.tools.bench_quality), masks and depth identical at every point."""
    _, rep = smoke
    c = rep["curves"]["generator"]
    rows = [r for r in rep["rows"] if r["curve"] == "generator"]
    if not bpy_available():
        assert "bpy" in c["absent"] and not rows
        return
    assert {r["knob"] for r in rows} == {"default", "samples", "denoiser", "bounces"}
    assert len(rows) == len(tradeoff.GENERATOR_CANDIDATES)
    assert c["masks_and_depth_identical"] is True
    assert all(r["masks_identical"] and r["depth_identical"] for r in rows)
    ref = next(r for r in rows if r["reference"])
    assert c["shipped_default"]["id"] == ref["id"]
    assert ref["render_settings"]["samples"] == 8 and ref["render_settings"]["denoise"]
    psnr = {r["setting"]: r["metrics"]["psnr"] for r in rows}
    assert 25 < psnr["1spp+oidn"] < psnr["16spp+oidn"]  # more samples, closer to reference
    assert all(r["metrics"]["render_s_per_view"] > 0 for r in rows)
    info = rep["scale_settings"]["tradeoff"]["generator"]
    assert info["resolution"] == 32 and info["reference_samples"] == 64


def test_every_render_point_of_the_shipped_recipes_is_a_valid_config():
    """The cpu recipe clips the floor inside the box: flipping clip_to_box off must turn off
    what only exists inside it, or the point's config is refused before anything is timed."""
    from benchmark import adapter
    from benchmark.protocols.tradeoff.render import render_points

    cpu = adapter.model_config("cpu", "clevr567", "full")
    assert cpu.clip_to_box and cpu.clip_floor_z is not None  # what makes the flip non-trivial
    for scale in ("smoke", "cpu", "paper"):
        cfg = adapter.model_config(scale, "clevr567", "full")
        for p in render_points(cfg):
            flipped = cfg.replace(**p.overrides)  # raises on an invalid combination
            if p.knob == "clip_to_box":
                assert flipped.clip_to_box is not cfg.clip_to_box
    flip = next(p for p in render_points(cpu) if p.knob == "clip_to_box")
    assert flip.setting.startswith("False (") and "clip_floor_z" in flip.setting
    # Where the floor is clipped, the floor in front of the box is a point too.
    front = [p for p in render_points(cpu) if p.knob == "clip_floor_front"]
    assert [p.overrides for p in front] == [{"clip_floor_front": not cpu.clip_floor_front}]
    smoke = adapter.model_config("smoke", "clevr567", "full")
    assert smoke.clip_floor_z is None
    assert not [p for p in render_points(smoke) if p.knob == "clip_floor_front"]
