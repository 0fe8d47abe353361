"""``svorf`` command line: a thin layer over :mod:`svorf.train` and :mod:`svorf.viz`.

Usage::

    svorf train --data DIR --preset clevr567 --scale smoke|cpu|paper --out RUN
                [--steps N] [--resume] [--seed S] [--eval-data DIR] [--image-size N]
                [--device auto|cpu|cuda] [--max-scenes N] [--threads N] [--no-progress]
    svorf render RUN --data DIR --scene I [--out DIR] [--force] [--allow-preset-mismatch]
                 [--input-view V] [--chunk N] [--refine-steps N [--refine-lr LR]]
                 [--device auto|cpu|cuda]
    svorf info --scale paper [--preset clevr567] [--image-size N]
    svorf edit RUN --data DIR --scene I [--move-object K --offset DX DY]
               [--swap-background DONOR] [--out DIR] [--force]   (svorf.edit_cli)
    svorf config --scale cpu --preset clevr567 [--image-size N] [--steps N] [--seed S]
                 [--json]

    torchrun --nproc_per_node N -m svorf.cli train ...   (data parallel, see below)

``svorf train`` under ``torchrun`` (``WORLD_SIZE`` > 1 in the environment) initialises
the process group (NCCL on CUDA, gloo on CPU) and trains data-parallel: the global batch
stays the scale's ``batch_scenes`` (it must be divisible by the number of ranks), rank 0
writes the run folder and prints; see ``svorf.distributed`` and ``docs/scaleout.md``.

``svorf config`` prints the config key of what ``svorf train`` with the same flags would
train (``svorf.train_config.config_key``: the model config and the training settings that
change what is learned, not the data, device or logging) without training anything;
``benchmark run NAME --scale S --show-config`` prints the key of every model a benchmark
protocol trains, so the two can be compared. ``--json`` adds both configs.

``svorf render`` writes into ``RUN/render/{preset}-{split}/scNNNN`` (named after the
data's manifest, so renders of different datasets never mix) and refuses a folder that
already holds files unless ``--force``. It refuses data of another preset than the run's
training data (as ``svorf train`` refuses data of another preset than ``--preset``),
except the paper's generalization tests (:data:`GENERALIZATION_TEST_DATA`: a CLEVR-567
model on clevr567-heldout, clevr567-gray or packed-clevr11 test data);
``--allow-preset-mismatch`` renders any other pair.

Bad input (unknown preset or scale, a data folder that is not a split or does not fit
the preset or scale, a run folder that already holds a run without ``--resume``, a
corrupt checkpoint) prints one line ``svorf: error: ...`` that says what was wrong and
how to fix it ("did you mean ...?" for a misspelt name), and exits with status 2; a
diverged training run exits with status 1.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from scenefmt.cli_util import RUNTIME, USAGE, OneLineParser, error_line, fail

#: ``svorf.refine.REFINE_LR`` for the help text, without importing torch to print it
#: (tests/test_refine.py checks that the two agree).
REFINE_LR_HELP = 2e-2

if TYPE_CHECKING:
    from scenefmt import Manifest
    from svorf.config import ModelConfig
    from svorf.distributed import DistContext
    from svorf.train import TrainConfig

__all__ = ["GENERALIZATION_TEST_DATA", "main"]

#: Data presets a run may be rendered on besides its training data's own preset: the
#: paper's generalization tests (section 4.6; ``benchmark run generalization``) test the
#: CLEVR-567 model on held-out appearances, grayscale images and packed 11-object scenes.
#: Keys and values are data presets (the ``preset`` of a split's ``manifest.json``).
GENERALIZATION_TEST_DATA: dict[str, tuple[str, ...]] = {
    "clevr567": ("clevr567-heldout", "clevr567-gray", "packed-clevr11"),
}


def _scale_help() -> str:
    from svorf.registry import SCALES

    return "model and schedule size: " + ", ".join(
        f"{name} ({spec.summary})" for name, spec in SCALES.items()
    )


def _parser() -> argparse.ArgumentParser:
    from svorf.registry import PRESETS, SCALE_NAMES

    scale_help = _scale_help()
    p = OneLineParser(prog="svorf", description="Train and inspect sVORF models.")
    sub = p.add_subparsers(dest="command", required=True)

    t = sub.add_parser("train", help="train a model on a generated split")
    t.add_argument("--data", required=True, help="training split folder (e.g. data/clevr567/train)")
    t.add_argument(
        "--preset",
        required=True,
        choices=sorted(PRESETS),
        help="training preset (sets the slot count; must match the data)",
    )
    t.add_argument("--scale", required=True, choices=SCALE_NAMES, help=scale_help)
    t.add_argument("--out", required=True, help="run folder (checkpoint, logs)")
    t.add_argument("--steps", type=int, help="total optimizer steps (default: the scale's)")
    t.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in --out from its checkpoint.pt (a rerun without it is refused)",
    )
    t.add_argument("--seed", type=int, help="random seed (default: 0)")
    t.add_argument("--eval-data", help="held-out split evaluated every eval_every steps")
    t.add_argument("--image-size", type=int, help="training resolution (default: the scale's)")
    t.add_argument("--device", help="auto (default), cpu, cuda or cuda:N")
    t.add_argument("--max-scenes", type=int, help="use only the first N scenes")
    t.add_argument(
        "--minutes",
        type=float,
        default=None,
        metavar="M",
        help="stop after M minutes of training wall time (checkpoint kept; --resume "
        "continues, with the same M where the config has progress-driven schedules); "
        "with --steps 1000000 this is how `benchmark --train-minutes M` trains. The "
        "cpu recipe's model says early when this machine is too slow for the steps its "
        "results were measured at, and which --steps would match them",
    )
    t.add_argument(
        "--init-from",
        metavar="RUN",
        default=None,
        help="start from the weights of another run (every tensor whose name and shape "
        "match); the paper starts Room-Diverse models from a CLEVR-567 model",
    )
    t.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    t.add_argument("--no-progress", action="store_true", help="no progress bar")

    r = sub.add_parser("render", help="render one scene of a split with a trained run")
    r.add_argument("run", help="run folder written by `svorf train`")
    r.add_argument("--data", required=True, help="split folder holding the scene")
    r.add_argument("--scene", type=int, required=True, help="scene number (sc%%04d)")
    r.add_argument(
        "--out", help="output folder (default RUN/render/PRESET-SPLIT/scNNNN, from the data)"
    )
    r.add_argument(
        "--force", action="store_true", help="overwrite an output folder that holds files"
    )
    r.add_argument(
        "--allow-preset-mismatch",
        action="store_true",
        help="render data of another preset than the run's training data (beyond the "
        "generalization tests that are always allowed)",
    )
    r.add_argument("--input-view", type=int, default=0, help="view fed to the encoder")
    r.add_argument("--chunk", type=int, default=4096, help="rays per rendering chunk")
    r.add_argument(
        "--refine-steps",
        type=int,
        default=0,
        metavar="N",
        help="test-time slot refinement: N Adam steps on the slots (networks frozen) to "
        "reproduce the input view's pixels before rendering (default: 0, the encoder's slots)",
    )
    r.add_argument(
        "--refine-lr",
        type=float,
        default=None,
        metavar="LR",
        help=f"the slots' Adam learning rate of --refine-steps (default: {REFINE_LR_HELP:g})",
    )
    r.add_argument("--device", default="auto", help="auto (default), cpu, cuda or cuda:N")

    from svorf.edit_cli import add_edit_parser

    add_edit_parser(sub)

    i = sub.add_parser("info", help="print the parameter count of a scale")
    i.add_argument("--scale", required=True, choices=SCALE_NAMES, help=scale_help)
    i.add_argument(
        "--preset", default="clevr567", choices=sorted(PRESETS), help="sets the slot count"
    )
    i.add_argument("--image-size", type=int, help="resolution (default: the scale's)")

    c = sub.add_parser(
        "config",
        help="print the config key (and with --json the configs) that `svorf train` with "
        "the same flags trains; trains nothing",
    )
    c.add_argument("--scale", required=True, choices=SCALE_NAMES, help=scale_help)
    c.add_argument(
        "--preset", required=True, choices=sorted(PRESETS), help="training preset (slot count)"
    )
    c.add_argument("--image-size", type=int, help="training resolution (default: the scale's)")
    c.add_argument("--steps", type=int, help="total optimizer steps (default: the scale's)")
    c.add_argument("--seed", type=int, help="random seed (default: 0)")
    c.add_argument("--json", action="store_true", help="print the key and both configs as JSON")
    return p


class _UsageError(Exception):
    """A bad command-line input; printed as one line, exit status 2."""


def _read_manifest(data: str, *, required: bool = True) -> Manifest | None:
    """The manifest of split folder ``data`` (None if it has none and not ``required``,
    or if it is not a JSON object: nothing recorded to check; the dataset loader rejects it).

    Any other manifest that is not a :class:`scenefmt.Manifest` fails with the message the
    dataset loader (``svorf.data``) gives for it, before any work.
    """
    from scenefmt import Manifest, read_json

    root = Path(data)
    if not root.is_dir():
        raise _UsageError(f"--data {data}: not a directory (expected a generated split folder)")
    manifest = root / "manifest.json"
    if not manifest.is_file():
        if not required:  # a uORF-layout folder: no metadata to check
            return None
        raise _UsageError(
            f"--data {data}: no manifest.json - not a generated split folder "
            f"(run `generate verify {data}`)"
        )
    try:
        meta = read_json(manifest)
    except (OSError, ValueError) as e:
        raise _UsageError(f"{manifest}: unreadable JSON ({e}); run `generate verify {data}`") from e
    if not isinstance(meta, dict):
        return None
    try:
        return Manifest.from_json(meta)
    except ValueError as e:
        raise _UsageError(f"{manifest}: {e}; run `generate verify {root}`") from e


def _manifest_preset(meta: Manifest | None) -> str | None:
    """The data preset a manifest records (None: no manifest, or none recorded)."""
    return (meta.preset or None) if meta is not None else None


def _check_data(
    data: str, preset: str, scale: str, image_size: int, target_size: int | None = None
) -> None:
    """Fail fast (before building the model) on a data folder that cannot fit the run."""
    from svorf.train import PRESETS

    meta = _read_manifest(data)
    found = _manifest_preset(meta)
    wanted = PRESETS[preset].data_presets
    if found not in wanted:
        raise _UsageError(
            f"--preset {preset} trains on {'/'.join(wanted)} data, but {data} holds "
            f"preset {found!r} (pass --preset {_preset_for(found)})"
        )
    res = tuple(meta.image_hw) if meta is not None else None
    if res is not None and target_size and min(int(r) for r in res) < target_size:
        raise _UsageError(
            f"--scale {scale} draws its training rays from {target_size}x{target_size} "
            f"images (TrainConfig.target_size) but {data} holds {res[0]}x{res[1]} ones; "
            f"render the split with --resolution {target_size}"
        )
    if res is not None and min(int(r) for r in res) < image_size:
        raise _UsageError(
            f"--scale {scale} trains at {image_size}x{image_size} but {data} holds "
            f"{res[0]}x{res[1]} images; pass --image-size {min(int(r) for r in res)} or "
            f"regenerate with --resolution {image_size}"
        )


def _check_out(out: str, resume: bool) -> None:
    """Refuse, before any work, to start a new run in a folder that holds one already."""
    from svorf.train import CHECKPOINT_NAME

    if not resume and (Path(out) / CHECKPOINT_NAME).exists():
        raise _UsageError(
            f"--out {out} already holds a run ({CHECKPOINT_NAME}); pass --resume to "
            "continue it, or --out DIR to start a new run elsewhere"
        )


def _preset_for(data_preset: object) -> str:
    from svorf.train import PRESETS

    names = [k for k, v in PRESETS.items() if data_preset in v.data_presets]
    return names[0] if names else "<one of " + ", ".join(sorted(PRESETS)) + ">"


def _set_threads(n: int) -> None:
    import torch

    torch.set_num_threads(n)


def _cmd_train(a: argparse.Namespace) -> int:
    from svorf import distributed
    from svorf.model import SVORF
    from svorf.train import run_configs

    if a.threads is not None:
        if a.threads < 1:
            raise _UsageError(f"--threads must be >= 1, got {a.threads}")
        _set_threads(a.threads)
    if a.minutes is not None and not (a.minutes > 0 and math.isfinite(a.minutes)):
        raise _UsageError(f"--minutes must be a positive number, got {a.minutes}")
    _check_out(a.out, a.resume)
    overrides = {
        k: v
        for k, v in (("steps", a.steps), ("seed", a.seed), ("device", a.device))
        if v is not None
    }
    mcfg, tcfg = run_configs(a.scale, a.preset, image_size=a.image_size, **overrides)
    _check_data(a.data, a.preset, a.scale, mcfg.image_size, tcfg.target_size)
    if a.max_scenes is not None and a.max_scenes < 1:
        raise _UsageError(f"--max-scenes must be >= 1, got {a.max_scenes}")
    world = distributed.env_world_size()
    if world > 1:  # before any process group exists: every rank fails alike, at once
        distributed.local_batch(tcfg.batch_scenes, world)
    ctx = distributed.init_from_env(tcfg.device)
    finished = False
    try:
        rc = _train_ranked(a, mcfg, tcfg, SVORF(mcfg).count_parameters(), ctx)
        finished = True
        return rc
    finally:
        distributed.shutdown(synchronise=finished)


def _train_ranked(
    a: argparse.Namespace,
    mcfg: ModelConfig,
    tcfg: TrainConfig,
    n: int,
    ctx: DistContext | None,
) -> int:
    """The training part of ``svorf train`` (every rank under torchrun; rank 0 prints)."""
    from svorf.train import train
    from svorf.train_config import config_key

    main = ctx is None or ctx.is_main
    resumed = ""
    if a.resume:  # a corrupt checkpoint is reported before any data is loaded
        from svorf.train import CHECKPOINT_NAME, read_checkpoint

        if (Path(a.out) / CHECKPOINT_NAME).exists():
            step = read_checkpoint(Path(a.out) / CHECKPOINT_NAME).get("step")
            resumed = f", resuming at step {step:,}" if isinstance(step, int) else ""
    if main:
        ranks = "" if ctx is None else f", {ctx.world_size} ranks ({ctx.backend})"
        print(
            f"svorf train: scale {a.scale}, preset {a.preset}, K={mcfg.num_slots}, "
            f"image {mcfg.image_size}, {n:,} parameters, {tcfg.steps} steps{ranks}, "
            f"config key {config_key(mcfg, tcfg)}{resumed}",
            flush=True,
        )
    summary = train(
        a.data,
        a.out,
        mcfg,
        tcfg,
        resume=a.resume,
        eval_data=a.eval_data,
        max_scenes=a.max_scenes,
        progress=not a.no_progress,
        init_from=a.init_from,
        max_wall_s=None if a.minutes is None else a.minutes * 60.0,
    )
    if main:
        print(json.dumps(summary.to_dict(), indent=2))
    return 0


def _check_render_preset(run: str, trained: object, data: str, found: object, allow: bool) -> str:
    """Refuse rendering data of another preset than the run was trained on (one line),
    unless it is a generalization test or ``allow``; returns a note for the summary line."""
    if not isinstance(trained, str) or not isinstance(found, str):
        return ""  # an old checkpoint or a uORF-layout folder: nothing recorded to compare
    if found == trained:
        return ""
    if found in GENERALIZATION_TEST_DATA.get(trained, ()):
        return f" (generalization test: {trained} model on {found} data)"
    if allow:
        return f" (preset mismatch allowed: {trained} model on {found} data)"
    raise _UsageError(
        f"{run} was trained on {trained!r} data but --data {data} holds preset {found!r}; "
        f"render a {trained} split (e.g. data/{trained}/test) or pass --allow-preset-mismatch"
    )


def _render_dir(run: str, data: str, meta: Manifest | None, scene: int) -> Path:
    """``RUN/render/{preset}-{split}/scNNNN``: one folder per dataset split and scene."""
    root = Path(data).resolve()
    preset = _manifest_preset(meta)
    split = (meta.split or None) if meta is not None else None
    preset = preset if isinstance(preset, str) else root.parent.name
    split = split if isinstance(split, str) else root.name
    name = re.sub(r"[^A-Za-z0-9._-]+", "_", f"{preset}-{split}").strip("._") or "data"
    return Path(run) / "render" / name / f"sc{scene:04d}"


#: Files ``svorf render`` writes (removed from the output folder first under ``--force``).
_RENDER_FILES = re.compile(r"(input|grid|v\d\d_\w+)\.png")


def _cmd_render(a: argparse.Namespace) -> int:
    from svorf.data import MultiViewDataset
    from svorf.train import load_run, predict_scene, resolve_device
    from svorf.viz import save_scene_figures

    if a.scene < 0:
        raise _UsageError(f"--scene must be >= 0, got {a.scene}")
    if a.chunk < 1:
        raise _UsageError(f"--chunk must be >= 1, got {a.chunk}")
    if a.refine_steps < 0:
        raise _UsageError(f"--refine-steps must be >= 0, got {a.refine_steps}")
    from svorf.refine import REFINE_LR

    refine_lr = REFINE_LR if a.refine_lr is None else a.refine_lr
    if not (math.isfinite(refine_lr) and refine_lr > 0):
        raise _UsageError(f"--refine-lr must be a positive number, got {a.refine_lr}")
    if a.refine_lr is not None and not a.refine_steps:
        raise _UsageError("--refine-lr sets the rate of --refine-steps N; pass that too")
    meta = _read_manifest(a.data, required=False)
    device = resolve_device(a.device)
    model, info = load_run(a.run, device=device)
    note = _check_render_preset(
        a.run, info.dataset.get("preset"), a.data, _manifest_preset(meta), a.allow_preset_mismatch
    )
    out = Path(a.out) if a.out else _render_dir(a.run, a.data, meta, a.scene)
    if out.exists() and not out.is_dir():
        raise _UsageError(f"--out {out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not a.force:
            raise _UsageError(
                f"{out} already holds files (an earlier render?); pass --force to overwrite "
                f"them or --out DIR to write elsewhere"
            )
        for p in out.iterdir():  # only what an earlier render wrote: stale views go too
            if p.is_file() and _RENDER_FILES.fullmatch(p.name):
                p.unlink()
    # Render at the training resolution (stored in the run), reading only this scene.
    hw = info.dataset.get("image_hw") or info.model.image_size
    ds = MultiViewDataset(a.data, image_size=hw, scenes=[a.scene])
    if not 0 <= a.input_view < ds.n_views:
        raise _UsageError(f"--input-view must be in [0, {ds.n_views}), got {a.input_view}")
    pos = 0
    try:
        pred = predict_scene(
            model,
            ds,
            pos,
            input_view=a.input_view,
            chunk=a.chunk,
            refine_steps=a.refine_steps,
            refine_lr=refine_lr,
        )
    except ValueError as err:  # a model whose slots cannot be refined
        raise _UsageError(str(err)) from None
    paths = save_scene_figures(pred, ds, pos, out)
    print(f"svorf render: wrote {len(paths)} PNGs to {out} (grid: {out / 'grid.png'}){note}")
    return 0


def _cmd_info(a: argparse.Namespace) -> int:
    from svorf.model import SVORF
    from svorf.train import run_configs

    mcfg, tcfg = run_configs(a.scale, a.preset, image_size=a.image_size)
    n = SVORF(mcfg).count_parameters()
    print(
        f"scale {a.scale}, preset {a.preset}: {n:,} parameters "
        f"(K={mcfg.num_slots}, image {mcfg.image_size}, samples {mcfg.n_coarse}+{mcfg.n_fine}; "
        f"train: {tcfg.steps} steps x {tcfg.batch_scenes} scenes x {tcfg.rays_per_scene} rays)"
    )
    return 0


def _cmd_config(a: argparse.Namespace) -> int:
    from svorf.registry import recipe_for
    from svorf.train_config import config_key, run_configs

    if a.steps is not None and a.steps < 1:
        raise _UsageError(f"--steps must be >= 1, got {a.steps}")
    overrides = {k: v for k, v in (("steps", a.steps), ("seed", a.seed)) if v is not None}
    mcfg, tcfg = run_configs(a.scale, a.preset, image_size=a.image_size, **overrides)
    key = config_key(mcfg, tcfg)
    if a.json:
        out = {
            "config_key": key,
            "scale": a.scale,
            "preset": a.preset,
            "model_config": mcfg.to_dict(),
            "train_config": tcfg.to_dict(),
        }
        print(json.dumps(out, indent=2, sort_keys=True))
        return 0
    scale_recipe = recipe_for(a.scale, a.preset)
    recipe = "" if scale_recipe is None else f" with the {scale_recipe.name}"
    print(
        f"config key {key}: svorf train --scale {a.scale} --preset {a.preset}{recipe} "
        f"(K={mcfg.num_slots}, image {mcfg.image_size}, {tcfg.steps} steps x "
        f"{tcfg.batch_scenes} scenes x {tcfg.rays_per_scene} rays, seed {tcfg.seed})"
    )
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``svorf`` console script; returns the exit status."""
    try:
        args = _parser().parse_args(argv)
    except SystemExit as e:  # argparse: --help (0) or a usage error (2)
        return int(e.code or 0)
    from svorf.data import DatasetError
    from svorf.edit_cli import cmd_edit
    from svorf.train import CheckpointError, TrainingDiverged

    cmd = {
        "train": _cmd_train,
        "render": _cmd_render,
        "edit": cmd_edit,
        "info": _cmd_info,
        "config": _cmd_config,
    }[args.command]
    try:
        return cmd(args)
    except TrainingDiverged as e:
        return fail("svorf", error_line(e), RUNTIME)
    except (_UsageError, DatasetError, CheckpointError, ValueError, FileNotFoundError) as e:
        return fail("svorf", error_line(e), USAGE)
    except KeyboardInterrupt:
        print("svorf: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
