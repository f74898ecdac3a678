"""``python -m infinirl.edge certs | cloud | edge | robot``: credentials, a cloud node, an edge node,
the robot of a ``realworld_sac`` run at the edge (``pipeline.transport=edge``).

    python -m infinirl.edge certs pki --edges edge-0 edge-1
    python -m infinirl.edge cloud --listen 0.0.0.0:7443 --certs pki --replay runs/edge/replay \\
        --weights runs/edge/actor.pt --page-port 8080
    python -m infinirl.edge edge --cloud cloud.example.org:7443 --certs pki --name edge-0 \\
        --robot sim_sawyer --robot-options '{"image_size": 224, "control_hz": 20}' --episodes 0 \\
        --page-target 127.0.0.1:8765
    python -m infinirl.edge robot realworld_sac_sawyer_reach --cloud trainer.example.org:7443 \\
        --certs pki --name edge-0

The cloud node stores every episode that arrives into a replay store (once per episode id: the
store keeps each episode's id as its source id, so a restarted cloud still recognises resends)
and publishes the actor state dict in ``--weights`` (a ``torch.save`` file a trainer rewrites
atomically) as a new version whenever the file changes. The edge node runs episodes on its robot
with the newest weights and ships them (docs/edge.md). Each node prints one JSON line of counters
when it stops (Ctrl-C, or after ``--episodes`` / ``--seconds``). With ``--page-port`` at the cloud
and ``--page-target`` at the edge, connections to the cloud's port reach the edge's intervention
page through the link (:mod:`infinirl.edge.tunnel`).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading
import time

__all__ = ["main"]


def _address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit():
        raise argparse.ArgumentTypeError(f"address {text!r}: expected HOST:PORT")
    return host, int(port)


def _link_options(args):
    from infinirl.edge.link import LinkOptions

    return LinkOptions(heartbeat_s=args.heartbeat_s, dead_after_s=args.dead_after_s)


def _add_link_arguments(parser) -> None:
    parser.add_argument("--heartbeat-s", type=float, default=1.0, help="send a heartbeat after this long quiet")
    parser.add_argument("--dead-after-s", type=float, default=6.0, help="close the link after this long silent")


def _certs(args) -> int:
    from infinirl.edge.credentials import issue_credentials

    issued = issue_credentials(args.folder, edges=tuple(args.edges))
    print(json.dumps({name: files.cert for name, files in issued.items()}))
    return 0


class _ReplaySink:
    """Episodes into a :class:`~infinirl.realworld.replay.ReplayStore` (created from the first
    episode's shapes), each with its episode id as the store's source id, so a restarted cloud
    deduplicates resends (``seen``: the ids stored before it started)."""

    def __init__(self, folder: str) -> None:
        self.folder, self.store = folder, None
        os.makedirs(folder, exist_ok=True)
        self.seen: set[str] = set()
        if os.path.exists(os.path.join(folder, "store.json")):
            from infinirl.realworld.replay import ReplayStore

            self.store = ReplayStore(folder)
            self.seen = set(self.store.sources.sources())

    def __call__(self, edge: str, episode_id: str, episode: dict) -> None:
        from infinirl.realworld.episodes import episode_spec
        from infinirl.realworld.replay import ReplayStore

        if self.store is None:
            cameras = {name[len("pixels."):]: array.shape[1:3] for name, array in episode.items()
                       if name.startswith("pixels.")}
            spec = episode_spec(episode["state"].shape[1], episode["action"].shape[1], cameras)
            self.store = ReplayStore(self.folder, spec)
        self.store.append(episode, source_id=episode_id)  # committed (durably) before the hub acknowledges


def _stop_event() -> threading.Event:
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def _cloud(args) -> int:
    from infinirl.edge.cloud_hub import CloudHub, HubOptions
    from infinirl.edge.credentials import TlsFiles
    from infinirl.edge.tunnel import TunnelListener

    sink = _ReplaySink(args.replay)
    stop = _stop_event()
    page = None
    if args.page_port is not None:  # the hub is looked up per connection, once it exists
        try:
            page = TunnelListener((args.page_host, args.page_port), lambda: hub.tunnel(args.page_edge),
                                  service="page")
        except OSError as exc:
            print(f"error: --page-port {args.page_port} on {args.page_host}: {exc}", file=sys.stderr, flush=True)
            return 2
    hub = CloudHub(args.listen, TlsFiles.in_folder(args.certs, "cloud"), on_episode=sink, seen_ids=sink.seen,
                   options=HubOptions(link=_link_options(args)))
    print(json.dumps({"listening": list(hub.address), "page": list(page.address) if page else None}), flush=True)
    version, mtime = 0, None
    started = time.monotonic()
    with hub:
        if page is not None:
            page.start()
        while not stop.is_set() and (args.seconds is None or time.monotonic() - started < args.seconds):
            if args.weights and os.path.exists(args.weights) and os.path.getmtime(args.weights) != mtime:
                mtime = os.path.getmtime(args.weights)
                version += 1
                import torch

                hub.publish(torch.load(args.weights, map_location="cpu", weights_only=True), version)
            stop.wait(0.5)
        stats = hub.stats()
        if page is not None:
            page.close()
            stats["page_connections"] = dict(page.counts)
    print(json.dumps({**stats, "weights_version": version,
                      "replay_episodes": sink.store.num_episodes if sink.store else 0}), flush=True)
    return 0


def _edge_node(args) -> int:
    from infinirl.edge.codec import FrameOptions
    from infinirl.edge.credentials import TlsFiles
    from infinirl.edge.edge_actor import EdgeActor, run_episode
    from infinirl.edge.edge_client import EdgeClient, EdgeOptions
    from infinirl.edge.link import LinkAuthError
    from infinirl.edge.spool import EpisodeSpool, SpoolFullError
    from infinirl.models.sac_nets import SquashedGaussianActor
    from infinirl.realworld.driver import make_robot
    from infinirl.realworld.robot_env import RobotEnv, RobotEnvSpec
    from infinirl.realworld.safety import SafeRobot, SafetyConfig

    stop = _stop_event()
    # durable: an episode the robot recorded must survive a power loss at the edge until the cloud has it
    spool = EpisodeSpool(args.spool, max_bytes=int(args.spool_gib * (1 << 30)), durable=True)
    size = tuple(int(v) for v in args.frame_size.split("x")) if args.frame_size else None
    try:  # bad files or a refused certificate stop the node before the robot moves; an unreachable cloud not
        client = EdgeClient(args.cloud, TlsFiles.in_folder(args.certs, args.name), name=args.name, spool=spool,
                            frames=FrameOptions(format=args.frame_format, quality=args.jpeg_quality, size=size),
                            options=EdgeOptions(link=_link_options(args)),
                            tunnel_targets={"page": args.page_target} if args.page_target else None).start()
        client.wait_connected(args.connect_wait_s)
    except (LinkAuthError, FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return 2
    robot = SafeRobot(make_robot(args.robot, **json.loads(args.robot_options)), SafetyConfig())
    robot.connect()
    env = RobotEnv(robot, RobotEnvSpec(observations=tuple(args.observations.split(",")),
                                       cameras=tuple(c for c in args.cameras.split(",") if c),
                                       max_episode_steps=args.max_episode_steps))
    actor = SquashedGaussianActor(env.observation_size(), env.action_dim, [-1.0] * env.action_dim,
                                  [1.0] * env.action_dim, hidden=[int(w) for w in args.hidden.split(",")])
    edge_actor = EdgeActor(actor, client, max_offline_s=args.max_offline_s, seed=args.seed)
    episodes, refused, started, drained = 0, 0, time.monotonic(), False
    try:
        client.check()
        while not stop.is_set() and (args.episodes == 0 or episodes < args.episodes):
            if args.seconds is not None and time.monotonic() - started >= args.seconds:
                break
            episode, info = run_episode(env, edge_actor)
            episodes += 1
            try:
                client.submit(episode)
            except SpoolFullError as exc:  # counted and reported; the robot keeps its pace
                refused += 1
                logging.getLogger(__name__).error("%s", exc)
            print(json.dumps({"episode": episodes, **info, "connected": client.connected}), flush=True)
        drained = client.wait_drained(args.drain_s)
    except LinkAuthError as exc:  # permanent: retrying cannot help, acting without the cloud is not the job
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return 2
    finally:
        client.close()
        robot.close()
    print(json.dumps({**client.stats(), "episodes": episodes, "spool_refused": refused, "drained": drained,
                      "holds": edge_actor.holds}), flush=True)
    return 0 if drained and client.error is None else 1


def _run_config(args):
    """The run's config: a resolved file (``--config-file``, what a trainer launching the node writes)
    or a config name with ``key=value`` overrides, as given to ``infinirl train``."""
    from infinirl.config import to_dataclass
    from infinirl.runners.realworld_sac_config import RealWorldSACConfig

    if args.config_file is not None:
        with open(args.config_file) as handle:
            return to_dataclass(RealWorldSACConfig, json.load(handle))
    if args.config is None:
        raise ValueError("name the run's config (e.g. realworld_sac_sawyer_reach) or give --config-file")
    from infinirl.cli import build_config

    _, cfg = build_config(args.config, list(args.overrides))
    if not isinstance(cfg, RealWorldSACConfig):
        raise ValueError(f"config {args.config!r} is not a realworld_sac config")
    return cfg


def _control_loop_of(cfg):
    """The robot's control loop of a run's config, built as the runner builds a robot worker's."""
    from infinirl.realworld.control_loop import RobotControlLoop
    from infinirl.runners.hg_dagger import intervention_spec_of
    from infinirl.runners.realworld_sac import env_spec_of, net_spec_of, robot_setup_of

    return RobotControlLoop(robot_setup_of(cfg), env_spec_of(cfg), net_spec_of(cfg), seed=cfg.seed,
                            intervention=intervention_spec_of(cfg))


def _robot_node(args) -> int:
    from infinirl.config import ConfigError
    from infinirl.edge.link import LinkAuthError
    from infinirl.edge.robot_node import run_robot_node
    from infinirl.realworld.driver import RobotError
    from infinirl.utils.threads import limit_threads

    try:
        cfg = _run_config(args)
    except (ConfigError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return 2
    limit_threads(cfg.actor.num_threads)
    try:
        summary = run_robot_node(cfg, lambda: _control_loop_of(cfg), cloud=args.cloud, certs=args.certs,
                                 name=args.name, spool=args.spool, stop=_stop_event(),
                                 connect_wait_s=args.connect_wait_s, parent_pid=args.parent_pid)
    except (LinkAuthError, FileNotFoundError, ValueError) as exc:  # before the robot moved, or a refusal
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return 2
    except RobotError as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return 1
    print(json.dumps(summary), flush=True)
    return 0 if summary["drained"] else 1


def _add_robot_parser(sub) -> None:
    robot = sub.add_parser("robot", help="run the robot of a realworld_sac run (pipeline.transport=edge) here")
    robot.add_argument("config", nargs="?", default=None, help="the run's config name, as given to infinirl train")
    robot.add_argument("overrides", nargs="*", help="the run's key=value overrides (the same as the trainer's)")
    robot.add_argument("--config-file", default=None, help="a resolved run config (JSON) instead of a name")
    robot.add_argument("--cloud", type=_address, required=True, help="HOST:PORT of the trainer's edge.listen")
    robot.add_argument("--certs", required=True, help="folder with ca.pem, <name>.pem, <name>.key")
    robot.add_argument("--name", default=None, help="the edge's name (default: the config's edge.name)")
    robot.add_argument("--spool", default=None, help="on-disk outbox (default: edge.spool, else "
                                                     "<output_dir>/edge/spool)")
    robot.add_argument("--connect-wait-s", type=float, default=60.0,
                       help="before building the robot, wait this long for the first connection")
    robot.add_argument("--parent-pid", type=int, default=None,
                       help="end when this process (the trainer that launched the node) is gone")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m infinirl.edge", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    certs = sub.add_parser("certs", help="issue a CA, the cloud's and the edges' certificates")
    certs.add_argument("folder")
    certs.add_argument("--edges", nargs="+", default=["edge-0"])
    cloud = sub.add_parser("cloud", help="accept edges, store their episodes, publish weights")
    cloud.add_argument("--listen", type=_address, default=("0.0.0.0", 7443))
    cloud.add_argument("--certs", required=True, help="folder with ca.pem, cloud.pem, cloud.key")
    cloud.add_argument("--replay", required=True, help="replay store folder")
    cloud.add_argument("--weights", default=None, help="actor state dict file to publish when it changes")
    cloud.add_argument("--seconds", type=float, default=None)
    cloud.add_argument("--page-port", type=int, default=None,
                       help="serve the edge's intervention page (its --page-target) on this cloud port")
    cloud.add_argument("--page-host", default="127.0.0.1",
                       help="interface of --page-port (the page's token is its only guard: keep it local)")
    cloud.add_argument("--page-edge", default=None,
                       help="the edge whose page --page-port shows (default: the one connected edge)")
    _add_link_arguments(cloud)
    edge = sub.add_parser("edge", help="run a robot at the edge, shipping its episodes to the cloud")
    edge.add_argument("--cloud", type=_address, required=True)
    edge.add_argument("--certs", required=True, help="folder with ca.pem, <name>.pem, <name>.key")
    edge.add_argument("--name", default="edge-0")
    edge.add_argument("--robot", default="sim_sawyer")
    edge.add_argument("--robot-options", default="{}", help="JSON of the driver's options")
    edge.add_argument("--observations", default="proprio,sim_state")
    edge.add_argument("--cameras", default="")
    edge.add_argument("--max-episode-steps", type=int, default=100)
    edge.add_argument("--hidden", default="256,256")
    edge.add_argument("--episodes", type=int, default=0, help="0: until stopped")
    edge.add_argument("--seconds", type=float, default=None)
    edge.add_argument("--spool", default=None, help="folder of the on-disk outbox (default: in memory)")
    edge.add_argument("--spool-gib", type=float, default=2.0)
    edge.add_argument("--frame-format", default="jpeg", choices=["jpeg", "png"])
    edge.add_argument("--jpeg-quality", type=int, default=90)
    edge.add_argument("--frame-size", default=None, help="HxW to resize camera frames to before sending")
    edge.add_argument("--max-offline-s", type=float, default=30.0, help="act on old weights this long, then hold")
    edge.add_argument("--drain-s", type=float, default=60.0, help="at the end, wait this long for acknowledgements")
    edge.add_argument("--seed", type=int, default=0)
    edge.add_argument("--connect-wait-s", type=float, default=10.0,
                      help="before starting the robot, wait this long for the first connection")
    edge.add_argument("--page-target", type=_address, default=None,
                      help="HOST:PORT of the intervention page at the edge, served by the cloud's --page-port")
    _add_link_arguments(edge)
    _add_robot_parser(sub)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    return {"certs": _certs, "cloud": _cloud, "edge": _edge_node, "robot": _robot_node}[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
