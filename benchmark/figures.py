"""PNG figures beside each report (matplotlib, Agg backend; no display needed).

Where this sits: protocols call these after their rows are final. The
qualitative grid shows one test scene per dataset (segmentation / nvs); the bar
chart compares measured rows with the paper's (ablation / generalization). Every
function writes atomically and returns the file name relative to the report
folder, which goes into the report's ``figures`` list. Numbers and names on the figures
come from :mod:`benchmark.display`, as in the tables (ARI family on the paper's 0-100 scale).
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Any

import numpy as np

from benchmark.display import (
    ARI_FAMILY,
    fmt_ari,
    fmt_memory,
    fmt_metric,
    fmt_ratio,
    fmt_seconds,
    metric_label,
    table_title,
)
from scenefmt import atomic_write_bytes

__all__ = [
    "bar_chart",
    "label_colors",
    "pareto_chart",
    "qualitative_grid",
    "speed_chart",
    "speed_compare_chart",
    "stability_chart",
    "tradeoff_chart",
    "training_chart",
]


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    _plt().close(fig)
    atomic_write_bytes(path, buf.getvalue())


def label_colors(labels: np.ndarray) -> np.ndarray:
    """Integer label map ``[H, W]`` -> RGB float ``[H, W, 3]`` (label 0 dark grey).

    The palette is fixed per label value so the same slot / instance keeps its
    colour across views.
    """
    rng = np.random.default_rng(12345)
    palette = rng.uniform(0.15, 1.0, size=(256, 3))
    palette[0] = (0.2, 0.2, 0.2)
    return palette[np.asarray(labels, dtype=np.int64) % 256]


def qualitative_grid(
    path: str | os.PathLike,
    title: str,
    gt_rgb: np.ndarray,
    pred_rgb: np.ndarray,
    pred_labels: np.ndarray,
    gt_labels: np.ndarray,
    pred_depth: np.ndarray,
    gt_depth: np.ndarray | None,
    input_view: int = 0,
) -> str:
    """One scene, every view: ground truth, render, masks and depth.

    Rows: ground-truth RGB, rendered RGB (the input view's render is the
    reconstruction, the others are novel views), predicted slot masks,
    ground-truth instance masks, rendered depth, ground-truth depth.

    Args:
        path: Output PNG.
        title: Figure title (dataset, model, scale).
        gt_rgb: Float ``[V, H, W, 3]`` in [0, 1].
        pred_rgb: Float ``[V, H, W, 3]`` in [0, 1].
        pred_labels: Integer ``[V, H, W]`` arg-max slot per pixel.
        gt_labels: Integer ``[V, H, W]`` instance ids (0 = background).
        pred_depth: Float ``[V, H, W]`` rendered planar depth, world units.
        gt_depth: Float ``[V, H, W]`` or None; inf/0 = background.
        input_view: The view the model was conditioned on.

    Returns:
        The file name of ``path``.
    """
    plt = _plt()
    path = Path(path)
    n_views = gt_rgb.shape[0]
    finite = np.isfinite(gt_depth) & (gt_depth > 0) if gt_depth is not None else None
    vals = [pred_depth[np.isfinite(pred_depth)]]
    if finite is not None and finite.any():
        vals.append(gt_depth[finite])
    allv = np.concatenate([v.ravel() for v in vals]) if vals else np.array([0.0, 1.0])
    lo, hi = (np.percentile(allv, 1), np.percentile(allv, 99)) if allv.size else (0.0, 1.0)
    if not hi > lo:
        hi = lo + 1.0
    rows = [
        ("GT RGB", [np.clip(gt_rgb[v], 0, 1) for v in range(n_views)], None),
        ("render", [np.clip(pred_rgb[v], 0, 1) for v in range(n_views)], None),
        ("pred. slots", [label_colors(pred_labels[v]) for v in range(n_views)], None),
        ("GT masks", [label_colors(gt_labels[v]) for v in range(n_views)], None),
        # One depth convention everywhere (svorf render, generate preview): near = bright
        # yellow, far = dark, no hit = black; the colour bar says which is which.
        ("pred. depth", [pred_depth[v] for v in range(n_views)], "viridis_r"),
    ]
    if gt_depth is not None:
        shown = [np.where(finite[v], gt_depth[v], np.nan) for v in range(n_views)]
        rows.append(("GT depth", shown, "viridis_r"))
    fig, axes = plt.subplots(
        len(rows), n_views, figsize=(1.6 * n_views + 0.6, 1.6 * len(rows) + 0.5), squeeze=False
    )
    depth_im = None
    for r, (name, images, cmap) in enumerate(rows):
        for v in range(n_views):
            ax = axes[r][v]
            if cmap is None:
                ax.imshow(images[v], interpolation="nearest")
            else:
                cm = plt.get_cmap(cmap).copy()
                cm.set_bad("black")
                depth_im = ax.imshow(images[v], cmap=cm, vmin=lo, vmax=hi, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(
                    f"input (view {v})" if v == input_view else f"novel view {v}", fontsize=8
                )
            if v == 0:
                ax.set_ylabel(name, fontsize=8)
    if depth_im is not None:
        bar = fig.colorbar(depth_im, ax=axes[-1].tolist(), fraction=0.04, pad=0.02)
        bar.set_label("depth (world units): near = yellow, far = dark; black = no hit", fontsize=6)
        bar.ax.tick_params(labelsize=6)
    fig.suptitle(title, fontsize=9)
    _save(fig, path)
    return path.name


def bar_chart(
    path: str | os.PathLike,
    title: str,
    groups: list[dict[str, Any]],
    metrics: list[str],
    chance: dict[str, float] | None = None,
) -> str:
    """Grouped bars of measured vs paper values, one panel per metric (ARI family, on the
    paper's 0-100 scale; each bar is labelled with its value).

    Args:
        path: Output PNG.
        title: Figure title.
        groups: One dict per model row: ``{"label": str, "paper": {metric: v|None},
            "measured": {metric: v|None}}`` and optionally ``"chance": {metric: v}``,
            the best chance baseline on that row's test set (a red tick over the group).
        metrics: Metric names to plot, one panel each.
        chance: Optional ``{metric: value}`` drawn as a dashed line across all groups.

    Returns:
        The file name of ``path``.
    """
    plt = _plt()
    path = Path(path)
    n = len(groups)
    fig, axes = plt.subplots(
        1, len(metrics), figsize=(max(4.0, 0.9 * n + 1.5) * len(metrics), 3.8), squeeze=False
    )
    x = np.arange(n)
    for ax, metric in zip(axes[0], metrics, strict=True):
        paper = [g["paper"].get(metric) for g in groups]
        meas = [g["measured"].get(metric) for g in groups]
        pv = [np.nan if v is None else v for v in paper]
        mv = [np.nan if v is None else v for v in meas]
        ax.bar(x - 0.2, pv, 0.4, label="paper", color="#9e9e9e")
        ax.bar(x + 0.2, mv, 0.4, label="measured", color="#1f77b4")
        for off, vals, missing in ((-0.2, paper, "not in paper"), (0.2, meas, "no value")):
            for xi, v in zip(x, vals, strict=True):
                text = missing if v is None else fmt_metric(metric, v)
                ax.text(xi + off, max(v or 0.0, 0.0) + 0.5, text, ha="center", va="bottom",
                        fontsize=6, rotation=90)  # fmt: skip
        if chance and chance.get(metric) is not None:
            ax.axhline(chance[metric], color="#d62728", ls="--", lw=1, label="chance baseline")
        ticks = [(xi, g.get("chance", {}).get(metric)) for xi, g in zip(x, groups, strict=True)]
        ticks = [(xi, v) for xi, v in ticks if v is not None]
        if ticks:
            ax.hlines(
                [v for _, v in ticks],
                [xi - 0.45 for xi, _ in ticks],
                [xi + 0.45 for xi, _ in ticks],
                colors="#d62728",
                linestyles="--",
                lw=1.2,
                label="best chance baseline (same test set)",
            )
        ax.set_xticks(x)
        ax.set_xticklabels([g["label"] for g in groups], rotation=35, ha="right", fontsize=7)
        scale = " (0-100)" if metric in ARI_FAMILY else ""
        ax.set_title(metric_label(metric) + scale, fontsize=9)
        # Headroom above 100 keeps the legend clear of the bars.
        ax.set_ylim(min(0.0, np.nanmin(mv + pv + [0.0]) - 5), 122.0)
        ax.set_yticks([0, 20, 40, 60, 80, 100])
        ax.legend(fontsize=7, loc="upper center", ncol=3, frameon=False)
    fig.suptitle(title, fontsize=10)
    _save(fig, path)
    return path.name


def speed_chart(path: str | os.PathLike, rows: list[dict[str, Any]], scale: str) -> str:
    """Memory and epoch time of tab:time (Table 8): the paper's models beside the measured
    sVORF.

    Args:
        path: Output PNG.
        rows: report rows (those of table ``tab:time`` are drawn).
        scale: the measured scale (for labels).

    Returns:
        The file name of ``path``.
    """
    plt = _plt()
    path = Path(path)
    sel = [r for r in rows if r["table"] == "tab:time"]
    labels = [
        r["model"] + (f"\n(measured, {scale})" if r["source"] == "measured" else "\n(paper)")
        for r in sel
    ]
    colors = ["#1f77b4" if r["source"] == "measured" else "#9e9e9e" for r in sel]
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    for ax, metric, unit in zip(axes, ("memory_gb", "epoch_time_s"), ("GB", "s"), strict=True):
        vals = [r["metrics"].get(metric) for r in sel]
        ax.bar(range(len(sel)), [np.nan if v is None else v for v in vals], color=colors)
        for i, v in enumerate(vals):
            if v is not None:
                ax.text(i, v, fmt_metric(metric, v), ha="center", va="bottom", fontsize=7)
        ax.set_xticks(range(len(sel)))
        ax.set_xticklabels(labels, rotation=30, ha="right", fontsize=7)
        ax.set_title(f"{metric_label(metric)} ({unit})", fontsize=9)
    fig.suptitle(
        f"{table_title('tab:time')}: training memory and one CLEVR-567 epoch at batch 1 "
        "(paper: V100)",
        fontsize=10,
    )
    _save(fig, path)
    return path.name


def _ratio_text(ratio: dict[str, Any], k: str) -> str:
    """``k`` of a ratio row as "step time ratio 2.504x (paper 2.56x, target 3x)" (3 decimals:
    a ratio just below its target must not print as the target)."""
    v, paper, goal = ratio["metrics"].get(k), ratio.get("paper", {}), ratio.get("targets", {})
    extra = []
    if k in paper:
        extra.append(f"paper {fmt_ratio(paper[k])}")
    if k in goal:
        extra.append(f"target {goal[k]:g}x")
    tail = f" ({', '.join(extra)})" if extra else ""
    return f"{metric_label(k)} " + ("no value" if v is None else fmt_ratio(v, 3)) + tail


def speed_compare_chart(path: str | os.PathLike, rows: list[dict[str, Any]], scale: str) -> str:
    """sVORF against the uORF-style configuration (table ``speed_vs_uorf``), one run.

    Left: median training step time; right: peak memory and the memory the training steps
    add (``train_memory_mb``), one pair of bars per compared batch. The title gives the
    measured ratios of each batch beside the paper's (Table 8) and the targets, from
    the ratio rows.

    Args:
        path: Output PNG.
        rows: report rows (those of table ``speed_vs_uorf`` are drawn).
        scale: the measured scale (for labels).

    Returns:
        The file name of ``path``.
    """
    plt = _plt()
    path = Path(path)
    sel = [r for r in rows if r["table"] == "speed_vs_uorf" and r.get("variant") != "ratio"]
    ratios = [r for r in rows if r["table"] == "speed_vs_uorf" and r.get("variant") == "ratio"]
    labels = [r["model"].replace(" (", "\n(").replace(", batch", "\nbatch") for r in sel]
    colors = ["#1f77b4" if r.get("variant") == "full" else "#ff7f0e" for r in sel]
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.0))
    ax = axes[0]
    vals = [r["metrics"].get("step_time_s") for r in sel]
    ax.bar(range(len(sel)), [np.nan if v is None else v for v in vals], color=colors)
    for i, v in enumerate(vals):
        ax.text(
            i, v or 0.0, "no value" if v is None else fmt_seconds(v), ha="center", va="bottom",
            fontsize=7,
        )  # fmt: skip
    ax.set_title("median training step (s)", fontsize=9)
    ax = axes[1]
    x = np.arange(len(sel))
    bars = (
        (-0.27, "peak_memory_mb", ""),
        (0.0, "train_memory_mb", "//"),
        (0.27, "tensor_peak_mb", ".."),
    )
    for off, key, hatch in bars:
        vals = [r["metrics"].get(key) for r in sel]
        ax.bar(x + off, [np.nan if v is None else v for v in vals], 0.27, color=colors,
               hatch=hatch, edgecolor="k", lw=0.5, label=metric_label(key))  # fmt: skip
        for i, v in enumerate(vals):
            ax.text(i + off, v or 0.0, "no value" if v is None else fmt_memory(v, ""),
                    ha="center", va="bottom", fontsize=6)  # fmt: skip
    ax.legend(fontsize=7, frameon=False)
    ax.set_title("memory (MiB): process peak / added by training / tensor peak", fontsize=9)
    for ax in axes:
        ax.set_xticks(range(len(sel)))
        # Long configuration names: rotated so neighbouring labels do not overlap.
        ax.set_xticklabels(labels, fontsize=6, rotation=30, ha="right")
    title = f"sVORF vs uORF-style configuration of the same code ({scale}, one run)"
    for ratio in ratios:
        title += f"\nbatch {ratio.get('batch_scenes')}: " + "; ".join(
            _ratio_text(ratio, k) for k in ratio["metrics"]
        )
    fig.suptitle(title, fontsize=9, y=1.02 + 0.03 * len(ratios))
    _save(fig, path)
    return path.name


def stability_chart(path: str | os.PathLike, rows: list[dict[str, Any]]) -> str:
    """Log-scale largest error per stress case (the max over its ``max_*`` metrics: rgb,
    acc, relative depth, slot masks, relative loss), coloured by table; failures in red."""
    plt = _plt()
    path = Path(path)
    colors = {"stability": "#1f77b4", "stability_compose": "#2ca02c", "stability_loss": "#9467bd"}
    names = [r["model"] for r in rows]
    fig, ax = plt.subplots(figsize=(max(11, 0.28 * len(rows)), 4.4))
    x = np.arange(len(rows))
    vals = []
    for r in rows:
        errs = [
            v for k, v in r["metrics"].items() if k.startswith("max_") and k != "max_abs_err_depth"
        ]
        vals.append(np.nan if any(v is None for v in errs) or not errs else max(errs))
    ax.bar(
        x,
        [max(v, 1e-12) if np.isfinite(v) else np.nan for v in vals],
        0.7,
        color=[colors.get(r["table"], "#7f7f7f") for r in rows],
    )
    for t, c in colors.items():
        if any(r["table"] == t for r in rows):
            ax.bar([np.nan], [np.nan], color=c, label=table_title(t))
    for i, r in enumerate(rows):
        if not r.get("pass", True):
            ax.text(i, 1.5e-12, "FAIL", color="#d62728", ha="center", fontsize=7, rotation=90)
        elif vals[i] == 0:
            ax.text(i, 1.5e-12, "0", ha="center", va="bottom", fontsize=7)
    ax.axhline(1e-4, color="#d62728", ls="--", lw=1, label="tolerance 1e-4")
    ax.set_yscale("log")
    ax.set_ylim(1e-12, 1.0)
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=60, ha="right", fontsize=6)
    ax.legend(fontsize=7)
    ax.set_title(
        "largest error per stress case vs its float64 reference (rgb, acc, depth / max t, "
        "slot masks, loss; floored at 1e-12 for display)",
        fontsize=9,
    )
    _save(fig, path)
    return path.name


def tradeoff_chart(
    path: str | os.PathLike,
    rows: list[dict[str, Any]],
    scale: str,
    rgb_tolerance: float,
    floor: float = 1e-8,
) -> str:
    """Time-vs-error curves of the ``tradeoff`` protocol, one line per knob.

    One column per weight set (``rows[i]["weights"]``); top: rgb max |diff|, bottom: depth
    mean |diff|, both on a log axis against the speed-up over the knob-free baseline.
    Every point is labelled with its setting; exact zeros (the off settings and those equal
    to the baseline by construction) are hollow, unlabelled markers at ``floor``.

    Args:
        path: Output PNG.
        rows: tradeoff rows (``knob``, ``setting``, ``weights``, ``reference`` and the
            metrics ``speedup``, ``rgb_max_err``, ``depth_mean_err``).
        scale: the measured scale (for the title).
        rgb_tolerance: drawn as a dashed line on the rgb panels.
        floor: display value of an error of exactly 0.

    Returns:
        The file name of ``path``.
    """
    plt = _plt()
    path = Path(path)
    sets = list(dict.fromkeys(r["weights"] for r in rows))
    knobs = list(dict.fromkeys(r["knob"] for r in rows if not r.get("reference")))
    colors = {k: plt.get_cmap("tab10")(i % 10) for i, k in enumerate(knobs)}
    panels = (("rgb_max_err", "rgb max |diff|"), ("depth_mean_err", "depth mean |diff| (world)"))
    fig, axes = plt.subplots(
        len(panels), len(sets), figsize=(6.2 * len(sets), 4.2 * len(panels)), squeeze=False
    )
    for j, w in enumerate(sets):
        sel = [r for r in rows if r["weights"] == w]
        for i, (metric, ylabel) in enumerate(panels):
            ax = axes[i][j]
            for knob in knobs:
                pts = [r for r in sel if r["knob"] == knob]
                xy = [
                    (r["metrics"].get("speedup"), r["metrics"].get(metric), r["setting"])
                    for r in pts
                    if r["metrics"].get("speedup") is not None
                    and r["metrics"].get(metric) is not None
                ]
                if not xy:
                    continue
                xs = [x for x, _, _ in xy]
                ys = [max(y, floor) for _, y, _ in xy]
                ax.plot(xs, ys, "-o", color=colors[knob], ms=4, lw=1.2, label=knob)
                for x, y, (_, raw, text) in zip(xs, ys, xy, strict=True):
                    if raw == 0:  # off / exact settings pile up at the floor: hollow, unlabelled
                        ax.plot([x], [y], "o", ms=6, mfc="white", mec=colors[knob])
                        continue
                    ax.annotate(
                        text.split(" (")[0],
                        (x, y),
                        textcoords="offset points",
                        xytext=(3, 3),
                        fontsize=6,
                        color=colors[knob],
                    )
            ref = [r for r in sel if r.get("reference")]
            if ref:
                ax.plot([1.0], [floor], "k*", ms=9, label="baseline (error 0)")
            if metric == "rgb_max_err":
                ax.axhline(
                    rgb_tolerance,
                    color="#d62728",
                    ls="--",
                    lw=1,
                    label=f"tolerance {rgb_tolerance:g}",
                )
            ax.axvline(1.0, color="#9e9e9e", ls=":", lw=1)
            ax.set_yscale("log")
            ax.set_xlabel("speed-up over the knob-free baseline (x, >1 = faster)", fontsize=8)
            ax.set_ylabel(f"{ylabel}, 0 drawn at {floor:g}", fontsize=8)
            ax.set_title(f"{w} weights: {ylabel}", fontsize=9)
            ax.tick_params(labelsize=7)
            if i == 0:
                ax.legend(fontsize=6, loc="best")
    fig.suptitle(
        f"tradeoff ({scale}): training-step speed-up vs evaluation-render error per speed knob",
        fontsize=10,
    )
    _save(fig, path)
    return path.name


def pareto_chart(
    path: str | os.PathLike,
    rows: list[dict[str, Any]],
    curves: dict[str, dict[str, Any]],
    title: str,
) -> str:
    """One panel per curve: every point, its Pareto front, knee and shipped default.

    Args:
        path: Output PNG.
        rows: report rows; a curve's ``points`` are row ids (``metrics[x]``, ``metrics[y]``;
            ``knob`` and ``setting`` label them).
        curves: name -> the ``tradeoff`` curve dict (``x``, ``y``, ``y_better``, ``points``,
            ``front``, ``knee``, optional ``shipped_default``).
        title: figure title.

    Returns:
        The file name of ``path``.
    """
    plt = _plt()
    path = Path(path)
    by_id = {r["id"]: r for r in rows}
    n = max(1, len(curves))
    fig, axes = plt.subplots(1, n, figsize=(6.4 * n, 4.8), squeeze=False)
    for ax, (name, c) in zip(axes[0], curves.items()):
        pts = [by_id[i] for i in c["points"]]
        knobs = list(dict.fromkeys(r.get("knob", "") for r in pts))
        colors = {k: plt.get_cmap("tab10")(i % 10) for i, k in enumerate(knobs)}
        for k in knobs:
            sel = [r for r in pts if r.get("knob", "") == k]
            ax.plot(
                [r["metrics"][c["x"]] for r in sel],
                [r["metrics"][c["y"]] for r in sel],
                "o",
                color=colors[k],
                ms=5,
                label=k,
            )
            for r in sel:
                ax.annotate(
                    str(r.get("setting", r["model"])).split(" (")[0].split(",")[0],
                    (r["metrics"][c["x"]], r["metrics"][c["y"]]),
                    textcoords="offset points",
                    xytext=(3, 3),
                    fontsize=6,
                    color=colors[k],
                )
        front = [by_id[i] for i in c["front"]]
        ax.plot(
            [r["metrics"][c["x"]] for r in front],
            [r["metrics"][c["y"]] for r in front],
            "--",
            color="#555555",
            lw=1,
            label="Pareto front",
        )
        d = c.get("shipped_default")
        if d:
            r = by_id[d["id"]]
            ax.plot([r["metrics"][c["x"]]], [r["metrics"][c["y"]]], "k*", ms=12,
                    label="shipped default")  # fmt: skip
        if c.get("knee") in by_id:
            r = by_id[c["knee"]]
            ax.plot([r["metrics"][c["x"]]], [r["metrics"][c["y"]]], "o", ms=13, mfc="none",
                    mec="#d62728", mew=1.5, label="knee")  # fmt: skip
        ax.set_xscale("log")
        if c["y_better"] == "lower" and all(r["metrics"][c["y"]] > 0 for r in pts):
            ax.set_yscale("log")
        ax.set_xlabel(f"{metric_label(c['x'])} (log)", fontsize=8)
        ax.set_ylabel(f"{metric_label(c['y'])} ({c['y_better']} is better)", fontsize=8)
        ax.set_title(name, fontsize=9)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6, loc="best")
    fig.suptitle(title, fontsize=10)
    _save(fig, path)
    return path.name


def training_chart(path: str | os.PathLike, curve: dict[str, Any]) -> str:
    """Training curve of ``tradeoff``: training-batch PSNR (raw and smoothed) against
    training wall time, the running-best front, the knee and the budget's end; held-out
    metrics (``eval.jsonl``) on a second axis when the run has them. ``eval.jsonl`` (and the
    curve's ``held_out``) store ARI on a 0-1 scale; it is drawn on the paper's 0-100 scale.

    Returns:
        The file name of ``path``.
    """
    plt = _plt()
    path = Path(path)
    pts = curve["points"]
    t = [p["wall_s"] / 60.0 for p in pts]
    fig, ax = plt.subplots(figsize=(8, 4.6))
    ax.plot(t, [p["train_psnr"] for p in pts], color="#9ecae1", lw=0.6, label="training PSNR")
    ax.plot(t, [p["train_psnr_smoothed"] for p in pts], color="#08519c", lw=1.4,
            label="smoothed")  # fmt: skip
    by = {p["id"]: p for p in pts}
    knee, end = by[curve["knee"]], pts[-1]
    ax.plot([knee["wall_s"] / 60], [knee["train_psnr_smoothed"]], "o", ms=11, mfc="none",
            mec="#d62728", mew=1.5, label=f"knee ({knee['wall_s'] / 60:.1f} min)")  # fmt: skip
    ax.plot([end["wall_s"] / 60], [end["train_psnr_smoothed"]], "k*", ms=12,
            label=f"shipped budget ({end['wall_s'] / 60:.1f} min)")  # fmt: skip
    ax.set_xlabel("training wall time (min)", fontsize=8)
    ax.set_ylabel("training-batch PSNR (dB)", fontsize=8)
    held = [h for h in curve.get("held_out", []) if "wall_s" in h]
    if held:
        ax2 = ax.twinx()
        for k, col in (("nv_ari", "#2ca02c"), ("fg_ari", "#ff7f0e")):
            if all(k in h for h in held):
                ax2.plot([h["wall_s"] / 60 for h in held], [100.0 * h[k] for h in held], "-o",
                         color=col, ms=3, label=f"held-out {metric_label(k)}")  # fmt: skip
                last = held[-1]
                ax2.annotate(fmt_ari(100.0 * last[k]), (last["wall_s"] / 60, 100.0 * last[k]),
                             textcoords="offset points", xytext=(3, 3), fontsize=6,
                             color=col)  # fmt: skip
        ax2.set_ylabel("held-out ARI (0-100, as in the paper)", fontsize=8)
        ax2.legend(fontsize=7, loc="lower center")
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title(f"tradeoff: training curve of run {curve['run']}", fontsize=9)
    _save(fig, path)
    return path.name
