"""The ``generate`` command (thin wrapper over ``pipeline.generate_dataset``).

    generate --preset clevr567 [--split train|test|manip] [--n N] [--out DIR] [--workers W]
             [--resolution 128] [--seed S] [--samples 8] [--denoise/--no-denoise]
             [--bounces 4] [--threads T] [--shard i/n] [--camera-radius R]
             [--source DIR] [--backend local|ray [--address ADDR]] [--no-progress]
    generate verify DIR
    generate preview --preset NAME [--n 4] [--out DIR]

``--backend ray`` renders the scenes as tasks on Ray actors (one Blender session per
actor) on the cluster at ``--address`` (default ``RAY_ADDRESS``, else a local Ray
instance); ``--shard i/n`` splits a split over plain job arrays. Either way the files
are the same bytes as a local run, and rerunning resumes. See ``docs/scaleout.md``.

Bad input (unknown preset, --n <= 0, unwritable --out, --resolution < 16, missing
bpy or ray) prints one line ``generate: error: ...`` (what was wrong and how to fix it;
"did you mean ...?" for a misspelt preset or subcommand) and exits with status 2, writing
nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from generators.presets import PRESETS
from generators.spec import RenderSettings
from scenefmt.cli_util import USAGE, OneLineParser, error_line, fail, unknown_choice

_D = RenderSettings()

#: ``generate SUBCOMMAND ...``; anything else is the options of ``generate`` itself.
SUBCOMMANDS = ("verify", "preview")


def _fail(msg: str) -> int:
    return fail("generate", msg, USAGE)


def _shard(text: str) -> tuple[int, int]:
    try:
        i, n = (int(x) for x in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--shard must look like i/n (e.g. 0/4), got {text!r}"
        ) from None
    return i, n


def _gen_parser() -> OneLineParser:
    ap = OneLineParser(prog="generate", description="Render a uORF-style multi-view dataset split "
                 "(subcommands: 'generate verify DIR', 'generate preview --preset NAME').")  # fmt: skip
    ap.add_argument("--preset", required=True, help=f"one of: {', '.join(sorted(PRESETS))}")
    ap.add_argument(
        "--split",
        default=None,
        help="train, test, or manip: per scene also a moved and a background-changed variant "
        "in uORF's manipulation layout (default: the preset's first split)",
    )
    ap.add_argument("--n", type=int, default=None, help="scenes (default: the preset's split size)")
    ap.add_argument(
        "--out", type=Path, default=None, help="split folder (default: data/{preset}/{split})"
    )
    ap.add_argument(
        "--workers", type=int, default=None, help="worker processes (default: cores // 2, >= 1)"
    )
    ap.add_argument(
        "--threads",
        type=int,
        default=None,
        help="Cycles threads per worker (default: cores // workers)",
    )
    ap.add_argument(
        "--resolution", type=int, default=128, help="square image size in pixels (>= 16)"
    )
    ap.add_argument("--seed", type=int, default=0, help="dataset seed (>= 0)")
    ap.add_argument(
        "--samples",
        type=int,
        default=_D.samples,
        help="Cycles samples/pixel",
    )
    ap.add_argument("--denoise", action=argparse.BooleanOptionalAction, default=_D.denoise,
                    help="OpenImageDenoise (default: on)")  # fmt: skip
    ap.add_argument(
        "--bounces",
        type=int,
        default=_D.max_bounces,
        help="max light bounces",
    )
    ap.add_argument(
        "--shard",
        type=_shard,
        default=(0, 1),
        help="i/n: only scenes with index %% n == i (default 0/1: all scenes)",
    )
    ap.add_argument(
        "--camera-radius",
        type=float,
        default=None,
        help="override the preset's camera radius (closer cameras for small datasets)",
    )
    ap.add_argument("--source", type=Path, default=None,
                    help="derived presets (clevr567-gray): folder of the source renders to convert")  # fmt: skip
    ap.add_argument(
        "--backend",
        choices=("local", "ray"),
        default="local",
        help="local: process pool here (default); ray: Ray actors on a cluster "
        "(pip install 'svorf-toolkit[ray]')",
    )
    ap.add_argument(
        "--address",
        default=None,
        help="Ray cluster address for --backend ray (auto, host:6379, ray://host:10001; "
        "default RAY_ADDRESS, else a local Ray instance)",
    )
    ap.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")
    return ap


def _generate(argv: list[str]) -> int:
    from generators.blender_backend import BpyMissingError
    from generators.pipeline import GenerateConfig, generate_dataset
    from generators.ray_backend import RayMissingError

    a = _gen_parser().parse_args(argv)
    try:
        cfg = GenerateConfig(
            preset=a.preset, split=a.split, n=a.n, out=a.out, resolution=a.resolution,
            seed=a.seed, samples=a.samples, denoise=a.denoise, bounces=a.bounces,
            workers=a.workers, threads=a.threads, shard=a.shard, progress=a.progress,
            source=a.source, camera_radius=a.camera_radius, backend=a.backend,
            address=a.address,
        )  # fmt: skip
        summary = generate_dataset(cfg)
    except (ValueError, BpyMissingError, RayMissingError) as e:
        return _fail(error_line(e))
    except KeyboardInterrupt:
        print("generate: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
    print(summary.line(), file=sys.stderr if a.progress else sys.stdout)
    return 0


def _verify(argv: list[str]) -> int:
    from generators.verify import verify_split

    ap = OneLineParser(
        prog="generate verify",
        tool="generate",
        description="Check a split folder against the format.",
    )
    ap.add_argument("dir", type=Path, help="split folder (e.g. data/clevr567/train)")
    a = ap.parse_args(argv)
    if not a.dir.is_dir():
        return _fail(
            f"{a.dir}: no such folder; pass a split folder written by `generate` "
            "(e.g. data/clevr567/train)"
        )
    problems = verify_split(a.dir)
    if problems:
        for p in problems:
            print(p)
        print(f"generate verify: {a.dir}: {len(problems)} problem(s)", file=sys.stderr)
        return 1
    print(f"generate verify: {a.dir}: OK")
    return 0


def _preview(argv: list[str]) -> int:
    from generators.blender_backend import BpyMissingError
    from generators.pipeline import GenerateConfig, generate_dataset
    from generators.preview import write_contact_sheet

    ap = OneLineParser(
        prog="generate preview",
        tool="generate",
        description="Render a few scenes of a preset and a contact sheet (OUT/preview.png: "
        "one row per scene; per view RGB | instance ids | depth) to check a preset by eye.",
    )
    ap.add_argument("--preset", required=True, help=f"one of: {', '.join(sorted(PRESETS))}")
    ap.add_argument(
        "--split", default=None, help="train or test (default: the preset's first split)"
    )
    ap.add_argument("--n", type=int, default=4, help="scenes to render (rows of the sheet)")
    ap.add_argument(
        "--out",
        type=Path,
        default=None,
        help="folder for the scenes (OUT/split) and OUT/preview.png "
        "(default: data/preview/{preset})",
    )
    ap.add_argument(
        "--resolution", type=int, default=128, help="square image size in pixels (>= 16)"
    )
    ap.add_argument("--seed", type=int, default=0, help="dataset seed (>= 0)")
    ap.add_argument("--samples", type=int, default=_D.samples, help="Cycles samples/pixel")
    a = ap.parse_args(argv)
    out = a.out if a.out is not None else Path("data") / "preview" / a.preset
    try:
        cfg = GenerateConfig(preset=a.preset, split=a.split, n=a.n, out=out / "split",
                             resolution=a.resolution, seed=a.seed, samples=a.samples)  # fmt: skip
        generate_dataset(cfg)
    except (ValueError, BpyMissingError) as e:
        return _fail(error_line(e))
    path = write_contact_sheet(out / "split", out / "preview.png", a.n)
    print(
        f"generate preview: {path} (rows = scenes; per view: RGB | instance ids | depth, "
        "near = yellow ... far = dark)"
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``generate`` console script; returns the exit status (a bad
    command line exits with status 2 from the parser)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "verify":
        return _verify(argv[1:])
    if argv and argv[0] == "preview":
        return _preview(argv[1:])
    if argv and not argv[0].startswith("-"):  # no positional arguments: a misspelt command
        return _fail(
            f"{unknown_choice(argv[0], SUBCOMMANDS, 'command')}; to render a split run "
            "`generate --preset NAME ...` (see `generate --help`)"
        )
    return _generate(argv)


if __name__ == "__main__":
    sys.exit(main())
