"""The registry of scales (``svorf.registry``): one place for each scale's model, training
and recipe, used by ``svorf train`` and the benchmark alike; ``svorf config`` and
``benchmark run ... --show-config`` print the same config key for the same model."""

from __future__ import annotations

import dataclasses
import re
from typing import get_args

import pytest

from benchmark import adapter
from benchmark import cli as benchmark_cli
from benchmark.context import Context
from benchmark.protocols.speed.options import SpeedOptions, default_options
from benchmark.protocols.tables import MEASURED_ROWS
from benchmark.protocols.tradeoff.common import SETTINGS
from benchmark.runner import planned_models
from benchmark.scales import SCALES as BENCH_SCALES
from benchmark.scales import SPEED_DEFAULTS, TRADEOFF
from benchmark.schema import SCALES as REPORT_SCALES
from svorf import cli as svorf_cli
from svorf.config import ModelConfig, Scale, model_config
from svorf.registry import PRESETS, SCALE_NAMES, SCALES, get_scale, recipe_for, slots_for
from svorf.train_config import (
    BOOKKEEPING_FIELDS,
    CPU_RECIPE,
    CPU_RECIPE_MODEL_FIELDS,
    CPU_RECIPE_PRESETS,
    TrainConfig,
    config_key,
    learning_fields,
    run_configs,
    train_config,
)


def test_every_scale_list_is_the_registry():
    assert get_args(Scale) == SCALE_NAMES == ("smoke", "cpu", "paper")
    assert tuple(BENCH_SCALES) == REPORT_SCALES == SCALE_NAMES
    assert tuple(TRADEOFF) == tuple(SPEED_DEFAULTS) == SCALE_NAMES
    assert SETTINGS is TRADEOFF  # the tradeoff protocol reads the benchmark's scales
    for name in SCALE_NAMES:  # the benchmark renders at the scale's model resolution
        assert BENCH_SCALES[name].resolution == SCALES[name].image_size
        assert isinstance(default_options(name), SpeedOptions)


def test_model_and_train_configs_come_from_the_registry():
    names = {f.name for f in dataclasses.fields(ModelConfig)}
    tnames = {f.name for f in dataclasses.fields(TrainConfig)}
    for name, spec in SCALES.items():
        assert set(spec.model) <= names and set(spec.train) <= tnames
        m, t = model_config(name), train_config(name)
        assert m.image_size == spec.image_size and m.num_slots == 8
        assert all(getattr(m, k) == v for k, v in spec.model.items())
        assert t == TrainConfig(**spec.train)
    assert model_config("paper") == ModelConfig()  # the defaults are the paper's model
    with pytest.raises(ValueError, match="scale must be one of"):
        model_config("huge")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="did you mean 'cpu'"):
        get_scale("cpux")


def test_the_cpu_recipe_is_the_cpu_scales_recipe_for_the_clevr_family():
    recipe = SCALES["cpu"].recipe
    assert recipe is not None
    assert CPU_RECIPE == recipe.fields and CPU_RECIPE_MODEL_FIELDS == tuple(recipe.model)
    assert CPU_RECIPE_PRESETS == recipe.presets
    assert list(CPU_RECIPE)[:3] == ["ray_sampling", "warmup", "nvs_warmup"]  # train first
    assert recipe.preset_model == {"room-chair": {"num_slots": 6}}  # a spare slot
    assert (slots_for("cpu", "room-chair"), slots_for("paper", "room-chair")) == (6, 5)
    for scale in SCALE_NAMES:
        for preset, spec in PRESETS.items():
            m, t = run_configs(scale, preset)
            masked = spec.slot_mask_train
            if recipe_for(scale, preset) is not None:
                masked = recipe.model.get("slot_mask_train", masked)
            assert m.num_slots == slots_for(scale, preset) and m.slot_mask_train == masked
            if recipe_for(scale, preset) is not None:
                assert scale == "cpu" and preset in CPU_RECIPE_PRESETS
                own = recipe.preset_model.get(preset, {})
                assert all(getattr(m, k) == v for k, v in {**recipe.model, **own}.items())
                assert all(getattr(t, k) == v for k, v in recipe.train.items())
            else:
                assert (m, t) == run_configs(scale, preset, recipe=False)


def test_config_key_names_what_is_learned():
    m, t = run_configs("cpu", "clevr567")
    key = config_key(m, t)
    assert re.fullmatch(r"[0-9a-f]{16}", key)
    changed = {"device": "cuda", "log_every": 1, "ckpt_every": 7, "eval_every": 3, "eval_scenes": 9}
    assert set(changed) == set(BOOKKEEPING_FIELDS)
    assert config_key(m, t.replace(**changed)) == key
    every = {f.name for f in dataclasses.fields(TrainConfig)} - set(BOOKKEEPING_FIELDS)
    # target_size, salient_fade, input_view_from, pixel_jitter, gray_scenes, coarse_to_fine,
    # ema_decay, enc_lr_scale, lr_decay_from, slot_distill, refine_train and average_probes
    # are written only when set, so the keys of earlier runs stay valid (the cpu recipe sets
    # ema_decay)
    unset = {
        "target_size",
        "salient_fade",
        "input_view_from",
        "pixel_jitter",
        "gray_scenes",
        "coarse_to_fine",
        "enc_lr_scale",
        "lr_decay_from",
        "slot_distill",
        "refine_train",
        "average_probes",
    }
    assert t.ema_decay == 0.999 and set(learning_fields(t)) == every - unset
    plain = t.replace(ema_decay=0.0)
    assert set(learning_fields(plain)) == every - unset - {"ema_decay"}
    finer = t.replace(
        target_size=128, salient_fade=(0.5, 0.7), input_view_from=0.5, pixel_jitter=1.0
    )
    assert set(learning_fields(finer)) == every - {
        "gray_scenes",
        "coarse_to_fine",
        "enc_lr_scale",
        "lr_decay_from",
        "slot_distill",
        "refine_train",
        "average_probes",
    }
    assert config_key(m, finer) != key
    probed = t.replace(average_probes=("ema0.9995", "tail0.8"))
    assert set(learning_fields(probed)) == every - unset | {"average_probes"}
    assert config_key(m, probed) != key
    coarse = t.replace(coarse_to_fine=(2, 0.5))
    assert set(learning_fields(coarse)) == every - unset | {"coarse_to_fine"}
    assert config_key(m, coarse) != key
    assert config_key(m, plain) != key
    faster = t.replace(enc_lr_scale=2.0)
    assert set(learning_fields(faster)) == every - unset | {"enc_lr_scale"}
    assert config_key(m, faster) != key
    late = t.replace(lr_decay="cosine", lr_decay_from=0.8)
    assert set(learning_fields(late)) == every - unset | {"lr_decay_from"}
    assert config_key(m, late) != config_key(m, t.replace(lr_decay="cosine")) != key
    taught = t.replace(slot_distill=(1.0, 5, 1e-2))
    assert set(learning_fields(taught)) == every - unset | {"slot_distill"}
    assert config_key(m, taught) != key
    iterative = t.replace(refine_train=(3, 2e-2, 128))
    assert set(learning_fields(iterative)) == every - unset | {"refine_train"}
    assert config_key(m, iterative) not in (key, config_key(m, taught))
    assert config_key(m, t.replace(seed=1)) != key
    assert config_key(m.replace(num_slots=7), t) != key
    assert config_key(*run_configs("cpu", "clevr567", recipe=False)) != key


def _svorf_key(capsys, *argv: str) -> str:
    assert svorf_cli.main(["config", *argv]) == 0
    out = capsys.readouterr().out
    return re.match(r"config key ([0-9a-f]{16}): svorf train ", out).group(1)


@pytest.mark.parametrize("scale", SCALE_NAMES)
def test_svorf_config_and_benchmark_show_config_print_the_same_key(scale, tmp_path, capsys):
    """`svorf train --scale S --preset clevr567` trains the model of `benchmark run
    segmentation --scale S --datasets clevr567`: both commands print one config key."""
    bench = [
        "run",
        "segmentation",
        "--scale",
        scale,
        "--datasets",
        "clevr567",
        "--out",
        str(tmp_path / "out"),
        "--data",
        str(tmp_path / "data"),
        "--show-config",
    ]
    assert benchmark_cli.main(bench) == 0
    out = capsys.readouterr().out
    keys = re.findall(r"full on clevr567: config key ([0-9a-f]{16})", out)
    cmd = re.search(r"same model: (svorf train .*)", out).group(1)
    assert len(keys) == 1 and f"--scale {scale} --preset clevr567" in cmd
    steps = BENCH_SCALES[scale].train_steps  # the benchmark's own step count (smoke)
    extra = [] if steps is None else ["--steps", str(steps)]
    assert f"--steps {steps}" in cmd if steps else "--steps" not in cmd
    assert _svorf_key(capsys, "--scale", scale, "--preset", "clevr567", *extra) == keys[0]
    assert not (tmp_path / "data").exists() and not (tmp_path / "out").exists()  # no work


def test_every_benchmark_model_has_svorfs_configs(tmp_path):
    """Every model of every table protocol, at every scale: the full models are exactly
    `svorf train`'s configs (same key), the ablations svorf's plus their overrides."""
    for scale in SCALE_NAMES:
        ctx = Context("segmentation", scale, tmp_path / "o", tmp_path / "d", seed=3)
        steps = ctx.train_steps
        for proto, rows in MEASURED_ROWS.items():
            for job in planned_models(ctx, rows()):
                preset = adapter.svorf_preset(job.train_preset, job.variant)
                over = {"seed": 3, **({} if steps is None else {"steps": steps})}
                m, t = run_configs(scale, preset, **over)
                cmd = ctx.svorf_command(job)
                if job.variant == "full":
                    assert ctx.config_key(job) == config_key(m, t), (scale, proto, job)
                    assert cmd is not None and f"--preset {preset} " in cmd and "--seed 3" in cmd
                elif job.variant != "packed11":
                    assert ctx.config_key(job) != config_key(m, t) and cmd is None
                mb, tb = ctx.configs(job)
                assert learning_fields(tb) == learning_fields(t)
                assert mb == m.replace(
                    **adapter.VARIANTS[job.variant],
                    **adapter.variant_adjustments(m, job.variant)[0],
                )
