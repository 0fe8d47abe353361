"""Scaling from 1 to N workers on this machine: generation (local pool, Ray) and training
(one process vs ``torchrun`` ranks), as JSON and a PNG figure (see docs/scaleout.md).

Where it sits: a measurement tool beside the ``benchmark`` protocols, not a protocol (it
measures the machine, not a model). Every configuration runs as a fresh subprocess of the
project's own command line (``generate``, ``svorf train``, ``torch.distributed.run``), one
after the other, so each sees the same machine; the load average before and after each
run is recorded, because on a 2-core box another job changes the result more than the
worker count does.

- generation: ``generate --preset P --n S --resolution R --samples SPP --threads 1
  --workers W`` for W in ``--workers`` (and ``--backend ray`` with ``--ray``); wall time
  of the command, seconds per view, and whether the scene JSONs and masks are the same
  bytes as the 1-worker output (they must be: sharding by scene index is deterministic);
- training: ``svorf train --scale S --preset synthetic`` on a small synthetic split, one
  process vs ``torchrun --nproc_per_node W`` (gloo), the same global batch; s/step from
  each run's ``summary.json`` and the final losses.

Speed-up = (1-worker time) / (W-worker time) of the same kind, same run.

Command::

    python -m benchmark.scaling --out reports/scaling            # ~3-5 min on 2 idle cores
    python -m benchmark.scaling --out reports/scaling --ray      # also the Ray backend
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from scenefmt import atomic_write_json
from scenefmt.cli_util import DefaultsFormatter, doc_summary

__all__ = ["main", "measure_generation", "measure_training", "scaling_figure"]


def _load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def _bin(name: str) -> str:
    """A console script of this environment (beside the interpreter), else on PATH."""
    here = Path(sys.executable).with_name(name)
    found = str(here) if here.is_file() else shutil.which(name)
    if not found:
        raise SystemExit(f"scaling: the {name!r} command is not installed; pip install -e .")
    return found


def _run(cmd: list[str], env: dict[str, str] | None = None, timeout: float = 1800) -> float:
    """Wall seconds of ``cmd``; a failure is a one-line error with the command's last line."""
    t0 = time.perf_counter()
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout, check=False)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        tail = (r.stderr or r.stdout).strip().splitlines()[-1:] or ["(no output)"]
        raise SystemExit(f"scaling: {' '.join(cmd[:3])} ... failed: {tail[0][:300]}")
    return wall


def _digest(split: Path) -> str:
    """SHA-256 over the scene JSONs and masks of a split (names and bytes)."""
    h = hashlib.sha256()
    for p in sorted(split.rglob("*")):
        if p.is_file() and (p.name.endswith("_mask.png") or p.suffix == ".json"):
            if p.name == "manifest.json":  # records workers/threads/timings
                continue
            h.update(p.relative_to(split).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def measure_generation(
    work: Path,
    workers: list[int],
    *,
    preset: str = "clevr567",
    scenes: int = 16,
    resolution: int = 64,
    samples: int = 4,
    backend: str = "local",
) -> list[dict[str, Any]]:
    """One row per worker count: wall, s/view, speed-up vs the first, same bytes."""
    rows: list[dict[str, Any]] = []
    ref = None
    for w in workers:
        out = work / f"gen_{backend}_{w}"
        shutil.rmtree(out, ignore_errors=True)
        cmd = [_bin("generate"), "--preset", preset, "--split", "train", "--n", str(scenes),
               "--resolution", str(resolution), "--samples", str(samples), "--threads", "1",
               "--workers", str(w), "--backend", backend, "--out", str(out), "--no-progress"]  # fmt: skip
        before = _load()
        wall = _run(cmd)
        digest = _digest(out)
        ref = ref or (wall, digest)
        views = scenes * 4
        rows.append({
            "kind": f"generate ({backend})", "workers": w, "threads_per_worker": 1,
            "wall_s": round(wall, 2), "s_per_view": round(wall / views, 4),
            "speedup": round(ref[0] / wall, 3), "same_bytes_as_first": digest == ref[1],
            "load_before": before, "load_after": _load(),
        })  # fmt: skip
    return rows


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def measure_training(
    work: Path, ranks: list[int], *, scale: str = "cpu", steps: int = 12, image: int = 32
) -> list[dict[str, Any]]:
    """One process (ranks == 1) vs ``torchrun`` with that many gloo ranks, same global batch."""
    from svorf.synthetic import write_synthetic_split

    split = write_synthetic_split(work / "synthetic", n_scenes=4, resolution=image, seed=0)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("WORLD_SIZE", None)
    if Path("/sys/class/net/lo").exists():  # gloo on loopback, whatever the host name says
        env.setdefault("GLOO_SOCKET_IFNAME", "lo")
    rows: list[dict[str, Any]] = []
    ref = None
    for n in ranks:
        out = work / f"train_{n}"
        shutil.rmtree(out, ignore_errors=True)
        args = ["-m", "svorf.cli", "train", "--data", str(split), "--preset", "synthetic",
                "--scale", scale, "--out", str(out), "--steps", str(steps), "--image-size",
                str(image), "--device", "cpu", "--threads", "1", "--no-progress"]  # fmt: skip
        if n > 1:
            args = ["-m", "torch.distributed.run", "--nnodes", "1", "--nproc_per_node", str(n),
                    "--master_addr", "127.0.0.1", "--master_port", str(_free_port()), *args]  # fmt: skip
        before = _load()
        wall = _run([sys.executable, *args], env=env)
        summary = json.loads((out / "summary.json").read_text())
        sps = float(summary["s_per_step"])
        ref = ref or sps
        rows.append({
            "kind": f"train ({scale} scale)", "workers": n, "threads_per_worker": 1,
            "wall_s": round(wall, 2), "s_per_step": sps, "speedup": round(ref / sps, 3),
            "final_loss": summary.get("final_loss", summary.get("loss")),
            "load_before": before, "load_after": _load(),
        })  # fmt: skip
    return rows


def scaling_figure(rows: list[dict[str, Any]], path: Path) -> Path:
    """Speed-up against workers, one line per kind, with the ideal (linear) line."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4.0))
    top = max(r["workers"] for r in rows)
    ax.plot([1, top], [1, top], "k--", lw=1, label="ideal")
    for kind in dict.fromkeys(r["kind"] for r in rows):
        pts = [(r["workers"], r["speedup"]) for r in rows if r["kind"] == kind]
        ax.plot(*zip(*pts), "o-", label=kind)
    ax.set_xlabel("workers (processes / ranks, 1 thread each)")
    ax.set_ylabel("speed-up over 1 worker")
    ax.set_xticks(range(1, top + 1))
    ax.set_title(f"scaling on this machine ({os.cpu_count()} cores)", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=120)
    plt.close(fig)
    os.replace(tmp, path)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m benchmark.scaling",
        description=doc_summary(__doc__),
        formatter_class=DefaultsFormatter,
    )
    ap.add_argument("--out", required=True, help="folder for scaling.json and scaling.png")
    ap.add_argument(
        "--workers", default="1,2", help="comma-separated worker counts (first = reference)"
    )
    ap.add_argument("--scenes", type=int, default=16)
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--samples", type=int, default=4)
    ap.add_argument("--train-steps", type=int, default=12)
    ap.add_argument("--train-scale", default="cpu", choices=("smoke", "cpu"))
    ap.add_argument("--ray", action="store_true", help="also the Ray backend of generate")
    ap.add_argument("--skip-train", action="store_true")
    a = ap.parse_args(argv)
    try:
        workers = [int(x) for x in a.workers.split(",")]
    except ValueError:
        raise SystemExit(f"--workers expects comma-separated integers, got {a.workers!r}") from None
    if not workers or min(workers) < 1:
        raise SystemExit(f"--workers expects counts >= 1, got {a.workers!r}")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="scaling-") as tmp:
        work = Path(tmp)
        rows += measure_generation(work, workers, scenes=a.scenes, resolution=a.resolution,
                                   samples=a.samples)  # fmt: skip
        if a.ray:
            rows += measure_generation(work, workers, scenes=a.scenes, resolution=a.resolution,
                                       samples=a.samples, backend="ray")  # fmt: skip
        if not a.skip_train:
            rows += measure_training(work, workers, scale=a.train_scale, steps=a.train_steps)
    report = {
        "what": "speed-up from 1 to N workers on this machine (one run, configurations in turn)",
        "machine": {
            "cpu_count": os.cpu_count(),
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
        },
        "settings": {
            "scenes": a.scenes,
            "resolution": a.resolution,
            "samples": a.samples,
            "train_steps": a.train_steps,
            "train_scale": a.train_scale,
        },
        "rows": rows,
    }
    atomic_write_json(out / "scaling.json", report)
    fig = scaling_figure(rows, out / "scaling.png")
    for r in rows:
        t = f"{r['s_per_view']} s/view" if "s_per_view" in r else f"{r['s_per_step']} s/step"
        print(f"{r['kind']:<22} {r['workers']} worker(s): {t}, speed-up {r['speedup']:.2f}x, "
              f"load {r['load_before'][0]} -> {r['load_after'][0]}")  # fmt: skip
    print(f"wrote {out / 'scaling.json'} and {fig}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
