"""svorf.distributed: `svorf train` under torchrun (2 CPU ranks, gloo) = one process.

The end-to-end test launches ``python -m torch.distributed.run --nproc_per_node 2 -m
svorf.cli train`` as a subprocess on 127.0.0.1 with a free port, interrupts and resumes
it, and compares the checkpoint with a single-process :func:`svorf.train.train` of the
same global batch.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path
from subprocess import PIPE

import pytest
import torch

from svorf import distributed
from svorf.cli import main
from svorf.config import model_config
from svorf.model import SVORF
from svorf.synthetic import write_synthetic_split
from svorf.train import run_configs, train

STEPS = 3
IMAGE = 16


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    # 4 scenes, smoke batch 2: every step draws 2 of 4 scenes, 1 per rank.
    return write_synthetic_split(
        tmp_path_factory.mktemp("ddp") / "train", n_scenes=4, resolution=32, seed=1
    )


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _torchrun_cmd(split: Path, out: Path, steps: int, launch: list[str], *extra: str) -> list[str]:
    return [
        sys.executable, "-m", "torch.distributed.run", *launch,
        "-m", "svorf.cli", "train", "--data", str(split), "--preset", "synthetic",
        "--scale", "smoke", "--out", str(out), "--steps", str(steps),
        "--image-size", str(IMAGE), "--device", "cpu", "--threads", "1", "--no-progress", *extra,
    ]  # fmt: skip


def _env() -> dict[str, str]:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("WORLD_SIZE", None)
    if Path("/sys/class/net/lo").exists():  # gloo on loopback, whatever the host name says
        env.setdefault("GLOO_SOCKET_IFNAME", "lo")
    return env


def _torchrun(split: Path, out: Path, steps: int, *extra: str) -> subprocess.CompletedProcess:
    launch = ["--nnodes", "1", "--nproc_per_node", "2", "--master_addr", "127.0.0.1",
              "--master_port", str(_free_port())]  # fmt: skip
    cmd = _torchrun_cmd(split, out, steps, launch, *extra)
    return subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=300, check=False)


def _failure(stdout: str, stderr: str) -> str:
    """What a failed launch said: where rank 0 got to (stdout) and the first and last lines
    of stderr (a rank's own message comes first, the launcher's summary last)."""
    head = stderr[:1500]
    tail = stderr[-1500:] if len(stderr) > 1500 else ""
    return f"stdout (tail):\n{stdout[-1500:]}\nstderr (head):\n{head}\n...\n{tail}"


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_two_cpu_ranks_match_one_process_and_resume(split, tmp_path):
    ddp = tmp_path / "ddp"
    # An interrupted 2-rank run (2 steps) resumed to 3 steps ...
    for steps, extra in ((STEPS - 1, ()), (STEPS, ("--resume",))):
        r = _torchrun(split, ddp, steps, *extra)
        assert r.returncode == 0, _failure(r.stdout, r.stderr)
        assert r.stdout.count("svorf train:") == 1, r.stdout  # rank 0 alone prints
    summary = json.loads((ddp / "summary.json").read_text())
    assert summary["world_size"] == 2 and summary["steps"] == STEPS

    # ... against one process with the same global batch (smoke: batch_scenes = 2).
    mcfg, tcfg = run_configs("smoke", "synthetic", image_size=IMAGE, steps=STEPS, device="cpu")
    assert tcfg.batch_scenes == 2
    single = tmp_path / "single"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the ranks (--threads 1)
    try:
        train(split, single, mcfg, tcfg, progress=False)
    finally:
        torch.set_num_threads(threads)

    a = torch.load(single / "checkpoint.pt", weights_only=True)
    b = torch.load(ddp / "checkpoint.pt", weights_only=True)
    assert a["step"] == b["step"] == STEPS
    # Identical random streams: data (scenes, views, rays) and the model's jitter.
    assert torch.equal(a["rng"]["data"], b["rng"]["data"])
    assert torch.equal(a["rng"]["torch"], b["rng"]["torch"])
    # Parameters agree up to float summation order. Tolerance 1e-4 (0.1 x lr): Adam
    # normalises each update, so a gradient that is zero in exact arithmetic (attention
    # key biases; softmax ignores them) but 1e-10 of round-off in one run moves by up
    # to ~lr * 1e-10 / eps = 1e-5 per step. Training itself moved them by ~1e-3.
    moved = 0.0
    for k, v in a["model"].items():
        w = b["model"][k]
        if v.is_floating_point():
            torch.testing.assert_close(w, v, rtol=0.0, atol=1e-4, msg=k)
        else:
            assert torch.equal(v, w), k
    for k in a["optimizer"]["state"]:
        ea, eb = a["optimizer"]["state"][k]["exp_avg"], b["optimizer"]["state"][k]["exp_avg"]
        moved = max(moved, float(ea.abs().max()))
        torch.testing.assert_close(eb, ea, rtol=1e-3, atol=1e-7)
    assert moved > 1e-4  # the comparison is not vacuous: gradients are far from zero

    la = [json.loads(x) for x in (single / "log.jsonl").read_text().splitlines()]
    lb = [json.loads(x) for x in (ddp / "log.jsonl").read_text().splitlines()]
    # One writer (no duplicate lines); smoke logs every 5 steps and at each run's last.
    assert [r["step"] for r in la] == [STEPS] and [r["step"] for r in lb] == [STEPS - 1, STEPS]
    for ra, rb in zip(la, lb[1:], strict=True):
        assert rb["loss"] == pytest.approx(ra["loss"], rel=1e-5), (ra, rb)
        assert rb["parts"]["psnr"] == pytest.approx(ra["parts"]["psnr"], rel=1e-5)


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_two_launchers_as_two_nodes_train_what_one_node_of_two_ranks_trains(split, tmp_path):
    """Two torchrun agents, ``--nnodes 2 --node_rank 0/1 --nproc_per_node 1``, as on two
    machines (here both on 127.0.0.1): every rank has LOCAL_RANK 0, so this checks that
    only global rank 0 writes, and that the run equals one node with 2 ranks."""
    port = str(_free_port())
    runs = {}
    for name, nodes in (("one_node", 1), ("two_nodes", 2)):
        out = tmp_path / name
        if nodes == 1:
            r = _torchrun(split, out, STEPS)
            assert r.returncode == 0, _failure(r.stdout, r.stderr)
            runs[name] = (out, r.stdout)
            continue
        procs = []
        for k in range(2):
            launch = ["--nnodes", "2", "--node_rank", str(k), "--nproc_per_node", "1",
                      "--master_addr", "127.0.0.1", "--master_port", port]  # fmt: skip
            cmd = _torchrun_cmd(split, out, STEPS, launch)
            procs.append(subprocess.Popen(cmd, env=_env(), stdout=PIPE, stderr=PIPE, text=True))
        outs = [p.communicate(timeout=300) for p in procs]
        for p, (out_k, err) in zip(procs, outs, strict=True):
            assert p.returncode == 0, _failure(out_k, err)
        # The node-rank-1 agent's rank (global rank 1, local rank 0) stays silent.
        assert outs[0][0].count("svorf train:") == 1 and "svorf train:" not in outs[1][0]
        runs[name] = (out, outs[0][0])

    (one, _), (two, _) = runs["one_node"], runs["two_nodes"]
    s1, s2 = (json.loads((d / "summary.json").read_text()) for d in (one, two))
    assert s1["world_size"] == s2["world_size"] == 2 and s1["steps"] == s2["steps"] == STEPS
    a = torch.load(one / "checkpoint.pt", weights_only=True)
    b = torch.load(two / "checkpoint.pt", weights_only=True)
    # Same ranks, same rows, same gloo reduction over 2 ranks: the same numbers.
    assert torch.equal(a["rng"]["data"], b["rng"]["data"])
    for k, v in a["model"].items():
        assert torch.equal(v, b["model"][k]), k
    assert sorted(p.name for p in two.iterdir()) == sorted(p.name for p in one.iterdir())


def test_global_batch_random_gives_each_rank_its_rows_of_the_single_process_draw():
    model = SVORF(model_config("smoke", num_slots=5, image_size=16, slot_mask_train=2))
    torch.manual_seed(7)
    full = torch.rand(4, 3, 5)
    full_n = torch.randn(4, 2)
    full_mask = model.sample_slot_mask(4)
    state = torch.get_rng_state()
    for rank in range(2):
        torch.manual_seed(7)
        with distributed.GlobalBatchRandom(rank, world_size=2, local_batch=2):
            part = torch.rand(2, 3, 5)
            part_n = torch.randn((2, 2))
            mask = model.sample_slot_mask(2)
        assert torch.equal(part, full[2 * rank : 2 * rank + 2])
        assert torch.equal(part_n, full_n[2 * rank : 2 * rank + 2])
        assert torch.equal(mask, full_mask[2 * rank : 2 * rank + 2])
        assert torch.equal(torch.get_rng_state(), state)  # every rank stays in step


def test_global_batch_random_refuses_draws_it_cannot_match():
    with distributed.GlobalBatchRandom(0, world_size=2, local_batch=2):
        with pytest.raises(RuntimeError, match="batch"):
            torch.rand(3, 4)  # no batch axis first
        with pytest.raises(RuntimeError, match="randint"):
            torch.randint(0, 5, (2, 3))
        with pytest.raises(RuntimeError, match="dropout"):
            torch.nn.functional.dropout(torch.ones(2, 3), p=0.5, training=True)
        torch.nn.functional.dropout(torch.ones(2, 3), p=0.0)  # a no-op is fine
        torch.zeros(2).add_(1)  # other ops pass through


def test_batch_not_divisible_by_world_size_is_a_one_line_error(
    split, tmp_path, capsys, monkeypatch
):
    with pytest.raises(ValueError, match="not divisible by the world size 4"):
        distributed.local_batch(6, 4)
    assert distributed.local_batch(8, 4) == 2
    # torchrun's environment for rank 0 of 4: the check fires before any process group.
    for k, v in {"WORLD_SIZE": "4", "RANK": "0", "LOCAL_RANK": "0"}.items():
        monkeypatch.setenv(k, v)
    argv = ["train", "--data", str(split), "--preset", "synthetic", "--scale", "smoke",
            "--out", str(tmp_path / "run"), "--image-size", str(IMAGE), "--no-progress"]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("svorf: error:") and len(err.splitlines()) == 1, err
    assert "batch_scenes=2 is not divisible by the world size 4" in err
    assert not (tmp_path / "run").exists()
    assert distributed.current() is None


def test_bad_torchrun_environment_is_a_one_line_error(monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "two")
    with pytest.raises(ValueError, match="WORLD_SIZE must be a positive integer"):
        distributed.init_from_env("cpu")
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.delenv("RANK", raising=False)
    with pytest.raises(ValueError, match="RANK is not"):
        distributed.init_from_env("cpu")
    monkeypatch.setenv("WORLD_SIZE", "1")
    assert distributed.init_from_env("cpu") is None
