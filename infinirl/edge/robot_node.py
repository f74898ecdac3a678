"""The robot of a ``realworld_sac`` run at the edge (``pipeline.transport=edge``).

:func:`run_robot_node` builds the run's robot and policy from its config exactly as a Ray robot
worker does (:class:`~infinirl.realworld.control_loop.RobotControlLoop`), dials the trainer with an
:class:`~infinirl.edge.edge_client.EdgeClient`, and answers the trainer's robot calls
(:mod:`infinirl.edge.robot_calls`) until the trainer says ``close`` or the node is stopped:

* episodes: each finished one is submitted to the client's spool (kept on disk until the trainer
  acknowledges it, resent after an outage, stored once by id); a full spool refuses the episode,
  which is counted (``spool_refused``) and logged, and the robot keeps its pace;
* weights: the trainer publishes each new version on the link (deltas when smaller); before every
  step the control loop loads the newest version the client holds, as a Ray worker loads its staged
  weights;
* outages: while the link is down the robot keeps acting on the last weights it holds and its
  episodes wait in the spool; once the link has been down for ``edge.max_offline_s`` the robot holds
  (the driver's ``hold()``, heartbeats kept, so it is paused, not stopped) until the link returns,
  then acts on (and loads the versions the trainer pushes). Holds are counted (``offline_holds``,
  ``offline_hold_s``) and logged; the client logs each outage's length and the episodes spooled;
* ``stop`` ends the control loop after its present step and waits until the trainer acknowledged
  every spooled episode (``edge.drain_s``), so the learner has them before it stops.

``python -m infinirl.edge robot <config> [overrides] --cloud HOST:PORT --certs DIR`` runs it.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import Counter
from collections.abc import Callable

import torch

from infinirl.edge.codec import FrameOptions
from infinirl.edge.credentials import TlsFiles
from infinirl.edge.edge_client import EdgeClient, EdgeOptions
from infinirl.edge.link import LinkOptions
from infinirl.edge.robot_calls import RobotCallServer
from infinirl.edge.spool import EpisodeSpool, SpoolFullError
from infinirl.realworld.control_loop import PolicyLayout, RobotControlLoop
from infinirl.realworld.driver import RobotError

__all__ = ["EdgeRobotNode", "edge_options_of", "run_robot_node", "shared_config"]

logger = logging.getLogger(__name__)
_HOLD_POLL_S = 0.1  # while holding: how often the link is looked at (and the robot's heartbeat given)

SHARED_SECTIONS = ("seed", "robot", "task", "network", "interventions")
"""Config sections that must agree between the trainer and the edge (the robot and the policy)."""


def shared_config(cfg) -> dict:
    """The plain values of :data:`SHARED_SECTIONS` (the trainer compares the edge's with its own)."""
    from infinirl.config import to_plain

    plain = to_plain(cfg)
    return {key: plain[key] for key in SHARED_SECTIONS}


def edge_options_of(cfg) -> EdgeOptions:
    return EdgeOptions(link=LinkOptions(heartbeat_s=cfg.edge.heartbeat_s, dead_after_s=cfg.edge.dead_after_s))


class EdgeRobotNode:
    """The control loop of one robot and the client of its link (see the module docstring)."""

    def __init__(self, cfg, loop, client: EdgeClient) -> None:
        self.cfg, self.loop, self.client = cfg, loop, client
        self.closed = threading.Event()
        self.halted = threading.Event()  # the loop is stopping: an offline hold ends
        self.spool_refused = 0
        self.counts: Counter[str] = Counter()

    def handlers(self) -> dict:
        return {"describe": self.describe, "configure": self.configure, "start": self.start, "stop": self.stop,
                "stats": self.stats, "evaluate": self.evaluate, "demonstrations": self.demonstrations,
                "close": self.close}

    # ------------------------------------------------------------------ the transport
    def between_steps(self) -> None:
        """Before each step of the control loop: hold while offline too long, then load new weights."""
        self.hold_while_offline()
        self.load_newest_weights()

    def hold_while_offline(self) -> None:
        """Past ``edge.max_offline_s`` without the link, hold the robot until the link returns (or
        the loop stops). The heartbeat goes on: a deliberate pause, not a stalled pipeline."""
        limit = self.cfg.edge.max_offline_s
        if self.client.offline_s() <= limit:
            return
        robot = self.loop.robot
        logger.warning("edge %s: the link has been down for %.1f s (edge.max_offline_s=%g): holding the robot "
                       "until it returns", self.client.name, self.client.offline_s(), limit)
        self.counts["offline_holds"] += 1
        started = time.monotonic()
        robot.hold()
        while not self.client.connected and not self.halted.is_set():
            self.client.check()
            robot.heartbeat()
            self.halted.wait(_HOLD_POLL_S)
        held = time.monotonic() - started
        self.counts["offline_hold_s"] += held
        logger.warning("edge %s: %s after holding the robot %.1f s", self.client.name,
                       "stopping" if self.halted.is_set() else "the link is back; acting again", held)

    def load_newest_weights(self) -> None:
        """Between steps: load the client's newest version when the policy acts with another."""
        held = self.client.weights
        if held is not None and held.version != self.loop.policy_version:
            self.loop.load_weights(((name, torch.from_numpy(array)) for name, array in held.tensors.items()),
                                   held.version)

    def submit(self, episode: dict) -> None:
        try:
            self.client.submit(episode)
        except SpoolFullError as exc:  # counted and reported; the robot keeps its pace
            self.spool_refused += 1
            logger.error("%s", exc)

    # ------------------------------------------------------------------ the trainer's calls
    def describe(self):
        return {**self.loop.describe(), "config": shared_config(self.cfg)}, []

    def configure(self, layout: dict):
        self.loop.configure(PolicyLayout(**layout))
        return None, []

    def start(self):
        self.halted.clear()
        self.loop.start(self.submit, between_steps=self.between_steps)
        return None, []

    def stop(self):
        self.halted.set()
        stats = self.loop.stop()
        drained = self.client.wait_drained(self.cfg.edge.drain_s)
        return {**self._with_link(stats), "drained": drained}, []

    def stats(self):
        return self._with_link(self.loop.stats()), []

    def evaluate(self, num_episodes: int):
        return self.loop.evaluate(num_episodes), []

    def demonstrations(self, num_episodes: int, policy: str, seed: int, noise_std: float, options: dict):
        return None, self.loop.demonstrations(num_episodes, policy, seed, noise_std, options)

    def close(self):
        self.closed.set()
        return None, []

    def _with_link(self, stats: dict) -> dict:
        counts = {**stats["counts"], **self.counts, "spool_refused": self.spool_refused,
                  **{f"link_{key}": value for key, value in self.client.counts.items()}}
        return {**stats, "counts": counts}


def run_robot_node(cfg, build_loop: Callable[[], RobotControlLoop], *, cloud: tuple[str, int], certs: str,
                   name: str | None = None, spool: str | None = None, stop: threading.Event | None = None,
                   connect_wait_s: float = 60.0, parent_pid: int | None = None) -> dict:
    """Run the robot of ``cfg`` (a ``RealWorldSACConfig``; ``build_loop()`` builds its control loop,
    the runner's way) at this edge until the trainer closes it or ``stop`` is set; returns the node's
    counters. Raises a refused certificate or missing files before the robot moves. With
    ``parent_pid`` (a trainer that launched the node), the node also ends when that process is gone,
    so a killed trainer leaves no robot running on its machine."""

    name = name or cfg.edge.name
    stop = stop or threading.Event()
    files = TlsFiles.in_folder(certs, name)
    files.check()
    spool_dir = spool or cfg.edge.spool or os.path.join(cfg.output_dir, "edge", "spool")
    client = EdgeClient(cloud, files, name=name,
                        spool=EpisodeSpool(spool_dir, max_bytes=int(cfg.edge.spool_gib * (1 << 30)), durable=True),
                        frames=FrameOptions(format=cfg.edge.frame_format, quality=cfg.edge.jpeg_quality),
                        options=edge_options_of(cfg)).start()
    server = None
    try:
        client.wait_connected(connect_wait_s)  # a refused certificate ends the node here, before the robot moves
        loop = build_loop()
        page = getattr(loop.intervention_device, "local_address", None)
        if page is not None:  # the web intervention page: the trainer serves it through the link (edge.page_listen)
            client.offer("page", page)
        node = EdgeRobotNode(cfg, loop, client)
        server = RobotCallServer(client, node.handlers()).start()
        try:
            while not (node.closed.is_set() or stop.is_set()):
                client.check()
                if parent_pid is not None and os.getppid() != parent_pid:
                    logger.warning("the trainer that launched this edge node (pid %d) is gone; stopping", parent_pid)
                    break
                stop.wait(0.2)
            final = node.stop()[0]  # a no-op when the trainer stopped the loop already
        finally:
            try:
                loop.close()
            except RobotError as exc:  # already raised above, or reported by the trainer's last call
                logger.warning("%s", exc)
        return {**client.stats(), "episodes_sent": final["counts"].get("episodes_sent", 0),
                "spool_refused": node.spool_refused, "drained": final["drained"],
                "policy_version": final["policy_version"]}
    finally:
        if server is not None:
            server.close()
        client.close()

