"""The ``speed`` protocol's parts: the uORF-style configuration of the same code,
the ratio row against the paper's and the target ratios, options, the generator rows
without Blender, and the schema of the new metrics. Fast tier: no training, no Blender
(the full protocol at smoke scale is ``tests/test_benchmark.py::
test_speed_protocol_on_synthetic_data``, slow tier).
"""

from __future__ import annotations

import copy

import pytest
import torch

from benchmark import adapter
from benchmark.protocols import speed
from benchmark.protocols.speed import generator as speed_generator
from benchmark.protocols.speed import worker
from benchmark.report import new_report
from benchmark.runner import Context
from benchmark.schema import METRIC_UNITS, check_report


@pytest.fixture(autouse=True)
def _restore_ray_sampling_registry():
    """``uorf_style`` registers ``full_image`` (meant for the worker process): undo it here."""
    from svorf.data import RAY_SAMPLING

    before = dict(RAY_SAMPLING)
    yield
    RAY_SAMPLING.clear()
    RAY_SAMPLING.update(before)


def test_full_image_rays_cover_one_view_exactly():
    rgb = torch.zeros(3, 4, 5, 3)
    gen = torch.Generator().manual_seed(0)
    for _ in range(5):
        idx = worker.full_image_rays(rgb, 20, gen)
        assert idx.dtype == torch.long and idx.shape == (20,)
        view = int(idx[0]) // 20
        assert 0 <= view < 3
        assert torch.equal(idx, view * 20 + torch.arange(20))  # every pixel once, in order
    with pytest.raises(ValueError, match="H\\*W = 20"):
        worker.full_image_rays(rgb, 64, gen)


def test_uorf_style_changes_only_what_the_issue_names():
    mcfg = adapter.model_config("smoke", "clevr567")
    tcfg = adapter.train_config("smoke", "clevr567", "full", 0, "cpu")
    um, ut = worker.uorf_style(mcfg, tcfg)
    assert um.composition == "density_weighted" and um.hypernetwork is False
    changed = {k for k, v in um.to_dict().items() if mcfg.to_dict()[k] != v}
    assert changed == {"composition", "hypernetwork"}
    assert ut.rays_per_scene == mcfg.image_size**2 and ut.ray_sampling == worker.FULL_IMAGE
    changed = {k for k, v in ut.to_dict().items() if tcfg.to_dict()[k] != v}
    assert changed == {"rays_per_scene", "ray_sampling"}  # same batch, lr, steps, ...
    worker.uorf_style(mcfg, tcfg)  # registering twice is harmless


def test_uorf_style_trains_a_full_image_step(tmp_path):
    """One step of each configuration through svorf's own training loop."""
    data = adapter.write_synthetic_split(tmp_path / "train", n_scenes=2, resolution=16, seed=0)
    mcfg = adapter.model_config("smoke", "clevr567", image_size=16)
    tcfg = adapter.train_config("smoke", "clevr567", "full", 0, "cpu", steps=1)
    tcfg = tcfg.replace(batch_scenes=1, log_every=1)
    um, ut = worker.uorf_style(mcfg, tcfg)
    out = adapter.train(data, tmp_path / "run", um, ut, progress=False)
    assert out["steps"] == 1 and out["final_loss"] is not None
    assert worker._step_times(tmp_path / "run" / "log.jsonl", 0)


def _side(model: str, step, peak, train_mem, n=6, tensor=None):
    metrics = {
        "step_time_s": step,
        "peak_memory_mb": peak,
        "train_memory_mb": train_mem,
        "tensor_peak_mb": tensor,
    }
    return {
        "model": model,
        "metrics": metrics,
        "null_reasons": {k: "out_of_memory" for k, v in metrics.items() if v is None},
        "n_cases": n,
    }


def test_ratio_row_values_targets_and_nulls():
    row = speed.ratio_row(
        _side("a", 0.1, 500.0, 100.0, tensor=60.0), _side("b", 0.4, 1000.0, 800.0, tensor=330.0)
    )
    m = row["metrics"]
    assert m == {
        "step_time_ratio": 4.0,
        "memory_ratio": 2.0,
        "train_memory_ratio": 8.0,
        "tensor_memory_ratio": 5.5,
    }
    assert row["target_met"] == {
        "step_time_ratio": True,
        "memory_ratio": False,
        "tensor_memory_ratio": True,
    }
    assert row["paper"] == {
        "step_time_ratio": 2.559,
        "memory_ratio": 5.13,
        "tensor_memory_ratio": 5.13,
    }
    assert row["targets"] == {
        "step_time_ratio": 3.0,
        "memory_ratio": 5.0,
        "tensor_memory_ratio": 5.0,
    }
    assert row["source"] == "measured" and row["null_reasons"] == {}
    # the uORF-style side did not fit: ratios null with the side's reason, target unknown
    row = speed.ratio_row(_side("a", 0.1, 500.0, 100.0), _side("b", None, None, None, n=0))
    assert all(v is None for v in row["metrics"].values())
    assert "out_of_memory" in row["null_reasons"]["memory_ratio"]
    assert row["target_met"] == {
        "step_time_ratio": None,
        "memory_ratio": None,
        "tensor_memory_ratio": None,
    }
    assert row["n_cases"] == 0


def test_compare_rows_take_medians_and_report_failed_repeats():
    ok = {
        "step_times_s": [0.3, 0.1, 0.2],
        "peak_memory_mb": 400.0,
        "train_memory_mb": 50.0,
        "batch_scenes": 1,
        "rays_per_scene": 64,
    }
    ok2 = {**ok, "step_times_s": [0.4, 0.5], "peak_memory_mb": 600.0, "train_memory_mb": 70.0}
    row = speed.compare_row("x", "svorf", [ok, ok2], [])
    assert row["metrics"]["step_time_s"] == 0.3 and row["n_cases"] == 5
    assert row["metrics"]["peak_memory_mb"] == 500.0 and row["repeats"] == 2
    oom = {"error": "out_of_memory", "message": "can't allocate"}
    row = speed.compare_row("y", "uorf", [oom], ["out_of_memory (limit 10 MiB): x"])
    assert row["n_cases"] == 0 and row["repeats_failed"] == 1
    assert all(v is None for v in row["metrics"].values())
    assert row["null_reasons"]["step_time_s"].startswith("out_of_memory")


def test_speed_options_validate_and_defaults():
    assert speed.default_options("smoke").compare_repeats == 1
    assert speed.default_options("cpu").compare_batches == (1, None)
    with pytest.raises(ValueError, match="compare_batches"):
        speed.SpeedOptions(compare_batches=())
    with pytest.raises(ValueError, match="compare_batches"):
        speed.SpeedOptions(compare_batches=(1, 0))
    with pytest.raises(ValueError, match="compare_repeats"):
        speed.SpeedOptions(compare_repeats=0)
    with pytest.raises(ValueError, match="memory_fraction"):
        speed.SpeedOptions(memory_fraction=0.0)
    with pytest.raises(ValueError, match="gen_workers"):
        speed.SpeedOptions(gen_workers=())
    assert speed.SpeedOptions().to_dict()["gen_workers"] == [1, 2]


def test_generator_rows_null_with_reason_without_generator(tmp_path):
    ctx = Context("speed", "smoke", tmp_path / "r", tmp_path / "d", data_source="synthetic")
    rows = speed.generator_rows(ctx, speed.default_options("smoke"))
    assert len(rows) == 1 and rows[0]["n_cases"] == 0
    assert all(v is None for v in rows[0]["metrics"].values())
    assert "synthetic" in rows[0]["null_reasons"]["overhead_ratio"]
    import dataclasses

    off = dataclasses.replace(speed.default_options("smoke"), generator=False)
    assert "switched off" in speed.generator_rows(ctx, off)[0]["null_reasons"]["s_per_view"]


def _fake_compare(speedup: float, psnr: float, base_psnr: float, exact: bool = True):
    """What ``bench_baseline.compare`` returns, with chosen numbers (the real run is
    ``tests/test_bench_baseline.py``)."""

    def compare(options, denoiser, out_root):
        views = options.baseline_scenes * 4
        dn = "ACCURATE" if denoiser == "factory" else "FAST"
        return {
            "generate": {"wall_s": 10.0, "s_per_view": 10.0 / views, "psnr_db": psnr},
            "naive": {"wall_s": 10.0 * speedup, "s_per_view": 10.0 * speedup / views,
                      "psnr_db": base_psnr},
            "speedup": speedup, "masks_identical": exact, "depth_identical": True,
            "load_before": [0.1, 0.2, 0.3], "load_after": [0.4, 0.5, 0.6],
            "settings": {"split": "train", "n_scenes": options.baseline_scenes, "views": views,
                         "resolution": options.baseline_resolution, "psnr_scenes": 1,
                         "generate": {"render": {"samples": 8}},
                         "naive": {"threads": 2, "denoiser": {"denoising_prefilter": dn,
                                                              "denoising_quality": "HIGH"}},
                         "reference": {"samples": 512}},
        }  # fmt: skip

    return compare


@pytest.mark.parametrize(
    ("speedup", "psnr", "base_psnr", "exact", "met"),
    [(2.0, 45.0, 44.4, True, True), (1.4, 45.0, 44.4, True, False),
     (2.0, 44.0, 44.4, True, False), (2.0, 45.0, 44.4, False, False)],
)  # fmt: skip
def test_baseline_rows_target_needs_speed_equal_psnr_and_exact_masks(
    tmp_path, monkeypatch, speedup, psnr, base_psnr, exact, met
):
    ctx = Context("speed", "cpu", tmp_path / "r", tmp_path / "d", data_source="generator")
    monkeypatch.setattr(speed_generator, "_generator_unavailable", lambda ctx, options: None)
    monkeypatch.setattr(
        speed_generator, "_compare_with_script", _fake_compare(speedup, psnr, base_psnr, exact)
    )
    opts = speed.default_options("cpu")
    assert opts.baseline_denoisers == ("factory", "tuned") and opts.baseline_resolution == 128
    rows = speed.baseline_rows(ctx, opts)
    assert [r["variant"] for r in rows] == ["factory", "tuned"]
    assert len({r["id"] for r in rows}) == 2
    for r in rows:
        assert r["table"] == "speed_generator" and r["n_cases"] == 80
        assert r["metrics"]["baseline_speedup"] == speedup
        assert r["metrics"]["psnr"] == psnr and r["metrics"]["baseline_psnr"] == base_psnr
    # the target is against the factory script; the tuned one is a control
    assert rows[0]["target"] == 1.5 and rows[0]["target_met"] is met
    assert rows[1]["target"] is None and rows[1]["target_met"] is None
    assert "ACCURATE" in rows[0]["note"] and "FAST" in rows[1]["note"]
    note = speed.baseline_note(rows[0])
    assert f"{speedup:.2f}x" in note and note.endswith("met")
    assert ("NOT met" in note) is (not met)
    assert "no target" in speed.baseline_note(rows[1])
    rep = new_report("speed", "cpu", "cpu")
    rep["rows"] = rows
    assert [p for p in check_report(rep) if "rows" in p] == []


def test_baseline_rows_null_with_reason_without_generator(tmp_path):
    ctx = Context("speed", "smoke", tmp_path / "r", tmp_path / "d", data_source="synthetic")
    rows = speed.baseline_rows(ctx, speed.default_options("smoke"))
    assert [r["variant"] for r in rows] == ["factory"] and rows[0]["n_cases"] == 0
    assert all(v is None for v in rows[0]["metrics"].values()) and rows[0]["target_met"] is None
    assert "synthetic" in rows[0]["null_reasons"]["baseline_speedup"]
    assert "null (" in speed.baseline_note(rows[0])
    with pytest.raises(ValueError, match="baseline_denoisers"):
        speed.SpeedOptions(baseline_denoisers=("nope",))
    with pytest.raises(ValueError, match="baseline_psnr_scenes"):
        speed.SpeedOptions(baseline_scenes=1, baseline_psnr_scenes=2)


def test_code_fingerprint_follows_the_measured_sources(tmp_path, monkeypatch):
    """Cached speed rows are keyed on the measured code: a change to it changes the key."""
    import shutil
    from pathlib import Path

    fp = speed.code_fingerprint()
    assert len(fp) == 16 and fp == speed.code_fingerprint()  # stable
    orig = speed.code_fingerprint(("svorf",))
    assert orig != speed.code_fingerprint(("generators",))
    # the same sources elsewhere give the same fingerprint; one changed byte another
    repo = Path(speed.__file__).resolve().parents[3]
    fake = tmp_path / "benchmark" / "protocols" / "speed"
    fake.mkdir(parents=True)
    shutil.copytree(repo / "svorf", tmp_path / "svorf")
    shutil.copy(speed.__file__, fake / "__init__.py")
    monkeypatch.setattr(speed, "__file__", str(fake / "__init__.py"))
    assert speed.code_fingerprint(("svorf",)) == orig
    f = tmp_path / "svorf" / "model.py"
    f.write_text(f.read_text() + "\n# changed\n")
    assert speed.code_fingerprint(("svorf",)) != orig


def test_new_speed_rows_pass_the_schema():
    for name in (
        "train_memory_mb",
        "step_time_ratio",
        "memory_ratio",
        "train_memory_ratio",
        "tensor_peak_mb",
        "tensor_memory_ratio",
        "images_per_s",
        "s_per_view",
        "overhead_ratio",
        "scaling_speedup",
    ):
        assert name in METRIC_UNITS
    a, b = _side("a", 0.1, 500.0, 100.0), _side("b", 0.4, 1000.0, None)
    rows = []
    for r in (a, b):
        r = copy.deepcopy(r)
        r.update(
            id=f"speed_vs_uorf|{r['model']}|clevr567|measured",
            table="speed_vs_uorf",
            dataset="clevr567",
            source="measured",
        )
        rows.append(r)
    rows.append(speed.ratio_row(rows[0], rows[1]))
    rep = new_report("speed", "smoke", "cpu")
    rep["rows"] = rows
    problems = [p for p in check_report(rep) if "rows" in p]
    assert problems == []


def test_tensor_memory_curve_closed_form():
    mib = 2**20
    # (time, bytes): 2 MiB set-up freed before the start, then a step that holds 3 MiB at once
    events = [(0, 2 * mib), (1, -2 * mib), (2, 1 * mib), (5, 2 * mib), (6, -2 * mib), (3, mib)]
    out = worker.tensor_memory_curve(events, start_ns=3)
    # live at t=3 (before its event): 1 MiB; then 2, 4, 2 -> peak 4, added 3
    assert out == {"tensor_peak_mb": 4.0, "tensor_train_mb": 3.0}
    # no start: the whole call counts from zero
    assert worker.tensor_memory_curve(events, None) == {
        "tensor_peak_mb": 4.0,
        "tensor_train_mb": 4.0,
    }
    # a start after every event: nothing happened during training
    assert worker.tensor_memory_curve(events, 10) == {
        "tensor_peak_mb": 2.0,
        "tensor_train_mb": 0.0,
    }


def test_profiled_tensor_memory_sees_a_real_training_step(tmp_path):
    """The CPU measure on a real (smoke) training call: the first step's activations and
    gradients are counted, and a known extra allocation in the step moves the peak."""
    data = adapter.write_synthetic_split(tmp_path / "train", n_scenes=2, resolution=16, seed=0)
    mcfg = adapter.model_config("smoke", "clevr567", image_size=16)
    tcfg = adapter.train_config("smoke", "clevr567", "full", 0, "cpu", steps=1)
    tcfg = tcfg.replace(batch_scenes=1, log_every=1)
    out = worker._profiled_tensor_memory(adapter, str(data), tmp_path / "run", mcfg, tcfg)
    from svorf.model import SVORF

    params_mb = sum(p.numel() * 4 for p in SVORF(mcfg).parameters()) / 2**20
    # the peak holds at least the weights and their gradients
    assert out["tensor_peak_mb"] >= 2 * params_mb
    assert 0.0 < out["tensor_train_mb"] <= out["tensor_peak_mb"]

    extra = 64 * 2**20  # 64 MiB held across one module's forward during the step
    held = []

    def hook(module, args):
        if not held:
            held.append(torch.empty(extra, dtype=torch.uint8))

    def release(module, args, output):
        held.clear()

    h1 = torch.nn.modules.module.register_module_forward_pre_hook(hook)
    h2 = torch.nn.modules.module.register_module_forward_hook(release)
    try:
        big = worker._profiled_tensor_memory(adapter, str(data), tmp_path / "run2", mcfg, tcfg)
    finally:
        h1.remove()
        h2.remove()
    assert big["tensor_peak_mb"] >= 64.0
