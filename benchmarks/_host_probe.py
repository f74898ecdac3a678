"""The host facts that decide the embodied benchmark's ratios, measured before its rows run.

Why it exists: the same code gives different ratios on different 2-core VMs (a faster simulator
makes the pipeline's fixed per-message costs a larger share of a step). What moves the ratios is
arithmetic over a few costs, so the result line carries them:

* ``sim_step_ms``: one pipeline stage's step of N/2 and of N MetaWorld ``reach-v3`` envs in one
  process (state observations; N the benchmark's env count, 16 by default, ``--envs`` here), as a
  stage process runs it (``StagedEnv``). Row (b) simulates N envs per step in one process, row (a)
  N/2 per stage in two (the first stage takes an odd env); the cheaper the simulation, the larger
  the share of each step that is fixed per-message cost, which pipelining does not hide and which
  (a) pays once per stage.
* ``link_round_trip_us``: median round trip of an N/2-env stage's message and its actions over the
  socket link the pipelined rows use (``infinirl.components.env_link``), between two processes.
* ``parallel_scaling``: how much work two busy processes get done together, relative to one alone
  (2.0: the VM gives two full cores; shared VMs give less). (a) needs both cores.
"""

from __future__ import annotations

import multiprocessing as mp
import statistics
import time

#: how long each process spins for ``parallel_scaling`` (seconds)
SPIN_S = 1.0


def probe_host(num_envs: int = 16) -> dict:
    """Every fact above for a benchmark of ``num_envs`` envs, in ~10 s; to be run while nothing
    else is busy."""
    from _bench_common import device_description

    stage = (num_envs + 1) // 2  # the pipelined row's (first) stage: its message is what the link carries
    stage_ms, stage_message = sim_step_ms(stage)
    whole_ms, _ = sim_step_ms(num_envs)
    return {"cpu": device_description(), "sim_step_ms": {f"{stage}_envs": stage_ms, f"{num_envs}_envs": whole_ms},
            "link_round_trip_us": link_round_trip_us(stage_message, stage), "parallel_scaling": parallel_scaling()}


def sim_step_ms(num_envs: int, steps: int = 300) -> tuple[float, object]:
    """Milliseconds per step of one pipeline stage of ``num_envs`` MetaWorld reach envs in this
    process (state observations), as a stage process steps them, and the last message it made."""
    import numpy as np

    from infinirl.components.env_worker import EnvSpec, StagedEnv

    env = StagedEnv(EnvSpec(name="metaworld:reach-v3", num_envs=num_envs))
    try:
        env.reset(list(range(num_envs)))
        actions = np.random.default_rng(0).uniform(-1, 1, (steps + 20, num_envs, 4)).astype(np.float32)
        for a in actions[:20]:
            env.step(0, a)
        start = time.perf_counter()
        for a in actions[20:]:
            message = env.step(0, a)
        return round((time.perf_counter() - start) / steps * 1e3, 3), message
    finally:
        env.close()


def _echo_stage(address_out, message, rounds: int) -> None:
    """Child: open the env side of a link, then answer each action message with ``message``."""
    from infinirl.components.env_link import accept, open_server

    server, address = open_server("socket")
    address_out.send(address)
    link = accept(server)
    link.send(message)
    for _ in range(rounds):
        link.recv()
        link.send(message)
    link.recv()
    link.close()


def link_round_trip_us(message, num_envs: int, rounds: int = 2000, warmup: int = 200) -> float:
    """Median microseconds from sending a stage's actions to receiving its next ``message``."""
    import numpy as np

    from infinirl.components.env_link import connect

    context = mp.get_context("spawn")
    parent_end, child_end = context.Pipe()
    child = context.Process(target=_echo_stage, args=(child_end, message, rounds + warmup), daemon=True)
    child.start()
    try:
        link = connect(parent_end.recv())
        link.recv()
        actions = (0, np.zeros((num_envs, 4), np.float32))
        times = []
        for _ in range(rounds + warmup):
            start = time.perf_counter()
            link.send(actions)
            link.recv()
            times.append(time.perf_counter() - start)
        link.send(actions)
        link.close()
    finally:
        child.join(10)
        if child.is_alive():
            child.kill()
    return round(statistics.median(times[warmup:]) * 1e6, 1)


def _spin(start_at: float) -> int:
    """Count loop turns from ``start_at`` (wall clock) for ``SPIN_S`` seconds."""
    while time.time() < start_at:
        time.sleep(0.001)
    turns, end = 0, start_at + SPIN_S
    while time.time() < end:
        turns += 1
    return turns


def parallel_scaling() -> float:
    """Turns two processes spinning at once count together, over the turns of one alone."""
    context = mp.get_context("spawn")
    with context.Pool(2) as pool:
        pool.map(_spin, [0.0, 0.0])  # both workers started and imported
        alone = pool.apply(_spin, (time.time() + 0.2,))
        together = sum(pool.map(_spin, [time.time() + 0.2] * 2))
    return round(together / alone, 2)


if __name__ == "__main__":
    import argparse
    import json
    import os
    import sys

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--envs", type=int, default=16, help="the benchmark's env count N (>= 2)")
    args = parser.parse_args()
    if args.envs < 2:
        parser.error(f"--envs {args.envs}: must be >= 2 (two pipeline stages)")
    here = os.path.dirname(os.path.abspath(__file__))
    sys.path[:0] = [here, os.path.dirname(here)]
    print(json.dumps(probe_host(args.envs)))
