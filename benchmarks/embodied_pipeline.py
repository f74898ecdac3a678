"""Benchmark: env-steps/s of the full PPO loop on MetaWorld, pipelined vs sequential vs single process.

Three ways to run the same PPO iteration, for state observations (MLP 2x64) and for 64x64 RGB
camera observations (CNN): the same registered policy, the same PPO update (10 epochs x 32
mini-batches) and the shipped `ppo_metaworld_reach` demo's shape, read from its config (16 envs x
100 steps of `reach-v3`; `--num-envs/--steps` change it, e.g. 8 x 200):

  (a) pipelined:      `infinirl train ppo_metaworld_reach` with the env and the rollout on disjoint
                      CPU slots (placement env=0 rollout=1 actor=0), `rollout.pipeline_stages=2` and
                      `env.stage_processes=true`: each stage simulates (and renders) in a process of
                      its own that streams straight to the rollout, so the two stages simulate at
                      the same time, on both cores, while the rollout decides for whichever stage
                      is ready.
  (b) sequential:     the same placement, runner and env settings with `rollout.pipeline_stages=1`
                      (one stage process: simulate all envs, then decide, then simulate ...).
  (c) single_process: a cleanRL-style loop in one Python process: gymnasium `AsyncVectorEnv` with
                      one subprocess per env (cleanRL's default for these runs), the same policy,
                      GAE and `ppo_update` called in-process. Same work, no components.
  (extra, opt-in with --impls ...,collocated): the shipped default placement, env inside the
                      rollout process (no hop per step), for comparison.

Every row runs the same update and the same policy inference: by default with `actor.compile=true`
(the whole optimizer step, forward pass, PPO loss, gradient, clipping and Adam, through
torch.compile; the same arithmetic as eager, in fewer, fused kernels) and
`rollout.compile=true` (the policy's `act` compiled, the same random draws as eager; row (c)
compiles its `act` the same way), with `--eager` without either. With RGB the CNN's update uses
every core in every row (`actor.num_threads=0`; row (c) sets torch's threads to the core count for
its update and back to 1 to act): it runs while the simulators wait. The update does not depend
on the placement, so it is the same cost in every row; pipelining only shortens collection.

The rows run side by side, in turns (`benchmarks/_bench_turns.py`): every row's process starts
at once, then the rows take turns, one PPO iteration each, while the others wait frozen (every
process of theirs, Ray included, stopped: no CPU), the order rotating every cycle. So the i-th
iteration of every row runs within seconds of the others' and a slow spell of a shared VM, whose
speed drifts by tens of percent within minutes, lands on all rows alike. Env-steps/s = env steps of
the measured iterations / their wall time (collection + update + weight sync, the runner's own
`time/iteration_s`), skipping each row's first `--warmup` iterations (the one-off compile, JIT of
the first calls); start-up, waiting for a turn and the final evaluation are not counted.

Usage:
    python benchmarks/embodied_pipeline.py                      # state and rgb, all impls (minutes)
    python benchmarks/embodied_pipeline.py --obs state --iterations 4
    python benchmarks/embodied_pipeline.py --only single_process --obs rgb   # one impl alone, its JSON line
    python benchmarks/embodied_pipeline.py --eager              # every row's update and act uncompiled
    python benchmarks/embodied_pipeline.py --obs state --iterations 4 --rounds 3   # three blocks of 4
    python benchmarks/embodied_pipeline.py --num-envs 8 --steps 200   # another iteration shape
    python benchmarks/embodied_pipeline.py --record docs/results.md   # also append the result as an entry

The table goes to stderr; the last stdout line is ONE JSON object:
    {"benchmark": "embodied_pipeline", "ratios": {"pipelined_vs_sequential": ..,
     "pipelined_vs_single_process": .., "<obs>/...": ..}, "targets": {...}, "results": {...}}
The unprefixed ratios are those of state observations (the issue's headline); rgb ratios carry
the "rgb/" prefix. Ratios > 1 mean the pipelined path is faster. "ratios" are over all measured
iterations; "paired_ratios" holds each round's own ratio (`--rounds N`: N consecutive blocks of
`--iterations` measured iterations per row) with their median, and the spread of the per-cycle
ratios (the i-th iterations of two rows, seconds apart). "host" holds what the ratios depend on,
measured before the rows start (`benchmarks/_host_probe.py`, ~10 s; `--no-probe` skips it): the
CPU, a MetaWorld step of one pipelined stage's envs and of all of them, the link's round trip, and
how two busy processes scale.
Read ratios from different machines side by side with it (docs/results.md).
A row that fails leaves its ratios null, its entry holding "failed" (the conductor stops the other
rows of that observation mode: theirs say so), is listed in "failures", and the script exits 1.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time

TARGETS = {"pipelined_vs_sequential": 1.3, "pipelined_vs_single_process": 1.0}
IMPLS = ("pipelined", "sequential", "single_process", "collocated")
DEFAULT_IMPLS = IMPLS[:3]
DEMO = "ppo_metaworld_reach"
#: envs and decisions per iteration; main() sets them (default: the demo config's own)
NUM_ENVS, STEPS = 16, 100
BENCH_DIR = os.path.dirname(os.path.abspath(__file__))
REPO_ROOT = os.path.dirname(BENCH_DIR)


def _child_env() -> dict:
    """The environment of a row's subprocess: this checkout first on the path, so the benchmark
    measures the code beside it whether or not (or wherever) infinirl is installed."""
    path = os.environ.get("PYTHONPATH")
    return {**os.environ, "PYTHONPATH": REPO_ROOT + (os.pathsep + path if path else "")}


if REPO_ROOT not in sys.path:  # row (c) runs in this process (``--only single_process``)
    sys.path.insert(0, REPO_ROOT)
if BENCH_DIR not in sys.path:
    sys.path.insert(0, BENCH_DIR)

from _bench_common import add_record_argument, conclude, concluded, failures_of, side_failed  # noqa: E402
from _bench_turns import Conductor, RowFailed, Turn  # noqa: E402

#: per observation mode: config overrides of `ppo_metaworld_reach` shared by every implementation
OBS_MODES = {
    "state": {},
    # the CNN's update takes every core (actor.num_threads=0, as ppo_pixels_metaworld_reach does;
    # row (c) likewise): it runs while the simulators wait, and convolutions parallelise
    "rgb": {"env.kwargs": {"obs_mode": "state+rgb", "image_size": 64}, "policy.name": "cnn_gaussian",
            "policy.kwargs": {}, "actor.num_threads": 0},
}
#: how (a) and (b) run the envs: each pipeline stage in a process of its own streaming straight to
#: the rollout (stages simulate in parallel, one message hop per step), its sub-envs in that process
STAGING = {"env.stage_processes": True, "env.num_workers": 0}
PLACEMENT = {"placement.env": "0", "placement.rollout": "1", "placement.actor": "0"}
IMPL_OVERRIDES = {"pipelined": {"rollout.pipeline_stages": 2}, "sequential": {"rollout.pipeline_stages": 1},
                  # opt-in row: the default placement of ppo_metaworld_reach (env inside the rollout process)
                  "collocated": {"placement.env": "0", "placement.rollout": "0", "env.stage_processes": False,
                                 "rollout.pipeline_stages": 1}}


def _hydra_value(value) -> str:
    """A value in Hydra's override grammar ({k:v}, [a,b], quoted strings with symbols)."""
    if isinstance(value, dict):
        return "{" + ",".join(f"{k}:{_hydra_value(v)}" for k, v in value.items()) + "}"
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(_hydra_value(v) for v in value) + "]"
    if isinstance(value, str):
        bare = value.replace("_", "").replace("-", "").replace("/", "").replace(".", "")
        if not bare.isalnum():
            return "'" + value + "'"
    return str(value)


def _override_args(overrides: dict) -> list[str]:
    return [f"{key}={_hydra_value(value)}" for key, value in overrides.items()]


def runner_overrides(impl: str, obs: str, iterations: int, compile_: bool, out: str) -> dict:
    """(a)/(b): the `infinirl train ppo_metaworld_reach` overrides of a row."""
    return {"iterations": iterations, "env.num_envs": NUM_ENVS, "rollout_steps": STEPS, "output_dir": out,
            "resume": False, "eval.every": 0, "eval.at_start": False, "eval.episodes": 1,
            "eval.num_envs": 1, "eval.video_episodes": 0, "loggers": [], "actor.compile": compile_,
            "rollout.compile": compile_,
            **PLACEMENT, **STAGING, **OBS_MODES[obs], **IMPL_OVERRIDES[impl]}


def row_command(impl: str, obs: str, iterations: int, warmup: int, compile_: bool, out: str) -> list[str]:
    """A row's process. (a)/(b): the real runner through the CLI, each PPO iteration in a turn when
    a conductor started it (`_bench_turns.gate_embodied_runner`); its metrics go to ``out``.
    (c): this script with ``--only single_process``, printing its result as JSON."""
    if impl == "single_process":
        return [sys.executable, os.path.abspath(__file__), "--only", impl, "--obs", obs, "--iterations",
                str(iterations), "--warmup", str(warmup), "--num-envs", str(NUM_ENVS),
                "--steps", str(STEPS)] + ["--eager"] * (not compile_)
    bootstrap = (f"import sys; sys.path[:0] = [{REPO_ROOT!r}, {BENCH_DIR!r}]; import _bench_turns; "
                 "_bench_turns.gate_embodied_runner(); from infinirl.cli import main; sys.exit(main())")
    return [sys.executable, "-c", bootstrap, "train", DEMO,
            *_override_args(runner_overrides(impl, obs, iterations, compile_, out))]


def runner_rows(out: str) -> list[dict]:
    """The per-iteration metrics a runner row wrote."""
    return [json.loads(line) for line in open(os.path.join(out, "metrics.jsonl")) if "time/iteration_s" in line]


def run_runner(impl: str, obs: str, iterations: int, warmup: int, compile_: bool) -> dict:
    """(a)/(b) on their own (``--only``): steps/s from the runner's metrics.jsonl."""
    with tempfile.TemporaryDirectory(prefix=f"bench-{impl}-") as out:
        cmd = row_command(impl, obs, iterations, warmup, compile_, out)
        proc = subprocess.run(cmd, capture_output=True, text=True, env=_child_env())
        if proc.returncode:
            raise RuntimeError(f"{impl}/{obs} failed ({' '.join(cmd)}):\n{proc.stderr[-4000:]}")
        rows = runner_rows(out)
    return summarise(rows[warmup:], impl)


def summarise(rows: list[dict], impl: str) -> dict:
    steps = NUM_ENVS * STEPS * len(rows)
    wall = sum(r["time/iteration_s"] for r in rows)
    mean = lambda key: sum(r.get(key, 0.0) for r in rows) / len(rows)  # noqa: E731
    return {"impl": impl, "iterations": len(rows), "env_steps": steps, "wall_s": round(wall, 3),
            "env_steps_per_s": round(steps / wall, 1), "collect_s": round(mean("time/collect_s"), 3),
            "train_s": round(mean("time/train_s"), 3),
            "iteration_s": [round(r["time/iteration_s"], 4) for r in rows]}


# --------------------------------------------------------------------------- (c) single process
def run_single_process(obs: str, iterations: int, warmup: int, compile_: bool) -> dict:
    """(c): cleanRL's shape: one process, AsyncVectorEnv, act -> step -> ... -> GAE -> update."""
    import gymnasium as gym
    import numpy as np
    import torch

    from infinirl.components.embodied_actor import PPOSpec
    from infinirl.components.embodied_rollout import PolicySpec, compiled_act
    from infinirl.components.env_worker import probe_env_specs
    from infinirl.config import compose

    torch.set_num_threads(1)
    raw = compose(DEMO)
    options = OBS_MODES[obs]
    env_kwargs = dict(options.get("env.kwargs", raw["env"].get("kwargs") or {}))
    task = raw["env"]["name"].partition(":")[2]
    alg = raw["algorithm"]
    spec, action_space = probe_env_specs(raw["env"]["name"], env_kwargs)
    keys = [k for k, v in spec.items() if v.dtype != "str"]
    policy_spec = PolicySpec(name=options.get("policy.name", raw["policy"]["name"]),
                             options=dict(options.get("policy.kwargs", raw["policy"]["kwargs"])))
    torch.manual_seed(0)
    model = policy_spec.build(spec, action_space)
    ppo = PPOSpec(lr=raw["actor"]["lr"], anneal_lr=True, total_iterations=iterations, epochs=alg["epochs"],
                  mini_batches=alg["mini_batches"], clip=alg["clip"], entropy_coef=alg["entropy_coef"],
                  max_grad_norm=alg["max_grad_norm"], strategy="ddp", compile=compile_)
    optimizer = torch.optim.Adam(model.parameters(), lr=ppo.lr, eps=ppo.adam_eps, fused=True)
    act = compiled_act(model) if compile_ else model.act  # what rollout.compile does in (a)/(b)
    # the update's threads, as actor.num_threads gives them in (a)/(b) (0: every core); acting keeps 1
    update_threads = options.get("actor.num_threads", 1) or len(os.sched_getaffinity(0))
    # NEXT_STEP (gymnasium's default): an env whose episode ended resets on its next step() call.
    # No episode ends before an iteration's last step (200-step episodes, no early termination,
    # at most 200 steps an iteration: checked below), and the next iteration starts with a seeded
    # reset(), so, like (a) and (b), this loop resets each env once per iteration and never for
    # an observation it does not use.
    envs = gym.vector.AsyncVectorEnv([_gym_env_fn(task, env_kwargs, keys)] * NUM_ENVS,
                                     autoreset_mode=gym.vector.AutoresetMode.NEXT_STEP)
    rows = []
    turn = Turn.from_env()  # a conductor runs this row side by side with the others, in turns
    try:
        for iteration in range(iterations):
            with turn or contextlib.nullcontext():
                rows.append(_single_process_iteration(envs, act, model, optimizer, iteration, ppo, alg, np,
                                                      update_threads))
        if turn is not None:
            turn.take()  # the last turn: closing the envs
    finally:
        envs.close()
    # every iteration's timings too: a conductor that ran this row in turns splits them into rounds
    return {**summarise(rows[warmup:], "single_process"), "rows": rows}


def _single_process_iteration(envs, act, model, optimizer, iteration: int, ppo, alg: dict, np,
                              update_threads: int = 1) -> dict:
    """One cleanRL-style PPO iteration: seeded reset, STEPS decisions, GAE, the update."""
    import torch

    from infinirl.components.embodied_actor import ppo_update
    from infinirl.components.embodied_rollout import array_obs
    from infinirl.components.env_worker import iteration_seeds
    from infinirl.models.policies.base import prepare_obs

    t0 = time.perf_counter()
    ob, _ = envs.reset(seed=iteration_seeds(0, iteration, NUM_ENVS))
    record = {"obs": [], "actions": [], "logprobs": [], "values": [], "rewards": [], "dones": []}
    with torch.no_grad():
        for _ in range(STEPS):
            step = act(prepare_obs(ob))
            record["obs"].append(array_obs(ob))
            for key in ("actions", "logprobs", "values"):
                record[key].append(getattr(step, key))
            ob, reward, terminated, truncated, _ = envs.step(step.actions[:, 0].numpy())
            record["rewards"].append(torch.as_tensor(reward, dtype=torch.float32))
            record["dones"].append(torch.as_tensor(terminated | truncated))
        last_value = model.value(prepare_obs(ob))
    if any(bool(done.any()) for done in record["dones"][:-1]):
        raise RuntimeError("an episode ended before the iteration's last step: this loop's "
                           "NEXT_STEP auto-reset would then need cleanRL's reset-step handling")
    t1 = time.perf_counter()
    batch = _gae_batch(record, last_value, alg["gamma"], alg["gae_lambda"], np)
    torch.set_num_threads(update_threads)
    try:
        ppo_update(model, optimizer, batch, iteration, ppo)
    finally:
        torch.set_num_threads(1)
    model.update_obs_stats({k: batch["obs"][k] for k in model.keys})
    t2 = time.perf_counter()
    return {"time/iteration_s": t2 - t0, "time/collect_s": t1 - t0, "time/train_s": t2 - t1}


def _gae_batch(record: dict, last_value, gamma: float, lam: float, np) -> dict:
    """GAE the slow obvious way (cleanRL's loop); the flat batch `ppo_update` takes."""
    import torch

    values = torch.stack(record["values"])
    rewards, dones = torch.stack(record["rewards"]), torch.stack(record["dones"]).float()
    advantages = torch.zeros_like(rewards)
    running = torch.zeros_like(rewards[0])
    for t in reversed(range(rewards.shape[0])):
        next_value = last_value if t == rewards.shape[0] - 1 else values[t + 1]
        delta = rewards[t] + gamma * next_value * (1 - dones[t]) - values[t]
        running = delta + gamma * lam * (1 - dones[t]) * running
        advantages[t] = running
    flat = lambda x: x.reshape(-1, *x.shape[2:])  # noqa: E731
    obs = {k: flat(torch.as_tensor(np.stack([o[k] for o in record["obs"]]))) for k in record["obs"][0]}
    actions = flat(torch.stack(record["actions"]))
    return {"obs": obs, "actions": actions, "logprobs": flat(torch.stack(record["logprobs"])),
            "step_mask": torch.ones(actions.shape[:2], dtype=torch.bool), "values": flat(values),
            "advantages": flat(advantages), "returns": flat(advantages + values)}


class _GymMetaWorld:
    """Picklable factory of a gymnasium.Env around our MetaWorld sub-env (same physics/render settings)."""

    def __init__(self, task: str, kwargs: dict, keys: list[str]):
        self.task, self.kwargs, self.keys = task, kwargs, keys

    def __call__(self):
        import gymnasium as gym
        import numpy as np

        from infinirl.envs.metaworld_env import MetaWorldSubEnv

        task, kwargs, keys = self.task, self.kwargs, self.keys

        class Env(gym.Env):
            def __init__(self):
                self.sub = MetaWorldSubEnv(task, **kwargs)
                spec = self.sub.observation_spec
                self.observation_space = gym.spaces.Dict({
                    k: gym.spaces.Box(0, 255, spec[k].shape, np.uint8) if spec[k].dtype == "uint8"
                    else gym.spaces.Box(-np.inf, np.inf, spec[k].shape, np.float32) for k in keys})
                space = self.sub.action_space
                self.action_space = gym.spaces.Box(space.low, space.high, dtype=np.float32)

            def reset(self, *, seed=None, options=None):
                return self._obs(self.sub.reset(seed=seed)), {}

            def step(self, action):
                out = self.sub.step(action)
                return self._obs(out.obs), float(out.reward), bool(out.terminated), bool(out.truncated), {}

            def _obs(self, obs):
                return {k: obs[k] for k in keys}

        return Env()


def _gym_env_fn(task: str, kwargs: dict, keys: list[str]):
    return _GymMetaWorld(task, kwargs, keys)


# --------------------------------------------------------------------------- driver
def run_one(impl: str, obs: str, iterations: int, warmup: int, compile_: bool) -> dict:
    if impl == "single_process":
        return run_single_process(obs, iterations, warmup, compile_)
    return run_runner(impl, obs, iterations, warmup, compile_)


def run_in_turns(obs: str, impls: list[str], measured: int, rounds: int, warmup: int, compile_: bool) -> dict:
    """Every row at once, in turns (`_bench_turns.Conductor`): ``warmup + rounds * measured``
    iterations each. Returns each row's per-iteration metrics, the warm-up iterations dropped."""
    total = warmup + rounds * measured
    with tempfile.TemporaryDirectory(prefix="bench-embodied-") as tmp:
        outs = {impl: os.path.join(tmp, impl) for impl in impls}
        commands = {impl: row_command(impl, obs, total, warmup, compile_, outs[impl]) for impl in impls}

        def progress(cycle: int) -> None:
            if (cycle + 1) % max(1, total // 4) == 0 or cycle + 1 == total:
                print(f"{obs:5s} cycle {cycle + 1}/{total} ({', '.join(impls)} one iteration each, in turns)",
                      file=sys.stderr)

        outputs = Conductor(commands, env=_child_env()).run(total, on_cycle=progress)
        rows = {impl: (json.loads(outputs[impl].strip().splitlines()[-1])["rows"] if impl == "single_process"
                       else runner_rows(outs[impl])) for impl in impls}
    return {impl: r[warmup:] for impl, r in rows.items()}


def probe_host() -> dict:
    """The host facts of `_host_probe.py`, measured in a process of their own (the conductor stays
    free of the simulator), printed to stderr and returned for the JSON line."""
    proc = subprocess.run([sys.executable, os.path.join(BENCH_DIR, "_host_probe.py"), "--envs", str(NUM_ENVS)],
                          capture_output=True, text=True, env=_child_env())
    if proc.returncode:
        raise RuntimeError(f"measuring the host failed (use --no-probe to skip it):\n{proc.stderr[-4000:]}")
    host = json.loads(proc.stdout.strip().splitlines()[-1])
    steps = ", ".join(f"{ms} ms ({key.replace('_', ' ')})" for key, ms in host["sim_step_ms"].items())
    print(f"host  {host['cpu']}: MetaWorld step {steps}; link round trip {host['link_round_trip_us']} us; "
          f"two busy processes {host['parallel_scaling']}x one", file=sys.stderr)
    return host


def demo_shape(num_envs: int | None = None, steps: int | None = None) -> tuple[int, int]:
    """(envs, decisions per env) of an iteration: the given ones, else the demo config's. Why the
    demo's: the benchmark measures the PPO loop users run, so it follows the demo's config."""
    if num_envs is not None and steps is not None:
        return num_envs, steps
    from infinirl.config import compose

    raw = compose(DEMO)
    return (num_envs if num_envs is not None else int(raw["env"]["num_envs"]),
            steps if steps is not None else int(raw["rollout_steps"]))


def shape_problem(num_envs: int, steps: int) -> str | None:
    """What is wrong with an iteration shape, checked before any row starts (a row would otherwise
    fail seconds later, inside the conductor's report); None when every row can run it."""
    if num_envs < 2:
        return f"--num-envs {num_envs}: the pipelined row splits the envs into 2 stages, so it needs >= 2"
    if not 1 <= steps <= 200:
        return (f"--steps {steps}: must be in [1, 200] (MetaWorld's episodes are 200 steps; row (c) "
                "handles no episode ending inside an iteration)")
    from infinirl.config import compose

    mini_batches = int(compose(DEMO)["algorithm"]["mini_batches"])
    if (num_envs * steps) % mini_batches:
        return (f"--num-envs {num_envs} x --steps {steps} = {num_envs * steps} decisions an iteration, which "
                f"{DEMO}'s algorithm.mini_batches={mini_batches} does not divide: pick a shape it divides")
    return None


def _median(values: list[float]) -> float:
    ordered = sorted(values)
    return ordered[(len(ordered) - 1) // 2]


def _pair(rows_a: list[dict], rows_b: list[dict], measured: int, rounds: int) -> dict:
    """(a)/(b) speed ratios of two rows that ran in turns: per round (a block of ``measured``
    consecutive iterations of each) and per cycle (the i-th iteration of each, seconds apart)."""
    time = lambda rows: sum(r["time/iteration_s"] for r in rows)  # noqa: E731
    per_round = [round(time(rows_b[k * measured:(k + 1) * measured]) / time(rows_a[k * measured:(k + 1) * measured]), 3)
                 for k in range(rounds)]
    per_cycle = [b["time/iteration_s"] / a["time/iteration_s"] for a, b in zip(rows_a, rows_b)]
    return {"rounds": per_round, "median": _median(per_round),
            "cycles": {"median": round(_median(per_cycle), 3), "min": round(min(per_cycle), 3),
                       "max": round(max(per_cycle), 3), "n": len(per_cycle)}}


def _parse_args() -> argparse.Namespace:
    """The command line, checked: every --obs and --impls name known, --rounds >= 1, a runnable shape
    (--num-envs and --steps resolved to the demo's where not given)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--obs", default="state,rgb", help="comma list of: " + ", ".join(OBS_MODES))
    parser.add_argument("--impls", default=",".join(DEFAULT_IMPLS),
                        help="comma list of: " + ", ".join(IMPLS) + " (collocated is an opt-in extra row)")
    parser.add_argument("--iterations", type=int, default=5,
                        help="measured PPO iterations per row and round (state; rgb measures 2 fewer, at least 2)")
    parser.add_argument("--warmup", type=int, default=1, help="first iterations of each row, not measured")
    parser.add_argument("--only", choices=IMPLS, help="run one impl in this process and print its result")
    parser.add_argument("--rounds", type=int, default=1,
                        help="measure each row in this many consecutive blocks of --iterations; each block "
                             "gives the rows' ratios once (all rows run side by side, in turns)")
    parser.add_argument("--num-envs", type=int, default=None,
                        help=f"envs per iteration in every row (default: {DEMO}'s env.num_envs)")
    parser.add_argument("--steps", type=int, default=None,
                        help=f"decisions per env and iteration (default: {DEMO}'s rollout_steps)")
    parser.add_argument("--no-probe", action="store_true",
                        help="skip measuring the host first (the JSON line's \"host\" is then null)")
    parser.add_argument("--eager", action="store_true",
                        help="every row without actor.compile and rollout.compile (default: every row compiles "
                             "its PPO optimizer step and its policy's act)")
    add_record_argument(parser)
    args = parser.parse_args()
    args.modes = [m.strip() for m in args.obs.split(",") if m.strip()]
    args.impl_names = [i.strip() for i in args.impls.split(",") if i.strip()]
    if args.rounds < 1:
        parser.error(f"--rounds {args.rounds}: must be >= 1")
    for name in args.modes:
        if name not in OBS_MODES:
            parser.error(f"--obs {name!r}: choose from {', '.join(OBS_MODES)}")
    for name in args.impl_names:
        if name not in IMPLS:
            parser.error(f"--impls {name!r}: choose from {', '.join(IMPLS)}")
    args.num_envs, args.steps = demo_shape(args.num_envs, args.steps)
    problem = shape_problem(args.num_envs, args.steps)
    if problem:
        parser.error(problem)
    return args


def _measure_obs(obs: str, args: argparse.Namespace, results: dict, ratios: dict, paired: dict) -> None:
    """Run every row of one observation mode in turns; add its results, speed ratios and paired ratios."""
    measured = args.iterations if obs == "state" else max(2, args.iterations - 2)
    prefix = "" if obs == "state" else f"{obs}/"
    pairs = [("pipelined_vs_sequential", "pipelined", "sequential"),
             ("pipelined_vs_single_process", "pipelined", "single_process"),
             ("collocated_vs_single_process", "collocated", "single_process")]
    try:
        rows = run_in_turns(obs, args.impl_names, measured, args.rounds, args.warmup, not args.eager)
    except RowFailed as error:  # the conductor stopped every row: the failing one named, the others stopped
        for impl in args.impl_names:
            results[f"{obs}/{impl}"] = side_failed(str(error) if impl == error.row
                                                   else f"stopped: the {error.row} row failed")
        ratios.update({prefix + key: None for key, a, b in pairs if {a, b} <= set(args.impl_names)})
        return
    for impl, impl_rows in rows.items():
        per_round = [summarise(impl_rows[k * measured:(k + 1) * measured], impl) for k in range(args.rounds)]
        for k, result in enumerate(per_round):
            print(f"{obs:5s} {impl:15s} {result['env_steps_per_s']:8.1f} env-steps/s  collect "
                  f"{result['collect_s']:.2f}s  train {result['train_s']:.2f}s  per iteration "
                  f"({result['iterations']} measured, round {k + 1}/{args.rounds})", file=sys.stderr)
        results[f"{obs}/{impl}"] = {**summarise(impl_rows, impl),
                                    "rounds_env_steps_per_s": [r["env_steps_per_s"] for r in per_round]}
    speed = lambda impl: results.get(f"{obs}/{impl}", {}).get("env_steps_per_s")  # noqa: E731
    for key, a, b in pairs:
        if a in rows and b in rows:
            ratios[prefix + key] = round(speed(a) / speed(b), 3)
            paired[prefix + key] = _pair(rows[a], rows[b], measured, args.rounds)


def _print_ratios(ratios: dict, paired: dict) -> None:
    """One stderr line per pair: its per-round and per-cycle ratios, and the verdict where it has a target."""
    for key, value in paired.items():
        target = TARGETS.get(key.rpartition("/")[2])
        verdict = ""
        if target is not None:
            verdict = f"; target {target}: {'met' if ratios[key] >= target else 'MISSED'} ({ratios[key]})"
        print(f"{key}: rounds {value['rounds']} (median {value['median']}); cycles median "
              f"{value['cycles']['median']} [{value['cycles']['min']}, {value['cycles']['max']}]{verdict}",
              file=sys.stderr)


def main() -> int:
    args = _parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl" if os.environ.get("INFINIRL_BENCH_EGL") else "osmesa")
    global NUM_ENVS, STEPS
    NUM_ENVS, STEPS = args.num_envs, args.steps
    if args.only:
        print(json.dumps(run_one(args.only, args.modes[0], args.iterations, args.warmup, not args.eager)))
        return 0
    started = time.time()
    print(f"each PPO iteration: {NUM_ENVS} envs x {STEPS} steps of {DEMO}", file=sys.stderr)
    host = None if args.no_probe else probe_host()
    results, ratios, paired = {}, {}, {}
    for obs in args.modes:
        _measure_obs(obs, args, results, ratios, paired)
    _print_ratios(ratios, paired)
    final = {"benchmark": "embodied_pipeline", "ratios": ratios, "paired_ratios": paired, "targets": TARGETS,
             "results": results, "interleaved": True, "num_envs": NUM_ENVS, "steps": STEPS,
             "actor_compile": not args.eager, "rollout_compile": not args.eager,
             "device": host["cpu"] if host else f"{os.cpu_count()} CPUs", "host": host,
             "elapsed_s": round(time.time() - started, 1)}
    return conclude(final, failures_of(results), record=(args.record, "Embodied pipeline benchmark"))


if __name__ == "__main__":
    sys.exit(concluded("embodied_pipeline", main))
