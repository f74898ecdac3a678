"""Cluster: local start, inventory, multi-node placement (simulated), clean shutdown, bad addresses."""

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from infinirl.runtime import Cluster, ClusterError, Worker, WorkerGroup
from tests.conftest import ship_by_value

ship_by_value(__name__)

SCENARIOS = Path(__file__).parent / "scenarios"
REPO = Path(__file__).resolve().parents[3]


def _scenario_env() -> dict:
    pythonpath = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)
    return {**os.environ, "PYTHONPATH": pythonpath}


def run_scenario(name: str, timeout: float = 300) -> dict:
    proc = subprocess.run([sys.executable, str(SCENARIOS / name)], capture_output=True, text=True,
                          timeout=timeout, cwd=REPO, env=_scenario_env())
    assert proc.returncode == 0, proc.stderr[-4000:]
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    return json.loads(line.removeprefix("RESULT "))


def test_local_inventory(ray_cluster):
    inv = ray_cluster.inventory
    assert inv.num_nodes == 1
    assert inv.nodes[0].num_cpus == 2
    assert inv.num_robots == 0  # none unless a robot plugin is configured
    assert inv.nodes[0].ip


def _idle_pool_workers() -> list[int]:
    """Ray worker processes of this session's raylet that hold no actor and run no task."""
    import ray

    raylet = ray._private.worker._global_node.all_processes["raylet"][0].process.pid
    idle = []
    for child in psutil.Process(raylet).children():
        try:
            if child.cmdline()[:1] == ["ray::IDLE"]:
                idle.append(child.pid)
        except psutil.NoSuchProcess:
            pass
    return idle


def test_a_cluster_we_start_keeps_no_idle_worker_processes(ray_cluster):
    """An idle Ray worker wakes every 10 ms (~3% of a core each on 2 busy cores): Ray's default
    pool (one per CPU, kept once idle) would only take CPU from the components' processes."""
    import ray

    @ray.remote(num_cpus=0)
    def task() -> int:
        return 1

    assert ray.get(task.remote()) == 1  # a task's worker, idle once it returns
    deadline = time.monotonic() + 20
    while _idle_pool_workers() and time.monotonic() < deadline:
        time.sleep(0.5)
    assert not _idle_pool_workers()


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_multinode_placement_on_simulated_cluster():
    out = run_scenario("multinode.py")
    assert out["num_nodes"] == 3 and out["cpus"] == [1, 2, 2]
    assert out["robots"] == 3  # one simulated robot per node
    assert out["actual"] == out["expected"]
    assert len(set(out["expected"]["actor"])) == 1 and out["expected"]["actor"][0] != out["expected"]["env"][0]


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_shutdown_leaves_no_process():
    out = run_scenario("lifecycle.py")
    pids = out["workers"] + out["ray"]
    assert out["workers"] and out["ray"]
    deadline = time.monotonic() + 30
    alive = pids
    while alive and time.monotonic() < deadline:
        alive = [p for p in pids if psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE]
        time.sleep(0.5)
    assert not alive, f"processes left after shutdown: {[psutil.Process(p).cmdline()[:3] for p in alive]}"


def _closed_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_unreachable_address_fails_fast_with_clear_message():
    start = time.monotonic()
    with pytest.raises(ClusterError, match="cannot reach the Ray head at 127.0.0.1"):
        Cluster(address=f"127.0.0.1:{_closed_port()}", connect_timeout_s=2).start()
    assert time.monotonic() - start < 10


def test_malformed_address():
    with pytest.raises(ClusterError, match="is not 'host:port'"):
        Cluster(address="not-an-address").start()


def test_inventory_before_start_is_an_error():
    with pytest.raises(ClusterError, match="not started"):
        _ = Cluster().inventory


class Idle(Worker):
    pass


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_the_next_launch_removes_crash_logs_of_a_killed_driver_and_keeps_live_ones(ray_cluster, deliberate_deaths):
    """A driver killed with SIGKILL never shuts its groups down: its ranks' (crash-free) logs would
    stay in the temp dir for good. The next launch on the host removes them, and only them."""
    import ray

    driver = subprocess.Popen([sys.executable, str(SCENARIOS / "killed_driver.py"),
                               ray.get_runtime_context().gcs_address],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=_scenario_env())
    live = None
    try:
        line = ""
        while not line.startswith("RESULT "):
            line = driver.stdout.readline()
            assert line, f"the driver scenario ended without a result: {driver.stderr.read()[-4000:]}"
        orphaned = json.loads(line.removeprefix("RESULT "))
        assert all(os.path.exists(path) for path in orphaned["logs"])
        live = WorkerGroup.launch(Idle, "live-driver", num_ranks=1)  # this (live) process's group
        deliberate_deaths(*orphaned["pids"])  # their driver's death ends them
        driver.kill()
        driver.wait(timeout=60)
        WorkerGroup.launch(Idle, "next-launch", num_ranks=1).shutdown()
        assert not any(os.path.exists(path) for path in orphaned["logs"])
        assert all(os.path.exists(info["crash_log"]) for info in live.rank_info)
    finally:
        driver.kill()
        driver.wait(timeout=60)
        if live is not None:
            live.shutdown()
