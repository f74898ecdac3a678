"""Settings shared by every module that talks to Ray: our namespace and the environment every
worker process starts with. A leaf module (imports nothing of ours), so that ``cluster``,
``worker``, ``memory`` and ``channel`` can all use it without importing each other."""

from __future__ import annotations

import os

NAMESPACE = "infinirl"
# Ray would otherwise blank CUDA_VISIBLE_DEVICES for tasks/actors that reserve no Ray GPU; we place
# devices ourselves (collocated components share a GPU), so we keep control of that variable.
KEEP_CUDA_VISIBLE_DEVICES = {"RAY_EXPERIMENTAL_NOSET_CUDA_VISIBLE_DEVICES": "1"}
# Every worker process starts with these (unless the driver's environment says otherwise).
# OpenMP's default spin-waiting keeps every idle torch thread busy on a core, so co-located torch
# processes take the cores from each other; passive waiting gives the cores back. Progress bars of
# worker processes (a model's "Loading weights") reach the driver's terminal whenever Ray forwards
# them, over the driver's own progress bar and after its summary line: the driver shows progress.
WORKER_ENV_DEFAULTS = {"OMP_WAIT_POLICY": "PASSIVE", "HF_HUB_DISABLE_PROGRESS_BARS": "1"}


def worker_env() -> dict[str, str]:
    """The environment variables a worker process starts with (Ray's ``runtime_env``)."""
    env = dict(KEEP_CUDA_VISIBLE_DEVICES)
    for key, value in WORKER_ENV_DEFAULTS.items():
        env[key] = os.environ.get(key, value)
    return env
