"""Tests of the benchmark's run-size controls: ``--datasets``, ``--train-minutes``, reuse of
existing splits, and where the cpu scale takes its configs from.

All on tiny ``smoke``-scale data (``svorf.synthetic`` splits, or synthetic splits whose
manifest is rewritten to look like a generator split); about half a minute in all.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmark import adapter
from benchmark.cli import main as cli_main
from benchmark.datasets import ensure_dataset
from benchmark.paper_numbers import PAPER_TABLES
from benchmark.runner import Context, MeasuredRow, ModelJob, run_table_protocol
from benchmark.scales import get_scale
from benchmark.schema import validate_report


def _run(tmp: Path, *extra: str, protocol: str = "segmentation") -> int:
    return cli_main(
        [
            "run",
            protocol,
            "--scale",
            "smoke",
            "--out",
            str(tmp / "reports"),
            "--data",
            str(tmp / "data"),
            "--data-source",
            "synthetic",
            "--no-progress",
            *extra,
        ]
    )


def _report(tmp: Path, protocol: str = "segmentation") -> dict:
    report = json.loads((tmp / "reports" / f"{protocol}-smoke" / "report.json").read_text())
    validate_report(report)
    return report


def test_datasets_filter_keeps_only_the_named_dataset_and_says_what_it_left_out(tmp_path):
    assert _run(tmp_path, "--datasets", "clevr567", "--steps", "2") == 0
    report = _report(tmp_path)
    assert {r["dataset"] for r in report["rows"]} == {"clevr567"}
    measured = [r for r in report["rows"] if r["source"] == "measured"]
    assert [r["model"] for r in measured] == ["sVORF"]
    paper = {r["model"] for r in report["rows"] if r["source"] == "paper"}
    want = {r["model"] for r in PAPER_TABLES["tab:seg"]["rows"] if r["dataset"] == "clevr567"}
    assert paper == want and len(want) == 4
    assert any(r["source"] == "baseline" for r in report["rows"])
    assert {d["preset"] for d in report["datasets"]} == {"clevr567"}  # nothing else was made
    (note,) = [n for n in report["notes"] if "left out by --datasets" in n]
    assert "room-chair" in note and "room-diverse" in note
    assert report["scale_settings"]["only_datasets"] == ["clevr567"]
    # smoke keeps svorf's plain scale configs (the cpu recipe is for --scale cpu only)
    (model,) = report["models"]
    assert model["config_source"] == "svorf.train.run_configs"
    assert model["steps_done"] == 2 and model["train_budget"]["stopped_by"] == "steps"
    assert model["weights_scored"] == "raw"  # no ema_decay at smoke: the optimizer's weights


@pytest.mark.parametrize(
    "args, needle",
    [
        (("--datasets", "clevr999"), "choose from clevr567, room-chair, room-diverse"),
        (("--datasets", ","), "(none given)"),
        (("--train-minutes", "0"), "--train-minutes must be a positive number"),
    ],
)
def test_bad_filter_or_budget_is_a_one_line_error_before_any_work(tmp_path, capsys, args, needle):
    assert _run(tmp_path, *args) == 2
    err = capsys.readouterr().err
    assert needle in err and err.count("\n") == 1 and err.startswith("benchmark: error:")
    assert not (tmp_path / "data").exists()  # no dataset was generated


def test_filter_and_budget_are_refused_for_protocols_without_a_dataset_axis(tmp_path, capsys):
    assert _run(tmp_path, "--datasets", "clevr567", protocol="stability") == 2
    assert "applies to the protocols that train models" in capsys.readouterr().err


def test_train_minutes_stops_on_the_budget_is_in_the_cache_key_and_the_report(
    tmp_path, monkeypatch
):
    # 0.05 min = 3 s of training wall time and no --steps: the budget alone stops the run.
    assert _run(tmp_path, "--datasets", "clevr567", "--train-minutes", "0.05") == 0
    report = _report(tmp_path)
    assert report["scale_settings"]["train_minutes"] == 0.05
    (model,) = report["models"]
    budget = model["train_budget"]
    assert budget["max_wall_s"] == pytest.approx(3.0) and budget["minutes"] == 0.05
    assert budget["stopped_by"] == "time_budget"
    assert 1 <= budget["steps_done"] < budget["step_limit"]
    assert budget["train_wall_s"] >= 3.0 and model["train_wall_s"] >= 3.0
    assert any(n.startswith("Training budget: 0.05 min") for n in report["notes"])
    marker = json.loads((Path(model["run_dir"]) / "benchmark_run.json").read_text())
    assert marker["key_source"]["train_budget_s"] == pytest.approx(3.0)

    # Another budget (or none) is another model; the same budget reuses the run.
    def key(minutes):
        ctx = Context(
            "segmentation",
            "smoke",
            tmp_path / "reports",
            tmp_path / "data",
            data_source="synthetic",
            progress=False,
            train_minutes=minutes,
        )
        return ctx.model_key(ModelJob("full", "clevr567"))[0]

    assert key(0.05) == model["run_key"]
    assert len({key(0.05), key(0.1), key(None)}) == 3

    def no_training(*a, **k):
        raise AssertionError("the finished budgeted run must be reused")

    monkeypatch.setattr(adapter, "train", no_training)
    assert _run(tmp_path, "--datasets", "clevr567", "--train-minutes", "0.05") == 0
    assert all(m["reused"] for m in _report(tmp_path)["models"])


def test_an_interrupted_budgeted_run_resumes_and_counts_the_time_already_trained(tmp_path):
    ctx = Context(
        "segmentation",
        "smoke",
        tmp_path / "reports",
        tmp_path / "data",
        data_source="synthetic",
        progress=False,
        train_minutes=0.03,
    )
    job = ModelJob("full", "clevr567")
    ds = ctx.dataset("clevr567", "train")
    mcfg, tcfg = ctx.configs(job)
    run_dir = tmp_path / "run"
    first = adapter.train(ds.path, run_dir, mcfg, tcfg, progress=False, max_wall_s=0.9)
    # "killed" by the budget after ~1 s, long before its step limit
    assert 1 <= first["steps"] < tcfg.steps and first["train_wall_s"] >= 0.9 - 1e-3
    # The second budget is relative to what the first call took (a loaded machine can make
    # one step longer than a fixed second budget).
    budget = first["train_wall_s"] + 0.9
    second = adapter.train(ds.path, run_dir, mcfg, tcfg, progress=False, max_wall_s=budget)
    assert second["start_step"] == first["steps"] and second["steps"] > first["steps"]
    # train_wall_s is reported rounded to 1 ms: compare with that resolution.
    assert second["train_wall_s"] >= budget - 1e-3
    assert second["wall_s"] < second["train_wall_s"]


def _fake_generator_split(root: Path, n: int, samples: int) -> None:
    """A synthetic split whose manifest claims a generator render with ``samples`` spp."""
    adapter.write_synthetic_split(
        root, n_scenes=n, resolution=32, seed=7, preset="clevr567", split=root.name
    )
    m = json.loads((root / "manifest.json").read_text())
    m.update(generator="generators 0.1.0", seed=0)
    m["render"] = {"samples": samples, "denoise": False}
    (root / "manifest.json").write_text(json.dumps(m))


def test_an_existing_split_with_other_render_settings_is_used_as_found_and_reported(
    tmp_path, monkeypatch
):
    from benchmark import datasets

    made = []
    monkeypatch.setattr(datasets, "_run_generator", lambda *a, **k: made.append(a))
    verified = []
    monkeypatch.setattr(datasets, "_verify", verified.append)  # the synthetic floor is finite
    data = tmp_path / "data"
    _fake_generator_split(data / "smoke" / "clevr567" / "train", 3, samples=8)  # nominal 4 x 1
    _fake_generator_split(data / "smoke" / "clevr567" / "test", 1, samples=8)  # nominal 2 x 1
    ctx = Context(
        "segmentation", "smoke", tmp_path / "reports", data, progress=False, train_steps=1
    )
    row = MeasuredRow("tab:seg", "sVORF", "clevr567", ModelJob("full", "clevr567"), ("fg_ari",))
    report = json.loads(run_table_protocol(ctx, ["tab:seg"], [row], None).read_text())
    assert not made  # the generator cannot extend them (other spp): nothing rendered
    assert len(verified) == 2
    by_split = {d["split"]: d for d in report["datasets"]}
    test = by_split["test"]
    assert test["n_scenes"] == 1 and test["render_samples"] == 8
    assert test["nominal"]["n_scenes"] == 2 and test["nominal"]["render_samples"] == 1
    assert test["deviations"] == ["1 scenes (nominal 2)", "8 render samples (nominal 1)"]
    assert by_split["train"]["deviations"] == [
        "3 scenes (nominal 4)",
        "8 render samples (nominal 1)",
    ]
    notes = [n for n in report["notes"] if "used as found" in n]
    assert len(notes) == 2 and "delete the folder" in notes[0]
    (measured,) = [r for r in report["rows"] if r["source"] == "measured"]
    assert measured["n_scenes"] == 1

    # Same render settings but fewer scenes: the generator is asked to extend it.
    extend = tmp_path / "ext"
    _fake_generator_split(extend / "smoke" / "clevr567" / "test", 1, samples=1)
    with pytest.raises(RuntimeError, match="still incomplete"):  # the stub renders nothing
        ensure_dataset(extend, get_scale("smoke"), "clevr567", "test", source="generator")
    assert made and made[0][3] == 2


def test_cpu_scale_takes_the_recipe_for_the_clevr_family_only():
    from benchmark.tools.recipe import recipe_configs
    from svorf.train import run_configs

    rm, rt = recipe_configs("clevr567")
    assert adapter.model_config("cpu", "clevr567", "full") == rm
    assert adapter.train_config("cpu", "clevr567", "full", 3, "cpu") == rt.replace(
        seed=3, device="cpu"
    )
    # ablation variants on top of the recipe
    assert adapter.model_config("cpu", "clevr567", "wo_sa") == rm.replace(self_attention=False)
    pm, _ = recipe_configs("packed-clevr11")
    # The packed setting: 11 slots; the cpu recipe masks none in training, the paper 4.
    assert adapter.model_config("cpu", "clevr567", "packed11") == pm
    assert (pm.num_slots, pm.slot_mask_train) == (11, 0)
    assert pm == rm.replace(num_slots=11)
    paper = adapter.model_config("paper", "clevr567", "packed11")
    assert (paper.num_slots, paper.slot_mask_train) == (11, 4)
    assert adapter.config_source("cpu", "clevr567-heldout") == adapter.RECIPE_CONFIG_SOURCE
    # Room-Chair at cpu gets the recipe too; Room-Diverse at cpu, and smoke / paper
    # everywhere, keep svorf's scale configs.
    assert adapter.config_source("cpu", "room-chair") == adapter.RECIPE_CONFIG_SOURCE
    assert adapter.model_config("cpu", "room-chair") == run_configs("cpu", "room-chair")[0]
    assert adapter.config_source("cpu", "room-diverse") == "svorf.train.run_configs"
    for scale in ("smoke", "paper"):
        assert adapter.model_config(scale, "clevr567") == run_configs(scale, "clevr567")[0]
        assert adapter.config_source(scale, "clevr567") == "svorf.train.run_configs"


def test_a_cpu_report_says_its_models_train_with_the_cpu_recipe(tmp_path):
    from benchmark.datasets import DatasetInfo
    from benchmark.paper_numbers import paper_rows
    from benchmark.runner import ModelRecord

    ctx = Context("segmentation", "cpu", tmp_path, tmp_path / "data", progress=False)
    ds = DatasetInfo(
        "clevr567/train", "clevr567", "train", tmp_path, "ab" * 32, 240, 4, 64, "generator",
        False, 0.0, deviations=("8 render samples (nominal 16)",),
    )  # fmt: skip
    job = ModelJob("full", "clevr567")
    mcfg, tcfg = ctx.configs(job)
    ctx.models["k"] = ModelRecord(
        "k", tmp_path / "run", job, ds, adapter.config_dict(mcfg), adapter.config_dict(tcfg),
        0, False, 60.0, {"steps": 100}, adapter.config_source("cpu", "clevr567"), None,
    )  # fmt: skip
    ctx.datasets[("clevr567", "train")] = ds
    report = ctx.base_report()
    report.update(rows=paper_rows("tab:seg"), verdicts=[], figures=[])
    report = json.loads(ctx.finish(report).read_text())
    assert any("cpu recipe" in n and "docs/notes/cpu_recipe.md" in n for n in report["notes"])
    assert any("8 render samples (nominal 16)" in n for n in report["notes"])
    assert report["models"][0]["config_source"] == adapter.RECIPE_CONFIG_SOURCE


def test_a_model_that_asks_for_finer_targets_trains_on_its_own_finer_split(tmp_path, monkeypatch):
    """TrainConfig.target_size above the scale's resolution: the benchmark makes the
    training split at that resolution in a folder of its own (``<scale>-<res>px``), trains
    on it, and evaluates on the scale's test split as always; the report lists both."""
    plain = adapter.train_config
    monkeypatch.setattr(
        adapter, "train_config", lambda *a, **k: plain(*a, **k).replace(target_size=64)
    )
    assert _run(tmp_path, "--datasets", "clevr567", "--steps", "2") == 0
    report = _report(tmp_path)
    splits = {(d["split"], d["resolution"]): Path(d["path"]) for d in report["datasets"]}
    assert set(splits) == {("train", 64), ("test", 32)}
    assert splits["train", 64].parent.parent.name == "smoke-64px"
    assert splits["test", 32].parent.parent.name == "smoke"
    assert not (tmp_path / "data" / "smoke" / "clevr567" / "train").exists()
    (model,) = report["models"]
    assert model["steps_done"] == 2
    measured = [r for r in report["rows"] if r["source"] == "measured"]
    assert measured and all(r["metrics"]["fg_ari"] is not None for r in measured)


def test_a_finished_run_of_another_training_preset_is_not_taken_for_a_cached_run(tmp_path):
    # CLEVR-567 and its held-out-appearance twin train with the same settings; only the
    # marker's job says which split a run was trained on, and a run trained on one must
    # not make a --no-train pass render the other's training split to look for it.
    ctx = Context(
        "generalization",
        "smoke",
        tmp_path / "reports",
        tmp_path / "data",
        data_source="synthetic",
        progress=False,
    )
    clevr, heldout = ModelJob("full", "clevr567"), ModelJob("full", "clevr567-heldout")
    assert ctx.no_cached_run(clevr) and ctx.no_cached_run(heldout)
    src = ctx._key_source(clevr, "fingerprint-of-the-clevr567-split")
    assert {**src, "dataset": None} == {**ctx._key_source(heldout, None), "dataset": None}
    run = ctx.out / "runs" / "abc"
    run.mkdir(parents=True)
    payload = {"key": "abc", "key_source": src, "job": vars(clevr)}
    (run / "benchmark_run.json").write_text(json.dumps(payload))
    assert not ctx.no_cached_run(clevr)
    assert ctx.no_cached_run(heldout)
    # A marker without its job (written before markers named it) may still be a match.
    (run / "benchmark_run.json").write_text(json.dumps({"key": "abc", "key_source": src}))
    assert not ctx.no_cached_run(heldout)
