"""Where a MetaWorld policy's hand ends against where the task's object is, episode by episode.

A policy that fails some layouts of a task and solves others may ignore where the object is and
replay one motion (a behaviour-cloned VLA from few demonstrations does). This runs a trained
embodied run's policy (its ``config.json`` and latest checkpoint; ``--untrained`` for the policy as
the run built it, e.g. a frozen VLA's noise-free start) noise-free on held-out layouts of one task,
and prints per episode the object's start position, the hand's position after ``--at-step`` steps
(50: before the demo's tasks are solved, so every episode is compared at the same point of its
motion; the end would compare a solved episode's last step with a failed one's drift) and the
outcome, then how much the hand follows the object: the least-squares slope of the hand's x (y)
on the object's x (y) over the episodes, 1 where it goes where the object is, 0 where it ignores it.

    python scripts/diagnose_vla_episodes.py runs/ppo_vla_metaworld_residual --task button-press-topdown-v3
    python scripts/diagnose_vla_episodes.py runs/ppo_vla_metaworld_residual --task button-press-topdown-v3 --untrained

``--probe N`` (a frozen VLA's policy: steered or residual) also asks whether the policy *could* know
where the object is: a ridge regression from the VLA's features (what the small networks read) of
``N`` freshly reset layouts to the object's x and y, its R² on a held-out quarter.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np
import torch

# MetaWorld's observation vector: the hand's position, the gripper's opening, the first object's position
_HAND, _OBJECT = slice(0, 3), slice(4, 7)


def _fail(message: str) -> None:
    sys.exit(f"diagnose_vla_episodes: {message}")


def read_config(run_dir: str) -> dict:
    """The run's ``config.json``; a one-line exit unless it is an embodied MetaWorld run."""
    path = os.path.join(run_dir, "config.json")
    if not os.path.isfile(path):
        _fail(f"{path} not found: give the output_dir of an embodied run (infinirl train ...)")
    cfg = json.load(open(path))
    if cfg.get("runner") != "embodied" or not cfg["env"]["name"].startswith("metaworld"):
        _fail(f"{path} is not an embodied MetaWorld run (runner {cfg.get('runner')!r}, env {cfg['env']['name']!r})")
    return cfg


def load_policy(cfg: dict, run_dir: str, untrained: bool):
    """The run's policy (weights of the latest checkpoint unless ``untrained``)."""
    from infinirl.components.embodied_policy import build_embodied_policy
    from infinirl.envs.registry import make_env

    probe = make_env(cfg["env"]["name"], 1, **cfg["env"].get("kwargs", {}))
    try:
        spec, space = probe.observation_spec, probe.action_space
    finally:
        probe.close()
    pol = cfg["policy"]
    model = build_embodied_policy(pol["name"], pol.get("kwargs", {}), spec, space, pol.get("chunk", 1),
                                  pol.get("normalize_obs", False), pol.get("normalize_keys"), pol.get("obs_clip", 10.0))
    if not untrained:
        root = os.path.join(run_dir, "checkpoints")
        steps = sorted(d for d in os.listdir(root) if d.startswith("iter_")) if os.path.isdir(root) else []
        if not steps:
            _fail(f"no checkpoint under {root}: the run saved none (save_every), or pass --untrained")
        state = torch.load(os.path.join(root, steps[-1], "actor", "actor.pt"), map_location="cpu", weights_only=False)
        model.load_state_dict(state["model"])
        print(f"weights: {os.path.join(root, steps[-1])}")
    return model.eval()


def _one_env_batch(obs: dict) -> dict:
    """One env's observation as a batch of one: arrays gain a leading axis, the instruction a list."""
    return {key: (torch.as_tensor(value)[None] if isinstance(value, np.ndarray) else [value])
            for key, value in obs.items()}


def _rounded(vector: np.ndarray) -> list[float]:
    return [round(float(v), 3) for v in vector]


def run_episode(env, model, seed: int, max_steps: int, at_step: int) -> dict:
    obs = env.reset(seed=seed)
    start = obs["state"].copy()
    hands, steps, success = [], 0, False
    while steps < max_steps and not success:
        batch = _one_env_batch(obs)
        with torch.no_grad():
            chunk = model.act(batch, deterministic=True).actions[0].reshape(model.chunk, -1).numpy()
        for action in chunk:
            step = env.step(action)
            obs, steps = step.obs, steps + 1
            hands.append(obs["state"][_HAND].copy())
            if step.success or step.truncated or step.terminated or steps >= max_steps:
                success = success or step.success
                break
        if step.truncated or step.terminated:
            break
    objects = obs["state"][_OBJECT]
    return {"seed": seed, "success": bool(success), "steps": steps, "object_start": _rounded(start[_OBJECT]),
            "hand": _rounded(hands[min(at_step, len(hands)) - 1]),
            "closest_hand_object_m": round(float(np.linalg.norm(np.array(hands) - objects, axis=1).min()), 3)}


def ridge_r2(features: np.ndarray, targets: np.ndarray, penalty: float = 10.0) -> list[float]:
    """R² per target column of a ridge regression (features standardised on the fitting rows) fitted
    on the first three quarters of the rows and scored on the last quarter."""
    if len(features) < 8:
        raise ValueError(f"ridge_r2 needs at least 8 rows, got {len(features)}")
    split = len(features) * 3 // 4
    mean, std = features[:split].mean(0), features[:split].std(0) + 1e-6
    x = (features - mean) / std
    fit, held = x[:split], x[split:]
    offset = targets[:split].mean(0)
    # the dual form: as many unknowns as fitting rows, however wide the features
    weights = fit.T @ np.linalg.solve(fit @ fit.T + penalty * np.eye(split), targets[:split] - offset)
    residual = ((held @ weights + offset - targets[split:]) ** 2).sum(0)
    spread = ((targets[split:] - targets[split:].mean(0)) ** 2).sum(0)
    return [float(v) for v in 1.0 - residual / spread]


def probe_features(model, env, count: int) -> list[float]:
    """R² of the object's x and y read linearly off the frozen VLA's features at ``count`` resets."""
    policy = model.policy
    if not hasattr(policy, "features"):
        _fail(f"--probe reads a frozen VLA's features; {type(policy).__name__} has none")
    rows, objects = [], []
    for k in range(count):
        obs = env.reset(seed=k)
        batch = _one_env_batch(obs)
        with torch.no_grad():
            rows.append(policy.features(model.normalize(batch))[0][0].float().numpy())
        objects.append(obs["state"][_OBJECT][:2])
    return ridge_r2(np.array(rows, np.float64), np.array(objects, np.float64))


def follow_slopes(rows: list[dict]) -> list[float]:
    """Least-squares slope of the hand's position on the object's start, for x and y."""
    objects = np.array([r["object_start"] for r in rows])
    hands = np.array([r["hand"] for r in rows])
    slopes = []
    for axis in (0, 1):
        spread = objects[:, axis] - objects[:, axis].mean()
        denominator = float((spread ** 2).sum())
        slopes.append(float((spread * (hands[:, axis] - hands[:, axis].mean())).sum() / denominator)
                      if denominator > 0 else float("nan"))
    return slopes


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", help="an embodied run's output_dir")
    parser.add_argument("--task", required=True, help="one MetaWorld task of the run, e.g. button-press-topdown-v3")
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--untrained", action="store_true", help="the policy as the run built it, no checkpoint")
    parser.add_argument("--at-step", type=int, default=50, help="the step whose hand position is compared")
    parser.add_argument("--probe", type=int, default=0, help="layouts for the features' ridge probe (0: none)")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    if args.at_step < 1:
        _fail(f"--at-step {args.at_step}: at least 1")
    if args.probe and args.probe < 8:
        _fail(f"--probe {args.probe}: at least 8 layouts (a quarter of them is held out)")
    if args.episodes < 2:
        _fail(f"--episodes {args.episodes}: at least 2 (the slopes need a spread of layouts)")
    torch.set_num_threads(args.threads)
    from infinirl.envs.metaworld_env import MetaWorldSubEnv
    from infinirl.runners.sim_config import EVAL_SEED_BASE

    cfg = read_config(args.run)
    tasks = cfg["env"]["name"].split(":", 1)[1].split(",")
    if args.task not in tasks:
        _fail(f"--task {args.task!r} is not one of the run's tasks {tasks}")
    model = load_policy(cfg, args.run, args.untrained)
    kwargs = {k: v for k, v in cfg["env"].get("kwargs", {}).items() if k in ("obs_mode", "image_size", "camera")}
    env = MetaWorldSubEnv(args.task, terminate_on_success=True, **kwargs)
    max_steps = cfg["env"].get("max_episode_steps") or 200
    rows = []
    for k in range(args.episodes):
        rows.append(run_episode(env, model, EVAL_SEED_BASE + k, max_steps, args.at_step))
        print(json.dumps(rows[-1]), flush=True)
    probe = probe_features(model, env, args.probe) if args.probe else None
    env.close()
    slope_x, slope_y = follow_slopes(rows)
    success_rate = float(np.mean([r["success"] for r in rows]))
    print(json.dumps({"task": args.task, "episodes": len(rows), "success_rate": success_rate,
                      "hand_follows_object_x": round(slope_x, 3), "hand_follows_object_y": round(slope_y, 3),
                      **({"features_probe_r2_xy": [round(v, 3) for v in probe]} if probe else {})}))


if __name__ == "__main__":
    main()
