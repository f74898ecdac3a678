#!/usr/bin/env bash
# The default test suite (CPU only; CI gives it 20 minutes on 2 cores). `pytest -m slow` runs the learning runs;
# `pytest -m gpu` the GPU checks (skipped without CUDA). Extra arguments go to pytest.
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
"$PY" -m pytest -m "not slow" -q "$@"
code=$?
if [ "$code" -eq 5 ]; then
  echo "test.sh: pytest collected no tests: that is a failure, not a pass" >&2
  exit 1
fi
exit "$code"
