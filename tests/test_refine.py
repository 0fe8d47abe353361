"""Test-time slot refinement (``svorf.refine``, ``predict_scene(refine_steps=)``,
``benchmark run --refine-slots``).

The refinement fits slots alone, every network frozen: on a tiny untrained model it lowers
the photometric error of a target the model can draw (its own render from other slots),
leaves the weights, their gradients and the train/eval mode as they were, and is
reproducible. Through the benchmark it changes the prediction, gets its own evaluation
cache entry and report folder, and refuses bad values with one line. What it does to a
trained model's segmentation is measured, not tested: ``python -m benchmark.tools.refine``.
"""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import torch.nn.functional as F

from benchmark import adapter
from benchmark.cli import main as benchmark_main
from benchmark.runner import Context
from benchmark.tools.refine import refine_scene, score_views
from svorf.config import model_config
from svorf.model import SVORF
from svorf.refine import refine_slots


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _model_and_target(seed: int = 0, rays: int = 128):
    torch.manual_seed(seed)
    model = SVORF(model_config("smoke", num_slots=3)).eval()
    with torch.no_grad():
        slots = model.encode(torch.rand(1, 3, 32, 32))
        o = torch.tensor([0.0, -12.0, 6.0]).expand(rays, 3).contiguous()
        d = F.normalize(-o + 0.3 * torch.randn(rays, 3), dim=-1)
        goal = slots + 0.5 * torch.randn_like(slots)  # a target the model can draw
        target = model.render_rays(goal, o[None], d[None], need_aux=False).rgb[0]
    return model, slots, o, d, target


def _mse(model, slots, o, d, target) -> float:
    with torch.no_grad():
        return float(((model.render_rays(slots, o[None], d[None]).rgb[0] - target) ** 2).mean())


def test_refinement_fits_the_target_and_leaves_the_networks_alone():
    model, slots, o, d, target = _model_and_target()
    model.train()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    mse0 = _mse(model, slots, o, d, target)
    refined, losses = refine_slots(model, slots, o, d, target, steps=40, lr=3e-2, rays=64)
    assert refined.shape == slots.shape and not refined.requires_grad
    assert len(losses) == 40 and all(math.isfinite(x) for x in losses)
    assert _mse(model, refined, o, d, target) < 0.5 * mse0
    assert model.training  # mode restored
    for k, v in model.state_dict().items():
        assert torch.equal(v, before[k]), k
    assert all(p.grad is None and p.requires_grad for p in model.parameters())


def test_refinement_is_reproducible_and_its_seed_matters():
    model, slots, o, d, target = _model_and_target()
    a, _ = refine_slots(model, slots, o, d, target, steps=5, rays=16, seed=3)
    b, _ = refine_slots(model, slots, o, d, target, steps=5, rays=16, seed=3)
    c, _ = refine_slots(model, slots, o, d, target, steps=5, rays=16, seed=4)
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


def test_refinement_refuses_bad_arguments():
    model, slots, o, d, target = _model_and_target()
    with pytest.raises(ValueError, match="steps and rays must be >= 1"):
        refine_slots(model, slots, o, d, target, steps=0)
    with pytest.raises(ValueError, match=r"slots must be \[1, K, D\]"):
        refine_slots(model, slots.expand(2, -1, -1), o, d, target, steps=1)
    with pytest.raises(ValueError, match="must all be"):
        refine_slots(model, slots, o, d, target[:5], steps=1)
    att = SVORF(model_config("smoke", num_slots=3, slot_locality=1.0, slot_centre="attention"))
    with pytest.raises(ValueError, match="attention"):
        refine_slots(att, slots, o, d, target, steps=1)


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    root = tmp_path_factory.mktemp("refine") / "test"
    split = adapter.write_synthetic_split(root, n_scenes=2, resolution=16, seed=7)
    torch.manual_seed(0)
    model = SVORF(model_config("smoke", num_slots=3, image_size=16)).eval()
    return model, adapter.open_dataset(split, image_size=16)


def test_prediction_with_refinement(toy):
    model, ds = toy
    base = adapter.predict_scene(model, ds, 0)
    ref = adapter.predict_scene(model, ds, 0, refine_steps=3)
    again = adapter.predict_scene(model, ds, 0, refine_steps=3)
    assert ref.labels.shape == base.labels.shape
    assert not torch.allclose(ref.rgb, base.rgb)
    torch.testing.assert_close(ref.rgb, again.rgb)  # reproducible
    # The control's slots are refined on their own scene's view, then moved.
    ctrl = adapter.predict_scene(model, ds, 0, slots_scene=1, input_view_only=True, refine_steps=3)
    assert ctrl.labels.shape == (1, *base.labels.shape[1:])
    # The rate reaches the refinement: None is svorf's default, another rate another render.
    same = adapter.predict_scene(
        model, ds, 0, refine_steps=3, refine_lr=adapter.default_refine_lr()
    )
    torch.testing.assert_close(ref.rgb, same.rgb)
    slow = adapter.predict_scene(model, ds, 0, refine_steps=3, refine_lr=1e-4)
    assert not torch.allclose(slow.rgb, ref.rgb)


def test_the_diagnostic_scores_both_slot_sets(toy):
    model, ds = toy
    enc, ref, losses = refine_scene(model, ds[0], fit="all", steps=3, rays=32)
    assert len(losses) == 3 and not torch.equal(enc, ref)
    s = score_views(model, ds[0], ref)
    assert {"ari", "fg_ari", "bleed_fraction", "psnr", "nv_ari", "nv_psnr"} <= set(s)
    with pytest.raises(ValueError, match="fit must be"):
        refine_scene(model, ds[0], fit="novel")


def test_context_keys_and_folders(tmp_path):
    off = Context("segmentation", "smoke", tmp_path, tmp_path / "data", progress=False)
    on = Context(
        "segmentation", "smoke", tmp_path, tmp_path / "data", progress=False, refine_slots=20
    )
    test = SimpleNamespace(fingerprint="cd" * 32)
    rec = SimpleNamespace(key="run")
    assert off.eval_dir(rec, test) != on.eval_dir(rec, test)
    # The chance baselines do not depend on the model's inference: one cache entry.
    assert off._eval_dir("baselines", test, {}) == on._eval_dir("baselines", test, {})
    assert on.report_dir.name == "segmentation-smoke-refine20"
    assert off.report_dir.name == "segmentation-smoke"
    assert on.base_report()["scale_settings"]["refine_slots"] == 20
    with pytest.raises(ValueError, match="--refine-slots must be a whole number >= 0"):
        Context("segmentation", "smoke", tmp_path, tmp_path, progress=False, refine_slots=-1)
    # The rate: svorf's by default and recorded; another rate has its own folder and cache.
    default = adapter.default_refine_lr()
    assert off.refine_lr is None and on.refine_lr == default
    assert on.base_report()["scale_settings"]["refine_lr"] == default
    other = Context(
        "segmentation", "smoke", tmp_path, tmp_path, progress=False, refine_slots=20, refine_lr=0.5
    )
    assert other.report_dir.name == "segmentation-smoke-refine20-lr0.5"
    assert other.eval_dir(rec, test) not in (on.eval_dir(rec, test), off.eval_dir(rec, test))
    # At the rate every earlier refined report used, the cache key is the one they wrote.
    old = Context(
        "segmentation",
        "smoke",
        tmp_path,
        tmp_path,
        progress=False,
        refine_slots=20,
        refine_lr=adapter.REFINE_LR_UNRECORDED,
    )
    assert old.refine_context() == {"refine_slots": 20}
    assert old.eval_dir(rec, test) == on._eval_dir("run", test, {"refine_slots": 20})
    for bad, needle in ((0.0, "positive number"), (float("nan"), "positive number")):
        with pytest.raises(ValueError, match=needle):
            Context(
                "segmentation",
                "smoke",
                tmp_path,
                tmp_path,
                progress=False,
                refine_slots=2,
                refine_lr=bad,
            )
    with pytest.raises(ValueError, match="pass that too"):
        Context("segmentation", "smoke", tmp_path, tmp_path, progress=False, refine_lr=0.01)


def test_the_help_texts_name_the_default_rate():
    from svorf.cli import REFINE_LR_HELP
    from svorf.refine import REFINE_LR

    assert REFINE_LR_HELP == REFINE_LR == adapter.default_refine_lr()
    import benchmark.cli

    assert f"svorf's, {REFINE_LR:g}" in Path(benchmark.cli.__file__).read_text()


def test_cli_refuses_refinement_outside_the_tables(tmp_path, capsys):
    code = benchmark_main(["run", "speed", "--refine-slots", "5", "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert "--refine-slots applies to the table protocols" in err
    code = benchmark_main(
        ["run", "segmentation", "--refine-lr", "0.01", "--out", str(tmp_path), "--no-train"]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "pass that too" in err


def test_module_example_runs():
    import doctest

    import svorf.refine as refine_mod

    assert doctest.testmod(refine_mod).failed == 0


def test_leaderboard_keeps_refined_rows_apart(tmp_path):
    from test_benchmark import _good_report  # tests/ is on the path (rootdir, no package)

    from benchmark.leaderboard import format_leaderboard, merge_reports
    from benchmark.report import write_report

    plain = _good_report(created="2025-01-01T00:00:00Z")
    refined = _good_report(created="2025-02-01T00:00:00Z")
    for rep in (plain, refined):
        rep["scale_settings"]["train_steps_override"] = 25000
    refined["scale_settings"]["refine_slots"] = 50
    faster = _good_report(created="2025-03-01T00:00:00Z")
    faster["scale_settings"].update(train_steps_override=25000, refine_slots=50, refine_lr=0.02)
    write_report(tmp_path / "a" / "report.json", plain)
    write_report(tmp_path / "b" / "report.json", refined)
    write_report(tmp_path / "c" / "report.json", faster)
    board = merge_reports(tmp_path)
    budgets = sorted(str(e["budget"]) for e in board["entries"] if e["source"] == "measured")
    # A refined report without a rate (written before it was recorded) refined at 3e-3.
    assert budgets == [
        "25000 steps",
        "25000 steps + refine 50 at lr 0.003",
        "25000 steps + refine 50 at lr 0.02",
    ]
    assert "smoke seed 0, 25000 steps + refine 50 at lr 0.02" in format_leaderboard(board)
