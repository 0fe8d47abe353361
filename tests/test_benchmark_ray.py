"""benchmark run ... --backend ray: a tiny table protocol (2 ablation rows, synthetic data)
on a local Ray cluster (2 CPUs) started by the test trains and evaluates on Ray workers,
gives the rows of a local run, resumes without rescheduling, and fails in one line."""

from __future__ import annotations

import json

import pytest

from benchmark.cli import main as cli_main
from benchmark.ray_jobs import cpus_per_task
from benchmark.runner import Context, MeasuredRow, ModelJob, run_table_protocol

METRICS = ("nv_ari", "fg_ari", "ari", "psnr")


def _rows() -> list[MeasuredRow]:
    return [
        MeasuredRow(
            "tab:ablation", "sVORF (ours)", "clevr567", ModelJob("full", "clevr567"), METRICS
        ),
        MeasuredRow(
            "tab:ablation", "sVORF (w/o SA)", "clevr567", ModelJob("wo_sa", "clevr567"), METRICS
        ),
    ]


def _run(out, data, backend):
    ctx = Context(
        "ablation",
        "smoke",
        out,
        data,
        data_source="synthetic",
        progress=False,
        train_steps=2,
        backend=backend,
    )
    path = run_table_protocol(ctx, ["tab:ablation"], _rows())
    return ctx, json.loads(path.read_text())


def _measured(report):
    return {
        r["model"]: r["metrics"]
        for r in report["rows"]
        if r["source"] == "measured" and r["table"] == "tab:ablation"
    }


@pytest.mark.timeout(300)
def test_ray_backend_trains_on_workers_matches_local_and_resumes(ray_cluster, tmp_path):
    data = tmp_path / "data"
    ctx_l, local = _run(tmp_path / "local", data, "local")
    ctx_r, remote = _run(tmp_path / "ray", data, "ray")
    # Both models were trained and evaluated by Ray tasks, in this run (not "reused").
    assert len(ctx_r.trained_elsewhere) == 2
    assert ctx_r.trained_elsewhere == {m.key for m in ctx_l.models.values()}
    for key in ctx_r.trained_elsewhere:
        assert (tmp_path / "ray" / "runs" / key / "benchmark_run.json").is_file()
    assert all(m["reused"] is False for m in remote["models"])
    assert any("Backend ray: 2 training run(s) and 2 evaluation(s)" in n for n in remote["notes"])
    assert remote["scale_settings"]["backend"] == "ray"
    # Same configs, data and seeds -> the same rows as the local run (thread counts
    # differ between the driver and the 1-CPU tasks, hence a tolerance).
    lm, rm = _measured(local), _measured(remote)
    assert lm.keys() == rm.keys() and len(lm) == 2
    for model in lm:
        for k in METRICS:
            assert rm[model][k] == pytest.approx(lm[model][k], abs=1e-3), (model, k)
    # Resume: a second invocation schedules nothing and reuses every row.
    ctx_2, again = _run(tmp_path / "ray", data, "ray")
    assert not ctx_2.trained_elsewhere
    assert any("Backend ray: 0 training run(s) and 0 evaluation(s)" in n for n in again["notes"])
    assert _measured(again) == rm


def test_cpus_per_task_shares_the_cluster():
    assert cpus_per_task(2, 3) == 1
    assert cpus_per_task(16, 3) == 5
    assert cpus_per_task(2, 1) == 2
    assert cpus_per_task(2, 0) == 1


def test_backend_flags_fail_in_one_line(capsys, tmp_path):
    assert cli_main(["run", "speed", "--backend", "ray", "--out", str(tmp_path)]) == 2
    assert "--backend applies to the table protocols" in capsys.readouterr().err
    assert cli_main(["run", "ablation", "--address", "auto", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "--address is a Ray cluster address; pass it with --backend ray" in err
    assert len(err.strip().splitlines()) == 1
