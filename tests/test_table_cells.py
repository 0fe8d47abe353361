"""Every cell of the table protocols builds a valid config, and the cpu-scale ones train.

A cell is (protocol, measured row, scale): the model variant and training preset of the
row, with the scale's base configs (the cpu recipe at ``cpu`` for its presets).
An ablation that cannot combine with a recipe item (Slot-Mixer has no per-slot density to
localise) must say what was changed instead of crashing the protocol.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from benchmark import adapter
from benchmark.protocols.tables import MEASURED_ROWS
from svorf.synthetic import write_synthetic_split
from svorf.train import train

SCALES = ("smoke", "cpu", "paper")


def _cells():
    seen = {}
    for protocol, rows in MEASURED_ROWS.items():
        for row in rows():
            for scale in SCALES:
                key = (scale, row.job.train_preset, row.job.variant)
                seen.setdefault(key, f"{protocol}/{row.table}/{row.model}/{row.dataset}")
    return seen


CELLS = _cells()


@pytest.mark.parametrize("scale,preset,variant", sorted(CELLS))
def test_every_cell_builds_a_config(scale, preset, variant):
    mcfg = adapter.model_config(scale, preset, variant)
    tcfg = adapter.train_config(scale, preset, variant, seed=0, device="cpu")
    assert mcfg.num_slots == adapter.num_slots(scale, preset, variant)
    for field, value in adapter.VARIANTS[variant].items():
        assert getattr(mcfg, field) == value, (field, CELLS[(scale, preset, variant)])
    assert tcfg.seed == 0 and tcfg.device == "cpu"


def test_slot_mixer_at_cpu_scale_says_what_it_changed():
    base, _ = adapter.base_configs("cpu", "clevr567", "slot_mixer")
    assert base.slot_locality is not None  # the recipe's locality ...
    assert base.slot_locality_narrow is not None  # ... and its narrowing schedule
    changes, notes = adapter.variant_adjustments(base, "slot_mixer")
    assert changes == {
        "slot_locality": None,
        "slot_locality_narrow": None,
        "slot_locality_xy": False,
        "slot_centre": "learned",
    }
    assert notes and "Slot-Mixer" in notes[0] and "slot_locality_narrow" in notes[0]
    assert "slot_locality_xy" in notes[0]
    assert adapter.model_config("cpu", "clevr567", "slot_mixer").slot_locality is None
    # ... and nothing changes where nothing conflicts.
    assert adapter.variant_adjustments(base, "wo_sa") == ({}, [])
    # Without a narrowing schedule only the radius and the centres go.
    plain = dataclasses.replace(base, slot_locality_narrow=None, slot_locality_xy=False)
    changes, _ = adapter.variant_adjustments(plain, "slot_mixer")
    assert changes == {"slot_locality": None, "slot_centre": "learned"}


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    return write_synthetic_split(
        tmp_path_factory.mktemp("cells") / "train", n_scenes=2, resolution=32, seed=3
    )


CPU_MODELS = sorted({(p, v) for (s, p, v) in CELLS if s == "cpu"})


@pytest.mark.parametrize("preset,variant", CPU_MODELS)
def test_every_cpu_scale_model_trains_one_step(preset, variant, split, tmp_path):
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        mcfg = dataclasses.replace(adapter.model_config("cpu", preset, variant), image_size=32)
        tcfg = adapter.train_config("cpu", preset, variant, seed=0, device="cpu")
        tcfg = dataclasses.replace(
            tcfg, steps=1, batch_scenes=1, rays_per_scene=16, nvs_warmup=0, eval_every=0
        )
        summary = train(split, tmp_path / "run", mcfg, tcfg, progress=False)
    finally:
        torch.set_num_threads(n)
    assert summary.steps == 1
    assert torch.isfinite(torch.tensor(summary.final_loss))


def test_room_diverse_starts_from_the_clevr567_model(split, tmp_path):
    """Paper appendix A: Room-Diverse models start from a CLEVR-567 model's weights."""
    from svorf.train import init_weights_from

    assert adapter.init_preset("room-diverse") == "clevr567"
    assert adapter.init_preset("clevr567") is None
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        tcfg = adapter.train_config("smoke", "clevr567", "full", seed=0, device="cpu")
        tcfg = dataclasses.replace(tcfg, steps=2, batch_scenes=1, rays_per_scene=16)
        src = adapter.model_config("smoke", "clevr567")
        train(split, tmp_path / "clevr", src, tcfg, progress=False)
        dst = adapter.model_config("smoke", "room-diverse")  # K=5 instead of 8
        summary = train(
            split, tmp_path / "room", dst, tcfg.replace(steps=1), progress=False,
            init_from=tmp_path / "clevr",
        )  # fmt: skip
    finally:
        torch.set_num_threads(n)
    info = summary.init_from
    assert info["step"] == 2 and info["loaded"] > 0 and info["kept"] > 0
    assert all("slot" in k or "pos" in k or "query" in k for k in info["kept_names"]), info
    model = adapter.load_model(tmp_path / "clevr")
    from svorf.model import SVORF

    fresh = SVORF(dst)
    res = init_weights_from(fresh, tmp_path / "clevr")
    for k, v in fresh.state_dict().items():
        theirs = model.state_dict().get(k)
        if theirs is not None and theirs.shape == v.shape:
            assert torch.equal(theirs, v), k
    assert res["loaded"] == info["loaded"]


def test_report_row_to_dict_is_the_report_json():
    """benchmark.rows.Row: the typed row gives exactly the dict a report holds."""
    from benchmark.rows import Row, row_id

    r = Row(table="tab:seg", model="sVORF", dataset="clevr567", source="measured",
            metrics={"ari": 50.0, "fg_ari": None}, null_reasons={"fg_ari": "no_scene_scored"},
            variant="full", n_scenes=3, extra={"run_key": "abc"})  # fmt: skip
    assert r.id == row_id("tab:seg", "sVORF", "clevr567", "measured")
    assert r.to_dict() == {
        "id": "tab:seg|sVORF|clevr567|measured", "table": "tab:seg", "model": "sVORF",
        "dataset": "clevr567", "variant": "full", "source": "measured",
        "metrics": {"ari": 50.0, "fg_ari": None}, "null_reasons": {"fg_ari": "no_scene_scored"},
        "n_scenes": 3, "run_key": "abc",
    }  # fmt: skip
    assert "n_scenes" not in Row("t", "m", "d", "paper", {}).to_dict()
