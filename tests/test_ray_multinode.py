"""generate --backend ray --address on a Ray cluster of two nodes (two raylets on this
machine, ``ray.cluster_utils.Cluster``): the CLI connects by address, the two 1-CPU nodes
each render a scene, and the bytes equal a local run's.

This is the multi-node code path (a driver joining a running cluster by address, actors
placed on a node other than the driver's) on one machine, not a run across machines.
"""

from __future__ import annotations

import numpy as np
import pytest

from generators.blender_backend import bpy_available

pytestmark = [
    pytest.mark.blender,
    pytest.mark.skipif(not bpy_available(), reason="bpy not installed"),
]

ARGS = ["--preset", "clevr567", "--n", "2", "--resolution", "32", "--samples", "2"]


@pytest.fixture
def two_node_cluster():
    from ray.cluster_utils import Cluster

    node = {"num_cpus": 1, "object_store_memory": 80 * 1024 * 1024, "include_dashboard": False}
    cluster = Cluster(initialize_head=True, head_node_args=node)
    cluster.add_node(**{k: v for k, v in node.items() if k != "include_dashboard"})
    cluster.wait_for_nodes()
    yield cluster
    cluster.shutdown()


@pytest.mark.timeout(300)
def test_generate_on_two_ray_nodes_by_address_matches_local(two_node_cluster, tmp_path, capsys):
    import ray

    from generators.cli import main
    from generators.verify import verify_split
    from scenefmt import SplitLayout, read_depth_exr

    assert not ray.is_initialized()  # the CLI connects by address, as on a real cluster
    rayd, local = tmp_path / "ray", tmp_path / "local"
    argv = [*ARGS, "--out", str(rayd), "--backend", "ray", "--workers", "2", "--threads", "1"]
    assert main([*argv, "--address", two_node_cluster.address, "--no-progress"]) == 0
    line = capsys.readouterr().out
    # One 1-thread actor per 1-CPU node: each node rendered one of the two scenes.
    assert "2 scenes (8 views) made" in line and "2 worker(s) x 1 thread(s) on 2 Ray nodes" in line
    assert not ray.is_initialized()  # the driver disconnected; the cluster keeps running
    assert verify_split(rayd) == []

    assert main([*ARGS, "--out", str(local), "--workers", "1", "--no-progress"]) == 0
    a, b = SplitLayout(local), SplitLayout(rayd)
    for sc in range(2):
        assert a.scene_json(sc).read_bytes() == b.scene_json(sc).read_bytes()
        for v in range(4):
            for pa, pb in zip(a.view_files(sc, v), b.view_files(sc, v), strict=True):
                if pa.suffix == ".exr":  # OIIO stamps a DateTime into the EXR header
                    assert np.array_equal(read_depth_exr(pa), read_depth_exr(pb)), pa.name
                else:
                    assert pa.read_bytes() == pb.read_bytes(), pa.name
