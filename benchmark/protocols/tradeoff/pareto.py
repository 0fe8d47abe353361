"""Pareto fronts, knees and the shipped default's place on every ``tradeoff`` curve.

Where this sits: each curve module of the ``tradeoff`` protocol (:mod:`.step`,
:mod:`.render`, :mod:`.generator`) summarises its rows with :func:`curve_summary`;
:func:`benchmark.protocols.tradeoff.run_tradeoff` marks the rows on a front
(:func:`mark_fronts`) and words every curve for the notes (:func:`front_notes`). Times
within the measured timing noise (:func:`timing_noise`) and quality differences below
:data:`METRIC_EPS` count as equal.
"""

from __future__ import annotations

import math
from typing import Any

__all__ = [
    "METRIC_EPS",
    "MIN_NOISE",
    "curve_summary",
    "front_notes",
    "knee_point",
    "mark_fronts",
    "pareto_front",
    "timing_noise",
]

#: Smallest relative timing noise assumed when comparing times on a front.
MIN_NOISE = 0.05
#: Differences of a quality metric below which two points count as equally good on a
#: front (report units: dB, ARI percent): below what a handful of test scenes resolves.
METRIC_EPS: dict[str, float] = {"psnr": 0.01, "nv_ari": 0.5, "nv_fg_ari": 0.5, "fg_ari": 0.5}


def _dominates(
    a: tuple[float, float], b: tuple[float, float], noise: float, eps: float = 0.0
) -> bool:
    """Whether (time, error) ``a`` dominates ``b``: no worse on both axes and better on one,
    where times within the relative timing ``noise`` of each other, and errors within
    ``eps`` of each other, count as equal."""
    (ta, ea), (tb, eb) = a, b
    faster = ta < tb * (1.0 - noise)
    not_slower = ta <= tb * (1.0 + noise)
    return (ea <= eb + eps and faster) or (ea < eb - eps and not_slower)


def pareto_front(
    points: list[tuple[str, float, float]], noise: float = 0.0, eps: float = 0.0
) -> list[str]:
    """Ids of the points no other point dominates, by increasing time.

    Args:
        points: ``(id, time, error)``; smaller is better on both axes (pass -PSNR for a
            quality metric).
        noise: relative timing noise: times within it count as equal (so a point is not
            dominated by an equal-error point that was only luckier on the clock).
        eps: errors within it count as equal (e.g. 0.01 dB of PSNR).
    Returns:
        The ids of the front: no other point has time <= and error <= with one of them <.
    """
    front = []
    for pid, t, e in points:
        if not any(
            _dominates((t2, e2), (t, e), noise, eps) for qid, t2, e2 in points if qid != pid
        ):
            front.append((t, e, pid))
    return [pid for _, _, pid in sorted(front)]


def knee_point(points: list[tuple[str, float, float]], front: list[str]) -> str | None:
    """The front's knee: the point farthest below the chord from its fastest to its most
    accurate end, both axes scaled to [0, 1] over the front (time on a log axis). None for
    an empty front and for a front with no point below that chord (no knee: each step to
    a slower point buys at least as much as the last); the single point of a one-point
    front; with two, the faster one."""
    if not front:
        return None
    if len(front) <= 2:
        return front[0]
    by = {pid: (t, e) for pid, t, e in points}
    ts = [math.log(max(by[p][0], 1e-12)) for p in front]
    es = [by[p][1] for p in front]

    def unit(v: list[float]) -> list[float]:
        lo, hi = min(v), max(v)
        return [0.0 if hi == lo else (x - lo) / (hi - lo) for x in v]

    x, y = unit(ts), unit(es)
    # chord from (x0, y0) (fastest, largest error) to (x1, y1) (slowest, smallest error)
    x0, y0, x1, y1 = x[0], y[0], x[-1], y[-1]
    n = math.hypot(x1 - x0, y1 - y0) or 1.0
    dist = [((x1 - x0) * (y0 - yi) - (xi - x0) * (y0 - y1)) / n for xi, yi in zip(x, y)]
    best = max(range(len(front)), key=lambda i: dist[i])
    return front[best] if dist[best] > 0 else None


def curve_summary(
    rows: list[dict[str, Any]],
    x: str,
    y: str,
    higher_is_better: bool,
    default_id: str | None,
    note: str,
    noise: float = 0.0,
    eps: float | None = None,
) -> dict[str, Any] | None:
    """Front, knee and where ``default_id`` (the shipped default) sits, for ``rows`` on the
    axes ``metrics[x]`` (time, smaller is better) and ``metrics[y]``, times within the
    relative ``noise`` and values of ``y`` within ``eps`` (default :data:`METRIC_EPS`, else
    0) counting as equal. Rows with a null on either axis are left out; None when no row
    remains."""
    eps = METRIC_EPS.get(y, 0.0) if eps is None else eps
    pts = []
    for r in rows:
        tv, ev = r["metrics"].get(x), r["metrics"].get(y)
        if tv is None or ev is None:
            continue
        pts.append((r["id"], float(tv), -float(ev) if higher_is_better else float(ev)))
    if not pts:
        return None
    front = pareto_front(pts, noise, eps)
    knee = knee_point(pts, front)
    out: dict[str, Any] = {
        "x": x,
        "y": y,
        "y_better": "higher" if higher_is_better else "lower",
        "timing_noise": noise,
        "metric_eps": eps,
        "points": [p[0] for p in pts],
        "front": front,
        "knee": knee,
        "note": note,
    }
    if default_id is not None and any(p[0] == default_id for p in pts):
        t, e = next((t, e) for pid, t, e in pts if pid == default_id)
        out["shipped_default"] = {
            "id": default_id,
            "on_front": default_id in front,
            "is_knee": default_id == knee,
            "dominated_by": [
                pid
                for pid, t2, e2 in pts
                if pid != default_id and _dominates((t2, e2), (t, e), noise, eps)
            ],
        }
    return out


def timing_noise(speedups: list[float | None]) -> float:
    """Relative timing noise from the speed-ups of instances equal to the reference: the
    largest |speed-up - 1|, at least :data:`MIN_NOISE`."""
    vals = [abs(1.0 - v) for v in speedups if v]
    return max([MIN_NOISE, *vals])


def mark_fronts(rows: list[dict[str, Any]], curves: dict[str, dict[str, Any]]) -> None:
    """Add ``on_front`` (names of the curves whose front holds the row) to every row of a
    curve."""
    by_id = {r["id"]: r for r in rows}
    for name, c in curves.items():
        if c.get("kind") == "training" or "points" not in c:
            continue
        for pid in c["points"]:
            by_id[pid].setdefault("on_front", [])
        for pid in c["front"]:
            by_id[pid]["on_front"].append(name)


def front_notes(curves: dict[str, dict[str, Any]], rows: list[dict[str, Any]]) -> list[str]:
    """One sentence per curve: its front, its knee and where the shipped default sits."""
    label = {r["id"]: f"{r['model']}" for r in rows}
    out = []
    for name, c in curves.items():
        if "absent" in c:
            out.append(f"Curve '{name}': absent ({c['absent']}).")
            continue
        if c.get("kind") == "training":
            out.append(f"Curve 'training' (run {c['run']}): {c['note']}")
            continue
        d = c.get("shipped_default")
        where = "not on this curve"
        if d:
            where = (
                ("the knee of the front" if d["is_knee"] else "on the front")
                if d["on_front"]
                else "off the front, dominated by " + ", ".join(label[i] for i in d["dominated_by"])
            )
        out.append(
            f"Curve '{name}' ({c['x']} vs {c['y']}, {c['y_better']} is better): front = "
            + ", ".join(label[i] for i in c["front"])
            + "; knee = "
            + (
                label[c["knee"]]
                if c["knee"] is not None
                else "none (no front point below the chord of its ends)"
            )
            + f"; the shipped default is {where}."
        )
    return out
