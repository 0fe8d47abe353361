"""Two arms of a recipe change side by side at each seed, read from written reports.

A recipe change is adopted only when it wins at two seeds; this tool lays the evidence out
without re-running anything. Each arm is a list of report folders (``report.json``, and
``diagnose.json`` where ``python -m benchmark.tools.recipe diagnose`` wrote one), such as
a segmentation and an nvs report per seed. Folders are grouped by their training seed; the
two arms must cover the same seeds, and at each seed both must have been scored on the same
test scenes (dataset fingerprints), or the comparison is refused.

    python -m benchmark.tools.compare \\
        --with results/cpu/segmentation-25k-front-seed0 results/cpu/nvs-25k-front-seed0 \\
        --without results/cpu/segmentation-25k-seed0 results/cpu/nvs-25k-seed0

For every metric it prints each seed's value in both arms, the difference, the means over
the seeds, and whether the change is better at every seed (for errors, lower is better).
``--json OUT`` writes the same as JSON (atomically).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from scenefmt import atomic_write_json
from scenefmt.cli_util import OneLineParser, doc_summary, fail

__all__ = ["ARMS", "DEFAULT_METRICS", "compare_arms", "format_comparison", "lower_is_better"]

_PROG = "python -m benchmark.tools.compare"

#: The two arms, in the order they are printed.
ARMS = ("with", "without")

#: What is shown unless ``--metrics all``: the decomposition scores, the novel views and
#: the failure breakdown.
DEFAULT_METRICS = (
    "segmentation.fg_ari",
    "segmentation.ari",
    "segmentation.nv_ari",
    "nvs.psnr",
    "nvs.ssim",
    "nvs.lpips",
    "nvs.depth_abs_rel",
    "diagnose.lost",
    "diagnose.merged",
    "diagnose.own",
    "diagnose.split",
)

_LOWER = {"depth_abs_rel", "depth_rmse", "lpips", "lost", "merged", "split"}


def lower_is_better(name: str) -> bool:
    """Whether a smaller value of metric ``name`` (``protocol.metric``) is the better one."""
    short = name.rsplit(".", 1)[-1]
    return short in _LOWER or "abs_err" in short


class CompareError(ValueError):
    """Folders that cannot be compared; the message says which and how to fix it."""


def _measured_row(report: dict[str, Any], folder: Path, dataset: str | None,
                  variant: str | None) -> dict[str, Any]:  # fmt: skip
    rows = [r for r in report.get("rows", []) if r.get("source") == "measured"]
    if dataset is not None:
        rows = [r for r in rows if r.get("dataset") == dataset]
    if variant is not None:
        rows = [r for r in rows if r.get("variant") == variant]
    elif len(rows) > 1 and any(r.get("variant") == "full" for r in rows):
        rows = [r for r in rows if r.get("variant") == "full"]
    if len(rows) != 1:
        found = sorted({f"{r.get('dataset')}/{r.get('variant')}" for r in rows})
        what = f"{len(rows)} measured rows ({', '.join(found)})" if rows else "no measured row"
        raise CompareError(f"{folder}: {what} for --dataset {dataset or 'any'} --variant "
                           f"{variant or 'any'}; name one with --dataset and --variant")  # fmt: skip
    return rows[0]


def _diagnose_metrics(d: dict[str, Any]) -> dict[str, float | None]:
    out: dict[str, float | None] = {}
    for key in ("lost", "merged", "own"):
        out[f"diagnose.{key}"] = (d.get(key) or {}).get("fraction")
    out["diagnose.split"] = (d.get("splits") or {}).get("split")
    if "own_share" in d:
        out["diagnose.own_share"] = d["own_share"]
    return out


def read_arm(folders: list[str | Path], dataset: str | None = None,
             variant: str | None = None) -> dict[int, dict[str, Any]]:  # fmt: skip
    """An arm's folders, grouped by training seed: ``{seed: {"metrics", "decomposes",
    "steps", "fingerprints", "folders"}}``. Metrics are named ``protocol.metric``."""
    seeds: dict[int, dict[str, Any]] = {}
    for f in folders:
        folder = Path(f)
        path = folder / "report.json" if folder.is_dir() else folder
        if not path.is_file():
            raise CompareError(f"{folder}: no report.json; pass a folder `benchmark run` wrote")
        try:
            report = json.loads(path.read_text())
        except json.JSONDecodeError as err:
            raise CompareError(f"{path}: not JSON ({err.msg} at line {err.lineno})") from err
        if report.get("kind") != "svorf-benchmark-report":
            raise CompareError(f"{path}: not a benchmark report (kind {report.get('kind')!r})")
        seed = (report.get("seeds") or {}).get("train")
        if seed is None:
            raise CompareError(f"{path}: the report records no training seed")
        row = _measured_row(report, path.parent, dataset, variant)
        entry = seeds.setdefault(int(seed), {"metrics": {}, "decomposes": None, "steps": None,
                                             "fingerprints": {}, "folders": []})  # fmt: skip
        entry["folders"].append(str(path.parent))
        protocol = report.get("protocol", "report")
        for k, v in (row.get("metrics") or {}).items():
            entry["metrics"][f"{protocol}.{k}"] = v
        if row.get("test_fingerprint"):
            entry["fingerprints"][row.get("test_dataset", row.get("dataset"))] = row[
                "test_fingerprint"
            ]
        for v in report.get("verdicts") or []:
            if v.get("dataset") == row.get("dataset") and v.get("model") == row.get("model"):
                entry["decomposes"] = bool(v.get("decomposes"))
        for m in report.get("models") or []:
            if m.get("run_key") == row.get("run_key") and m.get("steps_done") is not None:
                entry["steps"] = int(m["steps_done"])
        for diag in (
            path.parent / "diagnose.json",
            path.parent / f"diagnose-{row.get('variant')}.json",
        ):
            if diag.is_file():
                add_diagnose(seeds, int(seed), diag)
                break
    return seeds


def add_diagnose(seeds: dict[int, dict[str, Any]], seed: int, path: str | Path) -> None:
    """Adds a ``diagnose`` JSON's failure breakdown to ``seeds[seed]``; refused where its
    FG-ARI is not the FG-ARI the seed's reports give (then it scored another model)."""
    path = Path(path)
    if seed not in seeds:
        raise CompareError(f"{path}: seed {seed} has no report in this arm")
    if not path.is_file():
        raise CompareError(f"{path}: no such file; pass what `python -m benchmark.tools.recipe "
                           "diagnose` wrote")  # fmt: skip
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise CompareError(f"{path}: not JSON ({err.msg} at line {err.lineno})") from err
    if not isinstance(d, dict) or "lost" not in d:
        raise CompareError(f"{path}: not a failure breakdown (no 'lost')")
    own = (d.get("fg_ari_repairs") or {}).get("fg_ari")
    scored = {k: v for k, v in seeds[seed]["metrics"].items() if k.endswith(".fg_ari")}
    for name, seg in scored.items():
        if own is not None and seg is not None and abs(100 * own - seg) > 0.05:
            raise CompareError(f"{path}: FG-ARI {100 * own:.1f} but seed {seed}'s {name} is "
                               f"{seg:.1f}: it diagnosed another model")  # fmt: skip
    seeds[seed]["metrics"].update(_diagnose_metrics(d))


def _mean(values: list[float | None]) -> float | None:
    if not values or any(v is None for v in values):
        return None
    return sum(values) / len(values)  # type: ignore[arg-type]


def compare_arms(with_: dict[int, dict[str, Any]], without: dict[int, dict[str, Any]],
                 metrics: tuple[str, ...] | None = DEFAULT_METRICS,
                 allow_different_scenes: bool = False) -> dict[str, Any]:  # fmt: skip
    """Per-seed values, differences (with minus without), means and ``better_at_every_seed``
    for each metric that both arms report (``metrics=None``: all of them)."""
    if sorted(with_) != sorted(without):
        raise CompareError(f"the arms cover different seeds: --with {sorted(with_)}, --without "
                           f"{sorted(without)}; pass one folder set per seed to each")  # fmt: skip
    seeds = sorted(with_)
    for s in seeds:
        a, b = with_[s]["fingerprints"], without[s]["fingerprints"]
        for name in sorted(set(a) & set(b)):
            if a[name] != b[name] and not allow_different_scenes:
                raise CompareError(f"seed {s}: the arms were scored on different {name} scenes "
                                   f"({a[name][:12]} vs {b[name][:12]}); pass "
                                   "--allow-different-scenes to compare anyway")  # fmt: skip
    common = set.intersection(*(set(x[s]["metrics"]) for x in (with_, without) for s in seeds))
    names = [m for m in (metrics or sorted(common)) if m in common]
    table: dict[str, Any] = {}
    for name in names:
        w = [with_[s]["metrics"][name] for s in seeds]
        o = [without[s]["metrics"][name] for s in seeds]
        delta = [None if x is None or y is None else x - y for x, y in zip(w, o)]
        sign = -1.0 if lower_is_better(name) else 1.0
        table[name] = {
            "better": "lower" if sign < 0 else "higher",
            "with": dict(zip(seeds, w)),
            "without": dict(zip(seeds, o)),
            "delta": dict(zip(seeds, delta)),
            "mean_with": _mean(w),
            "mean_without": _mean(o),
            "mean_delta": _mean(delta),
            "better_at_every_seed": all(d is not None and sign * d > 0 for d in delta),
        }

    def per_arm(key: str) -> dict[str, dict[int, Any]]:
        return {arm: {s: x[s][key] for s in seeds} for arm, x in zip(ARMS, (with_, without))}

    return {
        "kind": "svorf-arm-comparison",
        "seeds": seeds,
        "folders": per_arm("folders"),
        "decomposes": per_arm("decomposes"),
        "steps": per_arm("steps"),
        "metrics": table,
    }


def _fmt(v: Any, name: str) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    short = name.rsplit(".", 1)[-1]
    if short.endswith("ari") and "." in name and name.startswith(("segmentation", "ablation")):
        return f"{v:.1f}"
    if name.startswith("diagnose.") and short in ("lost", "merged", "own", "own_share"):
        return f"{100 * v:.1f}%"
    if isinstance(v, int) or short == "split":
        return f"{v:.0f}" if float(v).is_integer() else f"{v:.1f}"
    return f"{v:.2f}" if abs(v) >= 10 else f"{v:.3f}"


def format_comparison(res: dict[str, Any]) -> str:
    """The comparison as a plain-text table, one metric per line."""
    seeds = res["seeds"]
    head = (
        ["metric"]
        + [f"s{s} with / without (diff)" for s in seeds]
        + ["mean diff", "better at every seed"]
    )
    lines = [head]
    for name, m in res["metrics"].items():
        cells = [f"{name} ({m['better']} better)"]
        for s in seeds:
            d = m["delta"][s]
            dd = "-" if d is None else ("+" if d >= 0 else "") + _fmt(d, name)
            cells.append(f"{_fmt(m['with'][s], name)} / {_fmt(m['without'][s], name)} ({dd})")
        md = m["mean_delta"]
        cells.append("-" if md is None else ("+" if md >= 0 else "") + _fmt(md, name))
        cells.append(_fmt(m["better_at_every_seed"], name))
        lines.append(cells)
    for key in ("decomposes", "steps"):
        cells = [key] + [" / ".join(_fmt(res[key][a][s], key) for a in ARMS) for s in seeds]
        lines.append(cells + ["", ""])
    widths = [max(len(r[i]) for r in lines) for i in range(len(head))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in lines)


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmark.tools.compare --with DIR... --without DIR...``; exit status."""
    ap = OneLineParser(prog=_PROG, description=doc_summary(__doc__))
    ap.add_argument("--with", dest="with_", nargs="+", required=True, metavar="DIR",
                    help="report folders of the arm with the change, one or more per seed")  # fmt: skip
    ap.add_argument("--without", nargs="+", required=True, metavar="DIR",
                    help="report folders of the control arm, the same seeds")  # fmt: skip
    ap.add_argument("--dataset", help="the measured rows' dataset, where a report has several")
    ap.add_argument("--variant", help="the measured rows' variant, where a report has several "
                    "(default: 'full' where present)")  # fmt: skip
    ap.add_argument("--metrics", default="default",
                    help="'default' (segmentation, novel views, failure breakdown), 'all', or "
                    "a comma-separated list of protocol.metric names")  # fmt: skip
    ap.add_argument("--allow-different-scenes", action="store_true",
                    help="compare arms scored on different test scenes (refused otherwise)")  # fmt: skip
    for arm in ARMS:
        ap.add_argument(f"--diagnose-{arm}", action="append", default=[], metavar="SEED=FILE",
                        help=f"a failure breakdown of the {arm!r} arm's model at SEED, where its "
                        "report folder holds none (diagnose.json or diagnose-VARIANT.json)")  # fmt: skip
    ap.add_argument("--json", metavar="OUT", help="also write the comparison as JSON to OUT")
    try:
        a = ap.parse_args(argv)
    except SystemExit as e:
        return int(e.code or 0)
    metrics: tuple[str, ...] | None
    if a.metrics == "default":
        metrics = DEFAULT_METRICS
    elif a.metrics == "all":
        metrics = None
    else:
        metrics = tuple(m.strip() for m in a.metrics.split(",") if m.strip())
    try:
        arms = [read_arm(a.with_, a.dataset, a.variant), read_arm(a.without, a.dataset, a.variant)]
        for arm, seeds in zip(ARMS, arms):
            for spec in getattr(a, f"diagnose_{arm}"):
                seed, sep, file = spec.partition("=")
                if not sep or not seed.strip().isdigit():
                    raise CompareError(f"--diagnose-{arm} {spec!r}: expected SEED=FILE, such as "
                                       "1=results/cpu/ablation-25k-seed1/diagnose-full.json")  # fmt: skip
                add_diagnose(seeds, int(seed), file)
        res = compare_arms(*arms, metrics, a.allow_different_scenes)
    except CompareError as err:
        return fail(_PROG, str(err))
    if not res["metrics"]:
        return fail(_PROG, f"no metric of --metrics {a.metrics} is in both arms; try --metrics all")
    print(format_comparison(res))
    if a.json:
        atomic_write_json(Path(a.json), res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
