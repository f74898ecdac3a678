"""Benchmark: a robot at the edge far from its trainer, naive remote control vs the edge link.

One simulated Sawyer (MetaWorld, real time, ``--control-hz``) with a ``--camera`` HxW camera (a real
robot's camera streams e.g. 480x640; training uses a ``--frame-size`` resize of it), one SAC actor
(``SquashedGaussianActor`` on the state vector), and between the robot and the cloud the link emulator
(``python -m infinirl.edge.emulator`` in its own process: ``--rtt-ms`` round trip,
``--mbit`` per direction) carrying one mutual-TLS link:

  naive:  every control step the edge sends the raw observation (the camera frame as uint8 and the
          state as float32, and the last reward) to the cloud, where the policy runs, and waits for
          the action before stepping the robot;
  edge:   the policy runs at the edge on the newest weights; finished episodes go up in the
          background with JPEG frames resized to ``--frame-size``, the resolution training uses
          (``infinirl.edge.edge_client``); the cloud publishes a new
          weight version every ``--publish-every`` seconds (the actor's weights with a small
          change, like a learner's update), which comes down as a compressed delta.

Measured per mode over ``--episodes`` episodes of ``--steps`` steps (no early termination): the
episode wall time (reset to last step) and the bytes the emulator forwarded per episode in each
direction (TLS records included), after every episode was acknowledged. The robot is paced in
real time, so a step cannot be shorter than the control period; a step whose action arrives late
starts the next period late (it is not made up for), as on a real controller.

    python benchmarks/edge_link.py                       # 3 + 3 episodes of 100 steps at 20 Hz, ~1.5 min
    python benchmarks/edge_link.py --control-hz 10 --rtt-ms 120 --mbit 10
    python benchmarks/edge_link.py --camera 224x224      # a camera already at the training resolution

The last stdout line is ONE JSON object: {"benchmark": "edge_link", "ratios": {"edge_episode_speedup":
naive episode s / edge episode s, "edge_bytes_up_reduction": naive bytes up / edge bytes up},
"targets": {...}, "results": {...}}.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if REPO_ROOT not in sys.path:
    sys.path.insert(0, REPO_ROOT)  # run from a checkout without installing

from _bench_common import add_record_argument, conclude, concluded, device_description  # noqa: E402

TARGETS = {"edge_episode_speedup": 3.0}


class Emulator:
    """The link emulator as a child process (its own interpreter: no GIL shared with the robot)."""

    def __init__(self, target, args) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "infinirl.edge.emulator", "--target", f"{target[0]}:{target[1]}",
             "--rtt-ms", str(args.rtt_ms), "--mbit", str(args.mbit)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": REPO_ROOT})
        self.address = tuple(json.loads(self.process.stdout.readline())["listening"])

    def stats(self) -> dict:
        self.process.stdin.write("stats\n")
        self.process.stdin.flush()
        return json.loads(self.process.stdout.readline())

    def close(self) -> None:
        try:
            self.process.stdin.write("quit\n")
            self.process.stdin.flush()
            self.process.wait(timeout=10)
        except (OSError, subprocess.TimeoutExpired):
            self.process.kill()


def make_env(args):
    from infinirl.realworld.driver import make_robot
    from infinirl.realworld.robot_env import RobotEnv, RobotEnvSpec
    from infinirl.realworld.safety import SafeRobot, SafetyConfig

    robot = SafeRobot(make_robot("sim_sawyer", control_hz=args.control_hz, image_size=list(args.camera),
                                 seed=args.seed), SafetyConfig())
    robot.connect()
    spec = RobotEnvSpec(observations=("proprio", "sim_state"), cameras=("corner",), max_episode_steps=args.steps,
                        rewards={"goal_distance": 1.0}, terminate_on_success=False)
    return robot, RobotEnv(robot, spec)


def make_actor(env, seed: int):
    import torch

    from infinirl.models.sac_nets import SquashedGaussianActor

    torch.manual_seed(seed)
    return SquashedGaussianActor(env.observation_size(), env.action_dim, [-1.0] * env.action_dim,
                                 [1.0] * env.action_dim, hidden=(256, 256)).eval()


def run_naive(env, actor, files, args) -> dict:
    """Each step: raw observation up, action down, over one link; the policy runs at the cloud."""
    import torch

    from infinirl.edge.credentials import client_context, server_context
    from infinirl.edge.link import CloudListener, LinkClosedError, dial

    listener = CloudListener("127.0.0.1", 0, server_context(files["cloud"]))
    emulator = Emulator(listener.address, args)
    served = {}

    def serve() -> None:  # the cloud-side policy
        link = served["link"] = listener.accept(timeout=60.0)
        generator = torch.Generator().manual_seed(args.seed)
        try:
            while True:
                message = link.recv("obs", timeout=600.0)
                state = np.frombuffer(message, np.float32, count=env.observation_size())
                with torch.no_grad():
                    action, _, _ = actor.sample(torch.from_numpy(state.copy())[None], generator)
                link.send("action", action[0].numpy().tobytes(), timeout=60.0)
        except (LinkClosedError, TimeoutError):
            return

    server = threading.Thread(target=serve, daemon=True)
    server.start()
    link = dial(emulator.address, client_context(files["edge-0"]))
    durations, late = [], 0
    try:
        for _ in range(args.episodes):
            started = time.monotonic()
            obs, reward = env.reset(), 0.0
            for _ in range(args.steps):
                link.send("obs", b"".join((obs["state"].astype(np.float32).tobytes(),
                                           np.float32(reward).tobytes(), obs["pixels.corner"].tobytes())),
                          timeout=60.0)
                action = np.frombuffer(link.recv("action", timeout=60.0), np.float32)
                step = env.step(action)
                obs, reward, late = step.obs, step.reward, late + int(step.late)
            durations.append(time.monotonic() - started)
        stats = emulator.stats()
    finally:
        link.close()
        emulator.close()
        listener.close()
    return summarise(durations, stats, late, args, frame_bytes=int(np.prod(obs["pixels.corner"].shape)))


def run_edge(env, actor, files, args) -> dict:
    """The policy at the edge; episodes up in the background (JPEG), weight deltas down."""
    import torch

    from infinirl.edge.cloud_hub import CloudHub
    from infinirl.edge.codec import FrameOptions
    from infinirl.edge.edge_actor import EdgeActor, run_episode
    from infinirl.edge.edge_client import EdgeClient

    stored = []
    hub = CloudHub(("127.0.0.1", 0), files["cloud"], on_episode=lambda edge, i, e: stored.append(i)).start()
    emulator = Emulator(hub.address, args)
    weights = {name: tensor.detach().clone() for name, tensor in actor.state_dict().items()}
    stop = threading.Event()

    def learner() -> None:  # a stand-in for the trainer: a new version every publish_every seconds
        generator, version = torch.Generator().manual_seed(args.seed), 0
        while not stop.is_set():
            version += 1
            for tensor in weights.values():
                if tensor.is_floating_point():
                    tensor.add_(1e-4 * torch.randn(tensor.shape, generator=generator))
            hub.publish({n: t.numpy().copy() for n, t in weights.items()}, version)
            stop.wait(args.publish_every)

    publisher = threading.Thread(target=learner, daemon=True)
    publisher.start()
    client = EdgeClient(emulator.address, files["edge-0"], name="edge-0",
                        frames=FrameOptions(format="jpeg", quality=args.jpeg_quality,
                                                               size=args.frame_size)).start()
    edge_actor = EdgeActor(make_actor(env, args.seed + 1), client, warmup="hold")
    durations, late = [], 0
    try:
        client.wait_weights(1, timeout=60.0)
        for _ in range(args.episodes):
            started = time.monotonic()
            episode, info = run_episode(env, edge_actor)
            durations.append(time.monotonic() - started)
            late += info["late_steps"]
            client.submit(episode)
        drained = client.wait_drained(timeout=300.0)
        stop.set()
        publisher.join(timeout=10.0)
        time.sleep(1.0)  # the last weight push and its acknowledgement finish
        stats = emulator.stats()
        hub_stats = hub.stats()
    finally:
        stop.set()
        client.close()
        hub.close()
        emulator.close()
    result = summarise(durations, stats, late, args)
    result.update(drained=drained, episodes_stored=len(stored), weight_versions_received=client.counts[
        "weights_received"], weight_pushes_delta=hub_stats.get("weight_pushes_delta", 0),
        weight_pushes_full=hub_stats.get("weight_pushes_full", 0), holds=edge_actor.holds)
    return result


def summarise(durations, stats, late, args, frame_bytes=None) -> dict:
    episodes = len(durations)
    result = {"episodes": episodes, "episode_s_mean": round(float(np.mean(durations)), 3),
              "episode_s_each": [round(d, 3) for d in durations],
              "step_s_mean": round(float(np.mean(durations)) / args.steps, 4),
              "bytes_up_per_episode": int(stats["bytes_up"] / episodes),
              "bytes_down_per_episode": int(stats["bytes_down"] / episodes), "late_steps": late,
              "link_connections": stats["connections"]}
    if frame_bytes is not None:
        result["raw_frame_bytes"] = frame_bytes
    return result


def height_width(text: str) -> tuple[int, int]:
    try:
        height, width = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW such as 480x640, got {text!r}") from None
    return height, width


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=3, help="per mode")
    parser.add_argument("--steps", type=int, default=100, help="control steps per episode")
    parser.add_argument("--control-hz", type=float, default=20.0)
    parser.add_argument("--camera", type=height_width, default=(480, 640), metavar="HxW",
                        help="the robot camera's raw frame, which the naive mode ships every step")
    parser.add_argument("--frame-size", type=height_width, default=(224, 224), metavar="HxW",
                        help="the training resolution: the edge resizes frames to it before the upload")
    parser.add_argument("--rtt-ms", type=float, default=60.0)
    parser.add_argument("--mbit", type=float, default=20.0, help="per direction")
    parser.add_argument("--jpeg-quality", type=int, default=90)
    parser.add_argument("--publish-every", type=float, default=2.0, help="seconds between weight versions")
    parser.add_argument("--seed", type=int, default=0)
    add_record_argument(parser)
    args = parser.parse_args()
    from infinirl.edge.credentials import issue_credentials

    folder = tempfile.mkdtemp(prefix="bench-edge-")
    started = time.perf_counter()
    try:
        files = issue_credentials(folder, edges=("edge-0",))
        robot, env = make_env(args)
        try:
            actor = make_actor(env, args.seed)
            results = {"naive": run_naive(env, actor, files, args), "edge": run_edge(env, actor, files, args)}
        finally:
            robot.close()
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    naive, edge = results["naive"], results["edge"]
    ratios = {"edge_episode_speedup": round(naive["episode_s_mean"] / edge["episode_s_mean"], 2),
              "edge_bytes_up_reduction": round(naive["bytes_up_per_episode"] / max(edge["bytes_up_per_episode"], 1),
                                               2)}
    final = {"benchmark": "edge_link", "ratios": ratios, "targets": TARGETS, "results": results,
             "settings": {"episodes": args.episodes, "steps": args.steps, "control_hz": args.control_hz,
                          "camera": "x".join(map(str, args.camera)),
                          "frame_size": "x".join(map(str, args.frame_size)), "rtt_ms": args.rtt_ms,
                          "mbit_per_direction": args.mbit,
                          "jpeg_quality": args.jpeg_quality, "publish_every_s": args.publish_every,
                          "seed": args.seed},
             "device": device_description(), "elapsed_s": round(time.perf_counter() - started, 1)}
    return conclude(final, record=(args.record, "Cloud-edge link: naive remote control vs the edge link"))


if __name__ == "__main__":
    sys.exit(concluded("edge_link", main))
