"""Make ``tests.unit.envs.toy_envs`` importable here and in spawned env-worker processes."""

import sys
from pathlib import Path

_REPO_ROOT = str(Path(__file__).resolve().parents[3])
if _REPO_ROOT not in sys.path:
    sys.path.insert(0, _REPO_ROOT)
