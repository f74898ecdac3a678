"""The trainer's end of ``pipeline.transport=edge``: a hub for the run's robot at the edge.

:class:`TrainerLink` runs a :class:`~infinirl.edge.cloud_hub.CloudHub` in the run's driver. Each
episode the edge sends is put on the learner's channel once per episode id, carrying that id
(:data:`~infinirl.realworld.learner_worker.SOURCE_ID`). The learner commits it to its replay store
under that id and reports the id back on the channel
(:func:`~infinirl.realworld.learner_worker.committed_key`); only then does the hub acknowledge it
to the edge, whose spool keeps the episode until that acknowledgement. So a trainer that dies, or a
link that drops, between the channel and the store loses no episode: the edge resends it, and the
store, which knows the ids it holds, keeps it once (also across a restarted trainer).
:meth:`TrainerLink.send_weights` publishes the learner's newest snapshot on the link (the hub sends
it as a delta when smaller; a slow edge skips to the newest version).
:class:`EdgeRobots` drives the edge's robot by calls on the link (:mod:`infinirl.edge.robot_calls`)
with the subset of a Ray worker group's interface the runner uses, so the runner's iteration logic
is the same for both transports.

With ``edge.launch`` the link also starts the edge node (:mod:`infinirl.edge.robot_node`) on this
machine as a process of its own, with the run's config (``<output_dir>/edge/config.json``) and its
output in ``<output_dir>/edge/node.log``. With ``edge.page_listen`` it serves the edge robot's web
intervention page on that address, each browser connection carried by the link's tunnel
(:mod:`infinirl.edge.tunnel`) to the page beside the robot.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import subprocess
import sys
import threading
import time
from urllib.parse import quote

from infinirl.edge.cloud_hub import CloudHub, HubOptions, wait_for
from infinirl.edge.credentials import TlsFiles
from infinirl.edge.link import LinkOptions
from infinirl.edge.robot_calls import RobotCaller
from infinirl.edge.robot_node import shared_config
from infinirl.edge.tunnel import TunnelListener

__all__ = ["EdgeRobots", "TrainerLink", "differences", "link_metrics"]

logger = logging.getLogger(__name__)
_EXIT_GRACE_S = 30.0
_PUT_TIMEOUT_S = 60.0
_COMMITS_WAIT_S = 0.5


def differences(ours: dict, theirs: dict, prefix: str = "") -> dict[str, tuple]:
    """Every dotted key whose value differs between two plain config trees: ``key -> (ours, theirs)``."""
    changes: dict[str, tuple] = {}
    for key in sorted(set(ours) | set(theirs)):
        a, b = ours.get(key), theirs.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            changes.update(differences(a, b, f"{prefix}{key}."))
        elif a != b:
            changes[f"{prefix}{key}"] = (a, b)
    return changes


# The hub's counters (cumulative since the run started) logged as link/<name>.
_HUB_COUNTERS = ("connects", "refused", "episodes", "duplicates", "episode_bytes", "weight_bytes",
                 "weight_pushes_full", "weight_pushes_delta", "delivery_failures")
# The edge's counters (its report with every robot stats call; cumulative since the edge node started)
# logged as edge/<name>: outages the edge lived through, and what it did meanwhile.
_EDGE_COUNTERS = {"link_outages": "outages", "link_offline_s": "offline_s",
                  "link_episodes_spooled_offline": "episodes_spooled_offline", "offline_holds": "offline_holds",
                  "offline_hold_s": "offline_hold_s", "spool_refused": "spool_refused"}


def link_metrics(hub: dict, edge: str, edge_counts: dict) -> dict[str, float]:
    """The trainer's view of its link to ``edge``: ``link/connected`` (1 when the edge is connected
    now), the hub's counters as ``link/<counter>``, and the edge's outage counters as ``edge/<counter>``,
    so an outage shows in the run's metrics, not only in the edge's log."""
    metrics = {"link/connected": float(edge in hub.get("edges", ()))}
    metrics.update({f"link/{name}": float(hub.get(name, 0)) for name in _HUB_COUNTERS})
    metrics.update({f"edge/{ours}": float(edge_counts.get(theirs, 0)) for theirs, ours in _EDGE_COUNTERS.items()})
    return metrics


class _Answer:
    """A finished call, shaped like a worker group's pending call (``wait`` returns one value per rank)."""

    def __init__(self, value) -> None:
        self.value = value

    def wait(self, timeout: float | None = None) -> list:
        return [self.value]

    def done(self) -> bool:
        return True


class _PublishedWeights:
    """A published version: done at once (the hub sends it when the edge can take it); ``wait``
    waits until the edge acknowledged it or a newer one, or ``timeout`` passed (an edge offline
    meanwhile keeps acting on what it holds)."""

    def __init__(self, hub: CloudHub, edge: str, version: int) -> None:
        self.hub, self.edge, self.version = hub, edge, version

    def done(self) -> bool:
        return True

    def wait(self, timeout: float | None = None) -> None:
        held = lambda: (self.hub.edge_version(self.edge) or 0) >= self.version  # noqa: E731
        if not wait_for(held, 60.0 if timeout is None else timeout):
            logger.warning("edge %s has not acknowledged weight version %d yet; it acts on what it holds",
                           self.edge, self.version)


class EdgeRobots:
    """The robot at one edge, behind the calls a worker group of robot ranks answers (one rank)."""

    world_size = 1

    def __init__(self, caller: RobotCaller, timeout_s: float, expected_config: dict) -> None:
        self.caller, self.timeout_s, self.expected_config = caller, timeout_s, expected_config

    def _call(self, method: str, *args):
        result, episodes = self.caller.call(method, *args, timeout=self.timeout_s)
        return episodes if method == "demonstrations" else result

    def describe(self) -> _Answer:
        from infinirl.config import ConfigError

        described = self._call("describe")
        changes = differences(json.loads(json.dumps(self.expected_config)), described.pop("config"))
        if changes:
            keys = ", ".join(f"{key} ({theirs!r} at the edge, {ours!r} here)"
                             for key, (ours, theirs) in list(changes.items())[:4])
            raise ConfigError(f"the edge {self.caller.edge} runs another robot or policy config: {keys}; start "
                              "the edge with the trainer's config and overrides")
        described["cameras"] = {name: tuple(size) for name, size in described["cameras"].items()}
        return _Answer(described)

    def call_each(self, method: str, args: list[tuple]) -> _Answer:
        (own,) = args
        return _Answer(self._call(method, *(dataclasses.asdict(a) if dataclasses.is_dataclass(a) else a
                                            for a in own)))

    def call(self, method: str, *args, ranks=None) -> _Answer:
        return _Answer(self._call(method, *args))

    def start(self, channel=None) -> _Answer:
        return _Answer(self._call("start"))

    def stop(self) -> _Answer:
        return _Answer(self._call("stop"))

    def stats(self) -> _Answer:
        return _Answer(self._call("stats"))

    def evaluate(self, num_episodes: int) -> _Answer:
        return _Answer(self._call("evaluate", num_episodes))

    def close(self) -> _Answer:
        return _Answer(self._call("close"))

    def shutdown(self) -> None:
        """Nothing to release here: the edge node ends when it is closed (or is stopped at the edge)."""


class TrainerLink:
    """See the module docstring; ``cfg`` is the run's ``RealWorldSACConfig``; the edge's episodes go
    on ``channel`` under ``key`` (the learner's), and its reports of committed ids come back there."""

    def __init__(self, cfg, channel, key: str = "episodes") -> None:
        from infinirl.realworld.learner_worker import committed_key

        self.cfg, self.channel, self.key, self.commits_key = cfg, channel, key, committed_key(key)
        self.folder = os.path.abspath(os.path.join(cfg.output_dir, "edge"))
        os.makedirs(self.folder, exist_ok=True)
        link = LinkOptions(heartbeat_s=cfg.edge.heartbeat_s, dead_after_s=cfg.edge.dead_after_s)
        host, _, port = cfg.edge.listen.rpartition(":")  # checked by the config
        self.hub = CloudHub((host, int(port)), TlsFiles.in_folder(cfg.edge.certs, "cloud"),
                            on_episode=self._on_episode, options=HubOptions(link=link), commit_acks=True)
        self.process: subprocess.Popen | None = None
        self.page: TunnelListener | None = None  # edge.page_listen: the edge's intervention page, served here
        self._stop = threading.Event()
        self._commits = threading.Thread(target=self._follow_commits, name="edge-commits", daemon=True)

    def _on_episode(self, edge: str, episode_id: str, episode: dict) -> None:
        from infinirl.realworld.learner_worker import SOURCE_ID

        self.channel.put({**episode, SOURCE_ID: episode_id}, key=self.key, timeout=_PUT_TIMEOUT_S)

    def _follow_commits(self) -> None:
        """Acknowledge to the edge what the learner reports committed, until closed."""
        from infinirl.runtime import ChannelClosed, ChannelError

        while not self._stop.is_set():
            try:
                reports = self.channel.get_batch(1e12, key=self.commits_key, timeout=_COMMITS_WAIT_S)
            except TimeoutError:
                continue
            except (ChannelClosed, ChannelError) as exc:  # the run is ending; the edge resends what is unacknowledged
                logger.info("edge link: no more commit reports (%r)", exc)
                return
            self.hub.commit(episode_id for report in reports for episode_id in report["ids"])

    def start(self) -> TrainerLink:
        self.hub.start()
        self._commits.start()
        print(f"edge link: waiting for edge {self.cfg.edge.name} on {self.hub.address[0]}:{self.hub.address[1]}",
              flush=True)
        if self.cfg.edge.page_listen is not None:
            self.page = self._serve_page(self.cfg.edge.page_listen)
        if self.cfg.edge.launch:
            self.process = self._launch_node()
        return self

    def _serve_page(self, listen: str) -> TunnelListener:
        """Accept browsers on ``listen``; each connection goes through the link to the edge's page."""
        host, _, port = listen.rpartition(":")  # checked by the config
        try:
            page = TunnelListener((host, int(port)), lambda: self.hub.tunnel(self.cfg.edge.name), service="page")
        except OSError as exc:
            raise RuntimeError(f"edge.page_listen={listen}: cannot listen there ({exc}); pick a free port or "
                               "0") from exc
        page.start()
        token = self.cfg.interventions.options.get("token")
        shown = f"[{page.address[0]}]" if ":" in page.address[0] else page.address[0]
        query = f"?token={quote(str(token), safe='')}" if token else ""
        print(f"intervention page of edge {self.cfg.edge.name}'s robot, through the link: "
              f"http://{shown}:{page.address[1]}/{query}", flush=True)
        return page

    def robots(self) -> EdgeRobots:
        """The edge's robot, once the edge connected (within ``edge.connect_timeout_s``)."""
        name, timeout = self.cfg.edge.name, self.cfg.edge.connect_timeout_s
        deadline = time.monotonic() + timeout
        while name not in self.hub.connected_edges():
            self.check_node()
            if time.monotonic() >= deadline:
                refused = f"; refused: {self.hub.refusals[-1]}" if self.hub.refusals else ""
                raise TimeoutError(f"edge {name} did not connect to {self.cfg.edge.listen} within {timeout:.0f} s "
                                   f"(edge.connect_timeout_s){refused}")
            time.sleep(0.1)
        return EdgeRobots(RobotCaller(self.hub, name, check=self.check_node), timeout, shared_config(self.cfg))

    def check_node(self) -> None:
        """Raise when the edge node launched here has ended (with its last line of output)."""
        if self.process is not None and self.process.poll() is not None:
            raise RuntimeError(f"the edge node launched here exited with status {self.process.returncode}: "
                               f"{self._log_tail()} (log: {os.path.join(self.folder, 'node.log')})")

    def send_weights(self, learner, robots, version: int, interrupt: bool = False) -> _PublishedWeights:
        """Publish the learner's newest snapshot (``start_weight_sync``'s signature; ``version`` is
        the one the snapshot carries, read from it)."""
        from infinirl.realworld.control_loop import VERSION_TENSOR

        named = learner.weights_for_sync().wait(timeout=60)[0]
        stamped = next(int(t.reshape(-1)[0]) for n, t in named if n == VERSION_TENSOR)
        self.hub.publish({n: t.numpy() for n, t in named if n != VERSION_TENSOR}, stamped)
        return _PublishedWeights(self.hub, self.cfg.edge.name, stamped)

    def stats(self) -> dict:
        stats = self.hub.stats()
        if self.page is not None:
            stats["page_connections"] = dict(self.page.counts)
        return stats

    def metrics(self, robots: list[dict]) -> dict[str, float]:
        """This iteration's link metrics (:func:`link_metrics`) from the hub and the edge's report."""
        return link_metrics(self.hub.stats(), self.cfg.edge.name, robots[0]["counts"] if robots else {})

    def close(self) -> None:
        if self.process is not None:
            try:
                self.process.wait(self.cfg.edge.drain_s + _EXIT_GRACE_S)
            except subprocess.TimeoutExpired:
                logger.warning("the edge node launched here did not end; terminating it")
                self.process.terminate()
                self.process.wait(_EXIT_GRACE_S)
        if self.page is not None:
            self.page.close()
        self._stop.set()
        if self._commits.is_alive():
            self._commits.join(_COMMITS_WAIT_S * 4)
        self.hub.close()

    # ------------------------------------------------------------------ the local edge node
    def _launch_node(self) -> subprocess.Popen:
        from infinirl.config import to_plain
        from infinirl.utils import write_json_atomic

        config_path = os.path.join(self.folder, "config.json")
        write_json_atomic(config_path, to_plain(self.cfg))
        dial = self.cfg.edge.dial or f"127.0.0.1:{self.hub.address[1]}"
        command = [sys.executable, "-m", "infinirl.edge", "robot", "--config-file", config_path, "--cloud", dial,
                   "--certs", os.path.abspath(self.cfg.edge.certs), "--name", self.cfg.edge.name,
                   "--parent-pid", str(os.getpid())]
        with open(os.path.join(self.folder, "node.log"), "ab") as log:
            return subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)

    def _log_tail(self) -> str:
        try:
            with open(os.path.join(self.folder, "node.log")) as handle:
                lines = [line.strip() for line in handle if line.strip()]
        except OSError:
            return "no log"
        return lines[-1] if lines else "no output"
