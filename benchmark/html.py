"""One static HTML page per report folder (``index.html``): tables and figures.

Where this sits: after a protocol writes ``report.json`` and its PNG figures, it
calls :func:`write_index` on the folder. The page is self-contained (inline CSS,
no script, images referenced by relative file name), so it opens from disk or
any static file server, and renders headless::

    chromium --headless --no-sandbox --disable-gpu --window-size=1400,2400 \
        --screenshot=shot.png file:///abs/path/to/report/index.html

(:func:`render_screenshot` runs exactly that.)
"""

from __future__ import annotations

import html
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

from benchmark.display import (
    LEGEND,
    fmt_metric,
    fmt_seconds,
    metric_label,
    reason_text,
    table_description,
    table_title,
)
from benchmark.paper_numbers import PAPER_TABLES
from scenefmt import atomic_write_bytes

__all__ = [
    "chromium_binary",
    "fmt_value",
    "metric_columns",
    "render_html",
    "render_screenshot",
    "write_index",
]

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:24px;
color:#222;max-width:1300px}
h1{font-size:22px}h2{font-size:18px;margin-top:28px;border-bottom:1px solid #ddd}
table{border-collapse:collapse;margin:8px 0 16px 0;font-size:13px}
th,td{border:1px solid #ccc;padding:3px 8px;text-align:right}
th{background:#f0f0f0}td.l,th.l{text-align:left}
tr.paper td{color:#555;background:#fafafa}tr.measured td{background:#eef5ff}
tr.baseline td{background:#fff4e5;font-style:italic}
.warn{background:#fdecea;border:1px solid #f5c2c0;padding:8px 12px;margin:8px 0}
.ok{background:#e8f5e9;border:1px solid #b7dfb9;padding:8px 12px;margin:8px 0}
.meta td{text-align:left}img{max-width:100%;border:1px solid #ddd;margin:6px 0}
code{background:#f4f4f4;padding:0 3px}.id{color:#777;font-size:12px}
"""


def fmt_value(v: Any, metric: str = "") -> str:
    """A metric value for a table cell, HTML-escaped (:func:`benchmark.display.fmt_metric`:
    ARI family 0-100 with one decimal, PSNR in dB, ...; null -> an em dash)."""
    return html.escape(fmt_metric(metric, v))


def _th(metric: str) -> str:
    """A metric's column header: its readable name, the stored name and unit on hover."""
    from benchmark.schema import METRIC_UNITS

    unit = METRIC_UNITS.get(metric, "")
    tip = f"{metric} in report.json" + (f"; stored as {unit}" if unit else "")
    return f"<th title='{_e(tip)}'>{_e(metric_label(metric))}</th>"


def _e(x: Any) -> str:
    return html.escape(str(x))


_YES_NO = {True: "yes", False: "<b>no</b>", None: "cannot tell"}
_HOLDS = {True: "holds", False: "does not hold", None: "n/a"}


def metric_columns(table: str, rows: list[dict[str, Any]]) -> list[str]:
    """Column order of a table: the paper's columns first, then the rest in schema order.

    (Report JSON is written with sorted keys, so the dict order of a row is alphabetical.)
    """
    from benchmark.schema import METRIC_UNITS

    present = {m for r in rows for m in r["metrics"]}
    cols: list[str] = []
    for prow in PAPER_TABLES.get(table, {}).get("rows", [])[:1]:
        cols.extend(m for m in prow["metrics"] if m in present)
    cols.extend(m for m in METRIC_UNITS if m in present and m not in cols)
    cols.extend(sorted(present - set(cols)))
    return cols


def _rows_table(rows: list[dict[str, Any]], scale: str) -> str:
    metrics = metric_columns(rows[0]["table"], rows) if rows else []
    head = "".join(_th(m) for m in metrics)
    out = [
        (
            "<table><tr><th class=l>model</th><th class=l>dataset</th><th class=l>source</th>"
            f"<th>n</th>{head}<th class=l>notes</th></tr>"
        )
    ]
    for r in rows:
        src = r["source"]
        label = src if src != "measured" else f"measured ({scale})"
        cells = []
        for m in metrics:
            if m not in r["metrics"]:  # the row has no such metric: an empty cell
                cells.append("<td></td>")
                continue
            v = r["metrics"][m]
            title = reason_text(r["null_reasons"].get(m, "")) if v is None else ""
            cells.append(f"<td title='{_e(title)}'>{fmt_value(v, m)}</td>")
        notes = []
        if "pass" in r:
            notes.append("pass" if r["pass"] else "<b>FAIL</b>")
        if "within_tolerance" in r:
            notes.append("within tolerance" if r["within_tolerance"] else "<b>beyond tolerance</b>")
        if r.get("note"):
            notes.append(_e(r["note"]))
        if r.get("imported_from"):
            src_of = r["imported_from"]
            notes.append(
                f"taken from {_e(str(src_of.get('report')))} ({_e(str(src_of.get('created_utc')))})"
            )
        for m, why in sorted(r["null_reasons"].items()):
            notes.append(f"{_e(metric_label(m))}: {_e(reason_text(why)[:120])}")
        out.append(
            f"<tr class={_e(src)}><td class=l>{_e(r['model'])}</td><td class=l>{_e(r['dataset'])}</td>"
            f"<td class=l>{_e(label)}</td><td>{_e(r.get('n_scenes', r.get('n_cases', '')))}</td>{''.join(cells)}"
            f"<td class=l>{'<br>'.join(notes)}</td></tr>"
        )
    out.append("</table>")
    return "".join(out)


def _reused(model: dict[str, Any]) -> str:
    """The models table's "reused" cell: True / False, or the report it was taken from."""
    where = model.get("imported_from")
    if where:
        return f"from {_e(str(where.get('report')))}"
    return str(model["reused"])


def _verdicts(report: dict[str, Any]) -> str:
    """A headline saying plainly whether the measured models decompose, and a table."""
    vs = report.get("verdicts") or []
    if not vs:
        return ""
    yes = [v for v in vs if v.get("decomposes")]
    no = [v for v in vs if v.get("decomposes") is False]
    scale = report["scale"]
    if no and not yes:
        head = (
            f"<div class=warn><b>At scale '{_e(scale)}' no measured model decomposes the scenes</b> "
            f"(FG-ARI not far above the chance baselines or the scene-shuffle control, see "
            f"below). These numbers test the "
            f"pipeline, not sVORF's accuracy.</div>"
        )
    elif no:
        head = (
            f"<div class=warn><b>{len(no)} of {len(vs)} measured rows do not decompose</b> at "
            f"scale '{_e(scale)}' (see below).</div>"
        )
    elif len(yes) < len(vs):
        head = (
            f"<div class=warn><b>{len(vs) - len(yes)} of {len(vs)} measured rows could not be "
            f"judged</b> at scale '{_e(scale)}' (see below).</div>"
        )
    else:
        head = f"<div class=ok><b>Every measured row decomposes</b> at scale '{_e(scale)}'.</div>"
    split = [v for v in yes if v.get("background_split")]
    if split:
        head += (
            f"<div class=warn><b>{len(split)} of the rows that decompose split the background"
            f"</b> among their slots: ARI (every pixel) below the best chance baseline's + the "
            f"margin. FG-ARI, which the verdict uses, does not score background pixels.</div>"
        )
    out = [
        head,
        (
            "<table><tr><th class=l>table</th><th class=l>model</th><th class=l>dataset</th>"
            "<th>FG-ARI</th><th>best chance</th><th>other scene's slots</th>"
            "<th class=l>decomposes</th><th class=l>verdict</th></tr>"
        ),
    ]
    for v in vs:
        cls = "measured" if v.get("decomposes") else "baseline"
        out.append(
            f"<tr class={cls}><td class=l>{_e(table_title(v.get('table', '')))}</td>"
            f"<td class=l>{_e(v['model'])}</td>"
            f"<td class=l>{_e(v['dataset'])}</td><td>{fmt_value(v.get('fg_ari'), 'fg_ari')}</td>"
            f"<td>{fmt_value(v.get('chance_fg_ari'), 'fg_ari')}</td>"
            f"<td>{fmt_value(v.get('fg_ari_shuffled'), 'fg_ari')}</td>"
            f"<td class=l>{_YES_NO.get(v.get('decomposes'), '')}</td>"
            f"<td class=l>{_e(v['message'])}</td></tr>"
        )
    out.append("</table>")
    return "".join(out)


def _held(held: bool | None, none: str = "n/a") -> str:
    return "holds" if held else (none if held is None else "<b>does not hold</b>")


def _orderings(report: dict[str, Any]) -> str:
    """The paper's comparisons and whether the measured rows keep them."""
    os_ = report.get("orderings") or []
    if not os_:
        return ""
    out = [
        (
            "<h2>The paper's comparisons</h2><table><tr><th class=l>table</th>"
            "<th class=l>claim</th><th class=l>metric</th><th>A</th><th>B</th><th>margin</th>"
            "<th>seed spread</th><th>mean over seeds</th><th class=l>paper</th>"
            "<th class=l>measured</th><th class=l>on the mean</th></tr>"
        )
    ]
    for o in os_:
        held = o["measured_holds"]
        cls = "measured" if held else "baseline"
        spread = o.get("seed_spread")
        mean, mean_holds = o.get("seed_mean"), o.get("seed_mean_holds")
        n = len(o.get("seed_margins") or {})
        out.append(
            f"<tr class={cls}><td class=l>{_e(table_title(o['table']))}</td>"
            f"<td class=l>{_e(o['claim'])}</td><td class=l>{_e(metric_label(o['metric']))}</td>"
            f"<td>{fmt_value(o['a']['measured'], o['metric'])}</td>"
            f"<td>{fmt_value(o['b']['measured'], o['metric'])}</td>"
            f"<td>{fmt_value(o['margin'], o['metric'])}</td>"
            f"<td>{fmt_value(spread, o['metric']) if spread is not None else '-'}</td>"
            f"<td>{fmt_value(mean, o['metric']) + f' ({n})' if mean is not None else '-'}</td>"
            f"<td class=l>{_HOLDS.get(o['paper_holds'], '')}</td>"
            f"<td class=l>{_held(held)}</td><td class=l>{_held(mean_holds, '-')}</td></tr>"
        )
    out.append("</table>")
    return "".join(out)


def render_html(report: dict[str, Any]) -> str:
    """The page for one report dict (pure function; see :func:`write_index`)."""
    scale = report["scale"]
    title = f"sVORF benchmark: {report['protocol']} ({scale})"
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>{_e(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{_e(title)}</h1>",
        (
            f"<p>{_e(LEGEND)} PSNR in dB; SSIM and LPIPS unitless. An empty cell: the row has "
            "no such metric; \u2014: no value (the reason is in the row's notes). Hover a "
            "column header for the name and unit stored in <code>report.json</code>.</p>"
        ),
    ]
    parts.append(_verdicts(report))
    if report.get("status") != "complete":
        parts.append("<div class=warn>Report status: partial (some rows are missing).</div>")
    hw = report["hardware"]
    git = report["git"]
    wall = report["wall_time_s"]
    meta = [
        ("protocol / scale", f"{report['protocol']} / {scale}"),
        ("created (UTC)", report["created_utc"]),
        ("git commit", git.get("commit") or f"unknown ({git.get('reason')})"),
        (
            "hardware",
            f"{hw['cpu_model']}, {hw['cpu_cores']} cores, device {hw['device']}"
            + (f" ({hw['gpu_name']})" if hw.get("gpu_name") else ""),
        ),
        ("torch / python", f"{hw['torch_version']} / {hw['python_version']}"),
        (
            "wall time",
            ", ".join(
                f"{k} {fmt_seconds(wall[k])}" for k in ("data", "training", "evaluation", "total")
            ),
        ),
        ("seeds", ", ".join(f"{k}={v}" for k, v in report["seeds"].items())),
    ]
    parts.append("<table class=meta>")
    parts.extend(f"<tr><th class=l>{_e(k)}</th><td>{_e(v)}</td></tr>" for k, v in meta)
    parts.append("</table>")
    parts.append(_orderings(report))
    if report.get("notes"):
        parts.append("<h2>Notes</h2><ul>")
        parts.extend(f"<li>{_e(n)}</li>" for n in report["notes"])
        parts.append("</ul>")

    # Rows grouped by table, in first-seen order.
    tables: dict[str, list[dict[str, Any]]] = {}
    for r in report["rows"]:
        tables.setdefault(r["table"], []).append(r)
    for table, rows in tables.items():
        parts.append(
            f"<h2>{_e(table_title(table))}</h2><p>{_e(table_description(table))} "
            f"<span class=id>(table id in report.json: <code>{_e(table)}</code>)</span></p>"
        )
        parts.append(_rows_table(rows, scale))

    if report.get("figures"):
        parts.append("<h2>Figures</h2>")
        for f in report["figures"]:
            parts.append(f"<div><p><code>{_e(f)}</code></p><img src='{_e(f)}' alt='{_e(f)}'></div>")

    parts.append(
        "<h2>Datasets</h2><table><tr><th class=l>name</th><th class=l>split</th>"
        "<th>scenes</th><th>res.</th><th class=l>source</th><th class=l>fingerprint</th></tr>"
    )
    for d in report["datasets"]:
        parts.append(
            f"<tr><td class=l>{_e(d['name'])}</td><td class=l>{_e(d['split'])}</td><td>{d['n_scenes']}</td>"
            f"<td>{d['resolution']}</td><td class=l>{_e(d['source'])}</td><td class=l><code>{_e(d['fingerprint'])}</code></td></tr>"
        )
    parts.append("</table>")
    if report["models"]:
        parts.append(
            "<h2>Models</h2><table><tr><th class=l>run key</th><th class=l>variant</th>"
            "<th class=l>train data</th><th>seed</th><th>steps</th><th>training time</th>"
            "<th class=l>reused</th></tr>"
        )
        for m in report["models"]:
            parts.append(
                f"<tr><td class=l><code>{_e(m['run_key'])}</code></td><td class=l>{_e(m['variant'])}</td>"
                f"<td class=l>{_e(m['train_dataset'])}</td><td>{m['seed']}</td>"
                f"<td>{_e(str(m.get('steps_done', '')))}</td><td>{fmt_seconds(m['train_wall_s'])}</td><td class=l>{_reused(m)}</td></tr>"
            )
        parts.append(
            "</table><p>Full model and training configs are in <code>report.json</code>.</p>"
        )
    parts.append("<h2>Scale settings</h2><pre>")
    parts.append(_e(_pretty(report.get("scale_settings", {}))))
    parts.append("</pre></body></html>\n")
    return "".join(parts)


def _pretty(obj: Any) -> str:
    import json

    return json.dumps(obj, indent=2, sort_keys=True)


def write_index(folder: str | os.PathLike, report: dict[str, Any]) -> Path:
    """Write ``index.html`` for ``report`` into ``folder`` (atomically)."""
    path = Path(folder) / "index.html"
    atomic_write_bytes(path, render_html(report).encode())
    return path


def chromium_binary() -> str | None:
    """Path of a headless-capable Chromium (or Chrome), or None if none is installed."""
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        found = shutil.which(name)
        if found:
            return found
    return None


def render_screenshot(
    index_html: str | os.PathLike,
    png: str | os.PathLike,
    size: tuple[int, int] = (1400, 2400),
    timeout_s: float = 120.0,
) -> Path:
    """Render a page with headless Chromium into a PNG.

    Raises:
        FileNotFoundError: If no Chromium binary is installed (``apt-get install -y chromium``).
        RuntimeError: If Chromium fails or writes no file.
    """
    exe = chromium_binary()
    if exe is None:
        raise FileNotFoundError(
            "no chromium binary on PATH; install it with: apt-get install -y chromium"
        )
    png = Path(png).resolve()
    url = Path(index_html).resolve().as_uri()
    cmd = [
        exe,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--hide-scrollbars",
        f"--window-size={size[0]},{size[1]}",
        f"--screenshot={png}",
        url,
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, check=False)
    if not png.is_file():
        raise RuntimeError(
            f"chromium wrote no screenshot (rc={proc.returncode}): {proc.stderr[-2000:]}"
        )
    return png
