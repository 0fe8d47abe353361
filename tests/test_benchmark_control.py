"""The benchmark's scene-shuffle control (``fg_ari_shuffled``, ``fg_ari_gain``).

A model whose foreground slots tile 3D space in a fixed pattern scores a high FG-ARI
without looking at the image; the control renders each test scene with another scene's
slots. Here: the decomposition verdict's rule, the adapter's ``slots_scene`` /
``input_view_only`` passthrough on a tiny untrained model, the control in
``evaluate_model`` with an oracle, and the evaluation cache key. The end-to-end check
(control columns in a smoke report on synthetic data, schema-valid) is
``tests/test_benchmark.py::test_tiny_protocol_end_to_end_writes_json_figures_html``.
"""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from benchmark import adapter, context
from benchmark.evaluate import CONTROL_KEYS, CONTROL_REASON, evaluate_model
from benchmark.runner import Context, verdicts_for
from benchmark.scales import get_scale


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    # 2 shared cores: a second OpenMP thread waiting on a busy core slows tiny renders.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    root = tmp_path_factory.mktemp("ctrl") / "test"
    return adapter.write_synthetic_split(root, n_scenes=3, resolution=32, seed=5)


# ---------------------------------------------------------------------- verdict rule


def _rows(
    fg: float, chance: float, shuffled: float | None, ari: float = 40.0, chance_ari: float = 0.5
) -> list[dict]:
    metrics = {"fg_ari": fg, "ari": ari, "fg_ari_shuffled": shuffled}
    reasons = {} if shuffled is not None else {"fg_ari_shuffled": CONTROL_REASON}
    measured = {
        "id": "m",
        "table": "tab:seg",
        "model": "sVORF",
        "dataset": "clevr567",
        "source": "measured",
        "metrics": metrics,
        "null_reasons": reasons,
    }
    baseline = {
        "id": "b",
        "table": "tab:seg",
        "model": "chance: K image blocks (2 rows)",
        "dataset": "clevr567",
        "source": "baseline",
        "metrics": {"fg_ari": chance, "ari": chance_ari},
        "null_reasons": {},
    }
    return [measured, baseline]


def test_verdict_requires_beating_the_scene_shuffle_control():
    settings = get_scale("cpu")  # threshold 50, margin 20
    assert (settings.decompose_threshold, settings.decompose_margin) == (50.0, 20.0)

    (v,) = verdicts_for(_rows(80.0, 30.0, 78.0), settings)
    assert v["decomposes"] is False
    assert "segmentation does not depend on the scene" in v["message"]
    assert "FG-ARI 80.0 vs 78.0 with another scene's slots" in v["message"]
    assert "chance + 20" not in v["message"]  # the chance rule passed: not named as failed
    assert v["fg_ari_shuffled"] == 78.0

    (v,) = verdicts_for(_rows(80.0, 30.0, 20.0), settings)
    assert v["decomposes"] is True and v["message"].startswith("decomposes:")

    # Exactly the margin passes (same >= as against the chance baselines).
    (v,) = verdicts_for(_rows(80.0, 30.0, 60.0), settings)
    assert v["decomposes"] is True

    # Chance rule fails, control passes: only the chance condition is named.
    (v,) = verdicts_for(_rows(45.0, 30.0, 5.0), settings)
    assert v["decomposes"] is False
    assert "chance + 20" in v["message"] and "depend on the scene" not in v["message"]

    # Both fail: both named.
    (v,) = verdicts_for(_rows(45.0, 40.0, 44.0), settings)
    assert "chance + 20" in v["message"] and "depend on the scene" in v["message"]

    # Control missing while the chance rule passes: undecided, with the reason.
    (v,) = verdicts_for(_rows(80.0, 30.0, None), settings)
    assert v["decomposes"] is None and "needs_two_scenes" in v["message"]


def test_verdict_says_when_the_background_is_split_among_the_slots():
    """FG-ARI ignores background pixels: slots that each take an object and the floor
    around it pass the rule. The verdict keeps ``decomposes`` and says so."""
    settings = get_scale("cpu")
    (v,) = verdicts_for(_rows(74.1, 50.8, 48.6, ari=2.2, chance_ari=0.5), settings)
    assert v["decomposes"] is True and v["background_split"] is True
    assert "The background is not one slot: ARI 2.2" in v["message"]
    # ARI far above chance: no such sentence.
    (v,) = verdicts_for(_rows(74.1, 50.8, 48.6, ari=72.0, chance_ari=0.5), settings)
    assert v["background_split"] is False and "background" not in v["message"]
    # Exactly chance + margin is not split (the same >= as the FG-ARI rules).
    (v,) = verdicts_for(_rows(74.1, 50.8, 48.6, ari=20.5, chance_ari=0.5), settings)
    assert v["background_split"] is False
    # No ARI on the row: cannot be told.
    rows = _rows(74.1, 50.8, 48.6)
    del rows[0]["metrics"]["ari"]
    (v,) = verdicts_for(rows, settings)
    assert v["background_split"] is None and v["decomposes"] is True


def test_command_summary_and_page_name_a_split_background():
    from benchmark.cli import _verdict_lines
    from benchmark.html import _verdicts

    settings = get_scale("cpu")
    rows = _rows(74.1, 50.8, 48.6, ari=2.2, chance_ari=0.5)
    report = {"scale": "cpu", "rows": rows, "verdicts": verdicts_for(rows, settings)}
    lines = "\n".join(_verdict_lines(report))
    assert "decomposes (1 of 1)" in lines and "background is split among the slots" in lines
    assert "1 of the rows that decompose split the background" in _verdicts(report)
    rows = _rows(74.1, 50.8, 48.6, ari=72.0, chance_ari=0.5)
    report = {"scale": "cpu", "rows": rows, "verdicts": verdicts_for(rows, settings)}
    assert "background" not in "\n".join(_verdict_lines(report))
    assert "split the background" not in _verdicts(report)


# ---------------------------------------------------------------------- adapter passthrough


@pytest.fixture(scope="module")
def toy(split):
    from svorf.config import model_config
    from svorf.model import SVORF

    torch.manual_seed(0)
    model = SVORF(model_config("smoke", num_slots=4, image_size=16)).eval()
    return model, adapter.open_dataset(split, image_size=16)


def test_adapter_slots_scene_passthrough(toy):
    model, ds = toy
    base = adapter.predict_scene(model, ds, 1, input_view=0)
    assert base.labels.shape == (4, 16, 16)

    same = adapter.predict_scene(model, ds, 1, input_view=0, slots_scene=1)
    torch.testing.assert_close(same.rgb, base.rgb)
    assert torch.equal(same.labels, base.labels)

    # Only the input view: the same render as that view of the full prediction.
    one = adapter.predict_scene(model, ds, 1, input_view=2, input_view_only=True)
    full = adapter.predict_scene(model, ds, 1, input_view=2)
    assert one.labels.shape == (1, 16, 16) and one.rgb.shape == (1, 3, 16, 16)
    assert torch.equal(one.labels[0], full.labels[2])
    torch.testing.assert_close(one.rgb[0], full.rgb[2])
    torch.testing.assert_close(one.depth_z[0], full.depth_z[2])

    # Another scene's slots change the render of the same rays.
    other = adapter.predict_scene(model, ds, 1, input_view=0, slots_scene=0, input_view_only=True)
    assert not torch.allclose(other.rgb[0], base.rgb[0])
    assert not torch.equal(other.labels[0], base.labels[0])

    with pytest.raises(ValueError, match="slots_scene"):
        adapter.predict_scene(model, ds, 1, slots_scene=len(ds))


# ---------------------------------------------------------------------- evaluation


def _prediction(truth: adapter.SceneTruth, labels, input_view: int, only: bool):
    keep = slice(input_view, input_view + 1) if only else slice(None)
    return adapter.Prediction(
        rgb=truth.images[keep],
        depth_z=truth.depth_z.nan_to_num(posinf=30.0)[keep],
        labels=labels[keep],
    )


def _oracle(model, dataset, index, input_view=0, *, slots_scene=None, input_view_only=False):
    """Predicts the objects of the scene whose slots it is given (a decomposer)."""
    src = adapter.ground_truth(dataset, index if slots_scene is None else slots_scene)
    truth = adapter.ground_truth(dataset, index)
    return _prediction(truth, src.instances * 3 + 1, input_view, input_view_only)


def _tiling(model, dataset, index, input_view=0, *, slots_scene=None, input_view_only=False):
    """The same labels for every scene, whatever slots it is given (a spatial prior)."""
    truth = adapter.ground_truth(dataset, index)
    shape = truth.instances.shape
    labels = (torch.arange(shape[-1]) * 4 // shape[-1]).expand(*shape).contiguous()
    return _prediction(truth, labels, input_view, input_view_only)


def test_evaluate_model_reports_the_control(split, monkeypatch):
    ds = adapter.open_dataset(split)
    monkeypatch.setattr(adapter, "predict_scene", _oracle)
    r = evaluate_model(object(), ds)
    assert r.metrics["fg_ari"] == pytest.approx(100.0)
    assert set(CONTROL_KEYS) <= set(r.metrics)
    assert r.metrics["fg_ari_shuffled"] < 60.0  # another scene's objects
    assert r.metrics["fg_ari_gain"] == pytest.approx(
        r.metrics["fg_ari"] - r.metrics["fg_ari_shuffled"]
    )
    assert len(r.per_scene["fg_ari_shuffled"]) == 3

    monkeypatch.setattr(adapter, "predict_scene", _tiling)
    r = evaluate_model(object(), ds)
    assert r.metrics["fg_ari_shuffled"] == pytest.approx(r.metrics["fg_ari"])
    assert r.metrics["fg_ari_gain"] == pytest.approx(0.0, abs=1e-9)

    r = evaluate_model(object(), ds, max_scenes=1)
    for k in CONTROL_KEYS:
        assert r.metrics[k] is None and r.null_reasons[k] == CONTROL_REASON


def test_evaluation_cache_key_includes_the_eval_version(tmp_path, monkeypatch):
    ctx = Context("segmentation", "smoke", tmp_path, tmp_path / "data", progress=False)
    test = SimpleNamespace(fingerprint="ab" * 32)
    before = ctx._eval_dir("run", test, {})
    monkeypatch.setattr(context, "EVAL_VERSION", "older")
    assert ctx._eval_dir("run", test, {}) != before
