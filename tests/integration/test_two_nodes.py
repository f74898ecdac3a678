"""Two real Ray nodes on this machine: a head and a second raylet joined with `ray start --address`,
each with its own temp dir and ports. The runners are placed across both by configuration only
(``placement.rollout=node:1``); losing the second node mid-run is one clear error naming the node
and the components lost, and the run resumes from its last checkpoint once the node is back.

Slow tier (starting two Ray nodes and the runs in fresh driver processes takes minutes on a
small machine): ``pytest -m slow tests/integration/test_two_nodes.py``."""

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
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow
pytest.importorskip("gymnasium")

REPO = Path(__file__).resolve().parents[2]
ITERATIONS = 20  # long enough that the second node is lost mid-run

# A driver that builds the runner's config from JSON and runs it: what `infinirl train` does with a
# config file, without needing one on disk.
DRIVER = """
import json, sys
from infinirl.config import to_dataclass
from infinirl.runners import load_runners
runner = load_runners().get(sys.argv[1])
summary = runner.run(to_dataclass(runner.config_cls, json.loads(sys.argv[2])))
print("SUMMARY " + json.dumps(summary, default=str), flush=True)
"""


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class TwoNodes:
    """A Ray head and a second node, each a `ray start --block` process of this test: stopping
    that process (SIGTERM) stops every Ray process of its node, and nothing else."""

    def __init__(self, root: Path):
        self.root = root
        # Ray's socket paths live in the temp dir and must fit AF_UNIX's 107 bytes: a short one
        self.ray_dir = Path(tempfile.mkdtemp(prefix="irl2n-", dir="/tmp"))
        self.port = free_port()
        self.address = f"127.0.0.1:{self.port}"
        # Ray enables token authentication: this cluster gets a token of its own, in the environment
        # of its nodes and drivers only.
        pythonpath = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)
        self.env = {**os.environ, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32),
                    "PYTHONPATH": pythonpath}
        self.env.pop("RAY_ADDRESS", None)
        self.head = self._start("head", ["--head", f"--port={self.port}", "--num-cpus=2",
                                         "--include-dashboard=false", f"--ray-client-server-port={free_port()}"])
        self.node = None
        deadline = time.monotonic() + 180
        while True:  # the head's GCS accepts connections once it is up
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=1).close()
                break
            except OSError:
                assert self.head.poll() is None, (root / "head.log").read_text()[-4000:]
                assert time.monotonic() < deadline, "the Ray head did not start within 180 s"
                time.sleep(0.5)

    def _start(self, name: str, args: list[str]) -> subprocess.Popen:
        log = open(self.root / f"{name}.log", "ab")
        return subprocess.Popen(
            ["ray", "start", "--block", "--node-ip-address=127.0.0.1", f"--temp-dir={self.ray_dir / name}",
             f"--dashboard-agent-listen-port={free_port()}", "--disable-usage-stats", *args],
            stdout=log, stderr=subprocess.STDOUT, env=self.env)

    def add_node(self) -> None:
        self.node = self._start("node1", [f"--address={self.address}", "--num-cpus=1",
                                          '--resources={"second_node": 1}'])

    def kill_node(self) -> None:
        """The node fails at once, as a crashed or unplugged machine does: every process of it
        (the `ray start` process and all it started: raylet, agents, workers) gets SIGKILL."""
        import psutil

        root = psutil.Process(self.node.pid)
        for proc in [*root.children(recursive=True), root]:
            try:
                proc.kill()
            except psutil.NoSuchProcess:
                pass
        self.node.wait(timeout=120)
        self.node = None

    def stop(self) -> None:
        for proc in (self.node, self.head):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                proc.wait(timeout=120)
        shutil.rmtree(self.ray_dir, ignore_errors=True)

    def run(self, runner: str, config: dict) -> subprocess.Popen:
        config = {**config, "cluster": {"address": self.address, "wait_for_nodes": 2, "log_to_driver": False}}
        return subprocess.Popen([sys.executable, "-c", DRIVER, runner, json.dumps(config)], cwd=REPO, env=self.env,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.fixture(scope="module")
def nodes(tmp_path_factory):
    cluster = TwoNodes(tmp_path_factory.mktemp("two-nodes"))
    try:
        cluster.add_node()
        yield cluster
    finally:
        cluster.stop()


def embodied_config(output_dir: Path, iterations: int) -> dict:
    return {
        "iterations": iterations, "rollout_steps": 16, "output_dir": str(output_dir), "save_every": 1,
        "env": {"name": "gym:Pendulum-v1", "num_envs": 4},
        "algorithm": {"epochs": 1, "mini_batches": 2},
        "eval": {"every": 0, "episodes": 2, "num_envs": 2, "video_episodes": 0},
        # env and actor on the head's CPU slots, the rollout on the second node: streamed over TCP
        "placement": {"env": "0", "actor": "1", "rollout": "node:1"},
    }


def finished(proc: subprocess.Popen, timeout: float = 600) -> tuple[str, str]:
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, err[-4000:]
    return out, err


def placement_rows(stdout: str, component: str) -> list[list[str]]:
    return [line.split() for line in stdout.splitlines() if line.split()[:1] == [component]]


def test_embodied_runner_across_two_nodes_and_the_loss_of_one(nodes, tmp_path):
    out_dir = tmp_path / "embodied"
    run = nodes.run("embodied", embodied_config(out_dir, iterations=ITERATIONS))
    checkpoint = out_dir / "checkpoints"
    deadline = time.monotonic() + 600
    while len([p for p in checkpoint.glob("*") if not p.name.startswith(".")]) < 2 and run.poll() is None:
        assert time.monotonic() < deadline, "no checkpoint after 600 s"
        time.sleep(0.2)
    assert run.poll() is None, run.communicate()[1][-4000:]
    nodes.kill_node()
    out, err = run.communicate(timeout=300)
    assert run.returncode != 0, out[-3000:]
    rollout_node = placement_rows(out, "rollout")[0][2]
    assert rollout_node == "1"  # the placement table: component, rank, node, ...
    lines = [line for line in err.splitlines() if "ClusterError" in line]
    assert lines, err[-4000:]
    message = lines[-1]
    assert "node 1 (" in message and "left the Ray cluster mid-run, taking rollout[rank 0]" in message, message
    assert f"ray start --address={nodes.address}" in message and "resume=true" in message, message
    assert "env[" not in message and "actor[" not in message  # they ran on the head, which is still there

    nodes.add_node()
    out, _ = finished(nodes.run("embodied", embodied_config(out_dir, iterations=ITERATIONS)))
    assert "resumed from" in out
    rows = [json.loads(line) for line in (out_dir / "metrics.jsonl").read_text().splitlines()]
    assert rows[-1]["step"] == ITERATIONS
    summary = json.loads([line for line in out.splitlines() if line.startswith("SUMMARY ")][-1][8:])
    assert summary["env_steps"] == ITERATIONS * 4 * 16


def test_reasoning_runner_with_its_rollout_on_the_second_node(nodes, tiny_llama_dir, tmp_path):
    out_dir = tmp_path / "reasoning"
    config = {
        "iterations": 2, "prompts_per_step": 2, "output_dir": str(out_dir), "save_every": 2,
        "model": {"path": tiny_llama_dir}, "rollout": {"group_size": 2, "max_new_tokens": 6},
        "task": {"eval_size": 2, "verifier": "infinirl.tasks.toy_rewards:response_length"},
        "actor": {"lr": 1e-3, "micro_batch_size": 2}, "eval": {"every": 2},
        "placement": {"actor": "0", "reward": "1", "rollout": "node:1"},
    }
    out, _ = finished(nodes.run("reasoning", config))
    assert placement_rows(out, "rollout")[0][2] == "1" and placement_rows(out, "actor")[0][2] == "0"
    rows = [json.loads(line) for line in (out_dir / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows][-2:] == [1, 2]
    assert rows[1]["train/logprob_mismatch_mean"] < 1e-3  # the weights reached the other node intact
