"""Run as a script: two Ray nodes on this machine, the second with a crash-log folder of its own (a
private tmpfs mounted over it in a mount namespace), so that, as on another machine, the driver
cannot read that node's crash logs from its own disk. A rank there segfaults: the driver's error
must quote the crash log, read on that node. Then a rank's whole node goes: the error says so.

Needs ``unshare -m`` (root, or CAP_SYS_ADMIN); prints ``RESULT {"skip": reason}`` without it.
Run it with ``RAY_AUTH_MODE=token`` and a fresh ``RAY_AUTH_TOKEN`` in its environment (the
cluster's own; Ray reads them when it is imported, so they cannot be set here).
"""

import json
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time

import psutil
import ray

from infinirl.runtime import Cluster, Worker, WorkerError, WorkerGroup, place
from infinirl.runtime.crash_logs import CRASH_LOG_DIR

# Find a node that stopped answering within a few seconds, not Ray's default half-minute.
HEAD_SYSTEM_CONFIG = {"health_check_period_ms": 1000, "health_check_failure_threshold": 3,
                      "health_check_timeout_ms": 1000}


class Sim(Worker):
    def node(self):
        return ray.get_runtime_context().get_node_id()

    def segfault(self):
        import faulthandler

        faulthandler._sigsegv()

    def sleep(self, seconds):
        time.sleep(seconds)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def ray_start(ray_dir: str, name: str, args: list[str], private_crash_logs: bool = False) -> subprocess.Popen:
    cmd = ["ray", "start", "--block", "--node-ip-address=127.0.0.1", f"--temp-dir={ray_dir}/{name}",
           f"--dashboard-agent-listen-port={free_port()}", "--disable-usage-stats", *args]
    if private_crash_logs:
        cmd = ["unshare", "-m", "--propagation", "private", "sh", "-c", 'mount -t tmpfs tmpfs "$0" && exec "$@"',
               str(CRASH_LOG_DIR), *cmd]
    log = open(os.path.join(ray_dir, f"{name}.log"), "ab")
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def kill_tree(proc: subprocess.Popen) -> None:
    root = psutil.Process(proc.pid)
    for p in [*root.children(recursive=True), root]:
        try:
            p.kill()
        except psutil.NoSuchProcess:
            pass
    proc.wait(timeout=60)


def main() -> dict:
    probe = subprocess.run(["unshare", "-m", "true"], capture_output=True)
    if probe.returncode != 0:
        return {"skip": f"unshare -m is not permitted here: {probe.stderr.decode().strip()}"}
    assert os.environ.get("RAY_AUTH_TOKEN"), "run with RAY_AUTH_MODE=token and a fresh RAY_AUTH_TOKEN"
    CRASH_LOG_DIR.mkdir(parents=True, exist_ok=True)
    ray_dir = tempfile.mkdtemp(prefix="irlcl-", dir="/tmp")  # Ray's socket paths must stay short
    port = free_port()
    head = ray_start(ray_dir, "head", ["--head", f"--port={port}", "--num-cpus=1", "--include-dashboard=false",
                                       f"--ray-client-server-port={free_port()}",
                                       f"--system-config={json.dumps(HEAD_SYSTEM_CONFIG)}"])
    node = None
    try:
        deadline = time.monotonic() + 180
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                assert head.poll() is None and time.monotonic() < deadline, "the Ray head did not start"
                time.sleep(0.5)
        node = ray_start(ray_dir, "node1", [f"--address=127.0.0.1:{port}", "--num-cpus=1"], private_crash_logs=True)
        cluster = Cluster(address=f"127.0.0.1:{port}", wait_for_nodes=2, log_to_driver=False).start()
        here = ray.get_runtime_context().get_node_id()
        other = next(n.node_index for n in cluster.inventory.nodes if n.node_id != here)
        plan = place(cluster.inventory, {"sim": f"node:{other}"})
        out = {"driver_node": here}

        group = WorkerGroup.launch(Sim, "sim", placement=plan.ranks("sim"))
        out["rank_node"] = group.node().wait(timeout=120)[0]
        out["log_on_driver_disk"] = os.path.exists(group.rank_info[0]["crash_log"])
        try:
            group.segfault().wait(timeout=120)
        except WorkerError as exc:
            out["crashed"] = str(exc)
        group.shutdown()

        lost = WorkerGroup.launch(Sim, "lost", placement=plan.ranks("sim"))
        handle = lost.sleep(600)
        kill_tree(node)
        node = None
        start = time.monotonic()
        try:
            handle.wait(timeout=180)
        except WorkerError as exc:
            out["node_gone"] = str(exc)
        out["node_gone_s"] = time.monotonic() - start
        lost.shutdown()
        cluster.shutdown()
        return out
    finally:
        for proc in (node, head):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                proc.wait(timeout=120)
        shutil.rmtree(ray_dir, ignore_errors=True)


if __name__ == "__main__":
    print("RESULT " + json.dumps(main()))
