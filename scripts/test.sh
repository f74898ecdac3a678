#!/usr/bin/env bash
# The default test suite: lint, then every test not marked slow (CPU only; CI gives it 20 minutes
# on 2 cores). Tiers: tests/unit (no Ray), tests/integration (Ray, runners end to end);
# `pytest -m slow` runs the learning runs (tests/learning), `pytest -m gpu` the GPU checks.
# Extra arguments go to pytest.
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if ! "$PY" -m ruff check infinirl tests benchmarks; then
  echo "test.sh: ruff found problems (fix them, or see pyproject.toml's [tool.ruff])" >&2
  exit 1
fi
"$PY" -m pytest -m "not slow" -q "$@"
code=$?
if [ "$code" -eq 5 ]; then
  echo "test.sh: pytest collected no tests: that is a failure, not a pass" >&2
  exit 1
fi
exit "$code"
