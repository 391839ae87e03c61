"""A Ray cluster of two nodes on one machine (a head and a worker, each started by ``ray start`` as a real
process with its own raylet and one CPU), used through the ``address:`` setting of the ``ray_actors`` and
``ray`` executors: the work lands on both nodes and the stored rows equal the ``local`` executor's (same
keys, same features). The nodes are torn down even when the test fails (docs/ray-cluster.md)."""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from test_dataset_toy import FEATURES, SIM, ToyFeatures, ToyOscillator

from invphys.core.dataset import DatasetStore
from invphys.data.generate import generate_dataset
from invphys.plugins.executors import RayActorsExecutor, RayExecutor

ray = pytest.importorskip("ray", reason="the Ray cluster test needs Ray (pip install 'invphys[ray]')")

TESTS = str(Path(__file__).resolve().parent)
NODE_TAG = "INVPHYS_TEST_RAY_NODE"   # which node a process runs on: 1 (head) or 2 (worker)
STARTED = "Ray runtime started"


class NodeTagFeatures(ToyFeatures):
    """The number of the cluster node whose process extracted the run (to see where the work ran)."""

    name = "node_tag_toy_features"

    @property
    def feature_names(self) -> tuple[str, ...]:
        return ("node",)

    def extract(self, trajectory):
        return np.array([float(os.environ.get(NODE_TAG, "0"))])


def _env(token: str) -> dict[str, str]:
    """The environment of the nodes and the driver: the toy plugins importable, the cluster's own token
    (Ray's token authentication, never the user's ~/.ray/auth_token), no usage stats."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    return {**env, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": token, "RAY_USAGE_STATS_ENABLED": "0",
            "PYTHONPATH": os.pathsep.join([TESTS, os.environ.get("PYTHONPATH", "")])}


def _free_ports(n: int) -> list[int]:
    socks = [socket.socket() for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def _ray_cli() -> str:
    near = Path(sys.executable).parent / "ray"
    found = str(near) if near.exists() else shutil.which("ray")
    if not found:
        pytest.skip("the `ray` command is not installed next to this Python")
    return found


def _start_node(tag: int, args: list[str], log: Path, token: str) -> subprocess.Popen:
    """``ray start ARGS --block`` as a process of its own group, once it says the node runs."""
    agent, metrics, runtime_env = _free_ports(3)
    env = {**_env(token), NODE_TAG: str(tag), "RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S": "0"}
    cmd = [_ray_cli(), "start", *args, "--num-cpus=1", "--num-gpus=0", "--block", "--disable-usage-stats",
           f"--object-store-memory={100 << 20}", f"--dashboard-agent-listen-port={agent}",
           f"--metrics-export-port={metrics}", f"--runtime-env-agent-port={runtime_env}"]
    with open(log, "wb") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, process_group=0,
                                preexec_fn=_die_with_parent)
    deadline = time.monotonic() + 90
    while STARTED not in log.read_text(errors="replace"):
        if proc.poll() is not None or time.monotonic() > deadline:
            _stop(proc)
            pytest.fail(f"`ray start` of node {tag} did not come up:\n{log.read_text(errors='replace')[-3000:]}")
        time.sleep(0.2)
    return proc


def _die_with_parent() -> None:
    """In the node's process before it runs: end it (SIGTERM) when the test's process dies (Linux)."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None).prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG


def _stop(proc: subprocess.Popen) -> None:
    """End a ``ray start --block`` process and its group (its raylet, GCS and workers share its fate)."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(proc.pid, sig)   # the group this test made for the node, never the test's own
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            continue
        if sig == signal.SIGTERM:
            time.sleep(0.5)   # let the group's other processes go; then make sure


@pytest.fixture(scope="module")
def cluster() -> Iterator[tuple[str, str]]:
    """(address, token) of a head node and one worker node on this machine, one CPU each."""
    tmp = Path(tempfile.mkdtemp(prefix="rc", dir="/tmp"))   # short: Ray's socket paths are limited
    gcs, client = _free_ports(2)
    token = secrets.token_hex(32)
    procs: list[subprocess.Popen] = []
    try:
        procs.append(_start_node(1, ["--head", f"--port={gcs}", f"--ray-client-server-port={client}",
                                     "--include-dashboard=false", f"--temp-dir={tmp / 'head'}"],
                                 tmp / "head.log", token))
        address = f"127.0.0.1:{gcs}"
        procs.append(_start_node(2, [f"--address={address}", f"--temp-dir={tmp / 'worker'}"],
                                 tmp / "worker.log", token))
        yield address, token
    finally:
        for proc in reversed(procs):
            _stop(proc)
        shutil.rmtree(tmp, ignore_errors=True)


SIM_BLOCK = {"type": SIM, "substeps": 1}
COMMON = dict(features={"type": FEATURES}, n=16, batch_size=2, progress=False, seed=7)


def _rows(path: Path) -> tuple[list[str], np.ndarray, list[str]]:
    frame = DatasetStore(path).frame().sort_values("key")
    cols = [c for c in frame.columns if c.startswith("f_")]
    return frame["key"].tolist(), frame[cols].to_numpy(), frame["status"].tolist()


def test_two_node_cluster_runs_on_both_nodes_and_matches_local(cluster, tmp_path) -> None:
    address, token = cluster
    generate_dataset(tmp_path / "local", SIM_BLOCK, executor={"type": "local"}, **COMMON)
    keys, feats, status = _rows(tmp_path / "local")
    assert status.count("ok") >= 8 and "failed" in status   # the toy has both (blow-ups fail)
    # the driver is a fresh process, as a user's would be (this one may hold another Ray instance)
    run = subprocess.run([sys.executable, __file__, address, str(tmp_path)], env=_env(token),
                         capture_output=True, text=True, timeout=240)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-4000:]
    seen = json.loads(run.stdout.strip().splitlines()[-1])
    for name in ("actors", "tasks"):   # the same keys, statuses and features as the local executor's
        k, f, s = _rows(tmp_path / name)
        assert k == keys and s == status, name
        np.testing.assert_array_equal(f, feats)
    # work landed on both nodes: each run's extraction says which node it ran on; one actor per node
    assert seen["actor_tags"] == [1.0, 2.0] and seen["task_tags"] == [1.0, 2.0], seen
    assert sorted(a["node_id"] for a in seen["actors"]) == sorted(seen["nodes"]), seen
    assert all(a["rows"] > 0 for a in seen["actors"]), seen


def _drive(address: str, out: Path) -> dict:
    """In the driver process: the dataset through both executors, then where the runs went."""
    import ray

    generate_dataset(out / "actors", SIM_BLOCK, executor={"type": "ray_actors", "address": address, "num_gpus": 0},
                     **COMMON)
    generate_dataset(out / "tasks", SIM_BLOCK, executor={"type": "ray", "address": address, "max_in_flight": 4},
                     **COMMON)
    tag_block = {"type": "test_ray_cluster:NodeTagFeatures"}
    params = ToyOscillator().parameter_space().denormalize(np.full((8, 3), 0.3))
    actors = RayActorsExecutor(address=address, num_gpus=0, keep_actors=True)
    try:
        actor_tags = sorted({float(r.features[0]) for _, r in actors.run(SIM_BLOCK, tag_block, params, 2)})
        info = actors.actor_info()
        nodes = [n["NodeID"] for n in ray.nodes() if n["Alive"]]
    finally:
        actors.close()
    task_tags = sorted({float(r.features[0]) for _, r in RayExecutor(address=address, max_in_flight=4).run(
        SIM_BLOCK, tag_block, params, 1)})
    return {"actor_tags": actor_tags, "task_tags": task_tags, "nodes": nodes,
            "actors": [{"node_id": a["node_id"], "rows": a["rows"]} for a in info]}


if __name__ == "__main__":
    print(json.dumps(_drive(sys.argv[1], Path(sys.argv[2]))))


def test_an_address_where_nothing_listens_is_one_error_line_at_once(tmp_path) -> None:
    """Before, Ray retried a wrong `address:` for minutes (the run seemed to hang); now exit 2 at once."""
    (port,) = _free_ports(1)
    spec = tmp_path / "spec.yaml"
    spec.write_text(f'name: wrong-address\nsimulator: {{type: "{SIM}", substeps: 1}}\n'
                    f'features: {{type: "{FEATURES}"}}\n'
                    f'executor: {{type: ray_actors, address: "127.0.0.1:{port}", num_gpus: 0}}\n'
                    'dataset: {n: 4, batch_size: 2}\n')
    start = time.monotonic()
    run = subprocess.run([sys.executable, "-m", "invphys.cli", "dataset", "generate", str(spec), "--out",
                          str(tmp_path / "ds")], env=_env(secrets.token_hex(32)), capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 2, run.stdout + run.stderr
    errors = [line for line in (run.stdout + run.stderr).splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "nothing answers there" in errors[0] and "ray-cluster" in errors[0], errors
    assert "Traceback" not in run.stderr and time.monotonic() - start < 60


def test_the_docs_executor_blocks_are_valid_settings() -> None:
    """Every `executor:` line of docs/ray-cluster.md builds its executor (without reaching a cluster)."""
    import yaml

    from invphys import registry

    text = (Path(TESTS).parent / "docs" / "ray-cluster.md").read_text()
    blocks = [yaml.safe_load(line)["executor"] for line in text.splitlines() if line.startswith("executor: {")]
    assert len(blocks) >= 3
    for block in blocks:
        executor = registry.create("executor", dict(block))
        assert executor.config.address == block["address"]
