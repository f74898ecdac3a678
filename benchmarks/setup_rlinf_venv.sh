#!/usr/bin/env bash
# Create (idempotently) a separate virtualenv holding the original RLinf (PyPI rlinf==0.3.0),
# used by benchmarks/rlinf_channel_child.py as the baseline for benchmarks/runtime_channel.py.
#
#   bash benchmarks/setup_rlinf_venv.sh            # create / complete the venv
#   INFINIRL_RLINF_VENV=/some/dir bash benchmarks/setup_rlinf_venv.sh
#   FORCE=1 bash benchmarks/setup_rlinf_venv.sh    # wipe and recreate
#
# The venv never touches the main Python environment.
#
# Torch is pinned to the CPU build torch==2.13.0+cpu (a local wheel found through pip's find-links,
# /opt/wheels on the dev machines; otherwise PyTorch's CPU index is added). Without the pin pip
# would resolve rlinf's `torch>=2.5.0` to the multi-GB CUDA build from PyPI. The resolution is
# checked with `pip install --dry-run` first and the script aborts if it would pull any CUDA
# torch or nvidia-*-cu* runtime package.
#
# Known-good resolution (2025, Python 3.11): rlinf 0.3.0 + torch 2.13.0+cpu + ray 2.60.0 +
# triton 3.9.0 (via liger_kernel; unused on CPU) + ~150 other packages. rlinf's own pins are loose
# (ray[default]>=2.47.0, torch>=2.5.0), so no different torch/ray version is needed. About 1.9 GB on
# disk, a few minutes to install.
set -euo pipefail

VENV="${INFINIRL_RLINF_VENV:-$HOME/.cache/infinirl/rlinf-venv}"
PY="${INFINIRL_RLINF_BASE_PYTHON:-}"
RLINF_SPEC="rlinf==0.3.0"
TORCH_SPEC="torch==2.13.0+cpu"
STAMP="$VENV/.infinirl-rlinf-ok"

if [[ -z "$PY" ]]; then
    for cand in python3.11 python3 python; do
        if command -v "$cand" >/dev/null 2>&1; then PY="$(command -v "$cand")"; break; fi
    done
fi
[[ -n "$PY" ]] || { echo "setup_rlinf_venv: no python found" >&2; exit 1; }

if [[ "${FORCE:-0}" == "1" && -d "$VENV" ]]; then
    echo "setup_rlinf_venv: FORCE=1, removing $VENV"
    rm -rf "$VENV"
fi

if [[ -f "$STAMP" ]] && "$VENV/bin/python" -c "import rlinf.scheduler, torch, ray" >/dev/null 2>&1; then
    echo "setup_rlinf_venv: $VENV already set up ($(cat "$STAMP"))"
    exit 0
fi

start=$(date +%s)
if [[ ! -x "$VENV/bin/python" ]]; then
    echo "setup_rlinf_venv: creating venv $VENV with $PY ($("$PY" --version 2>&1))"
    mkdir -p "$(dirname "$VENV")"
    "$PY" -m venv "$VENV"
fi
VPIP=("$VENV/bin/python" -m pip)

# Constraint file: the global one (if any, e.g. /etc/xdg/pip/constraints.txt) is still applied by
# pip's own config; this one adds the exact CPU torch pin.
CONS="$VENV/infinirl-constraints.txt"
printf '%s\n' "$TORCH_SPEC" > "$CONS"

# Where does torch 2.13.0+cpu come from? A local wheel via find-links if there is one, else the
# PyTorch CPU index.
EXTRA=()
have_local_torch=0
for d in ${PIP_FIND_LINKS:-} /opt/wheels; do
    if ls "${d#file://}"/torch-2.13.0+cpu-*.whl >/dev/null 2>&1; then have_local_torch=1; fi
done
if [[ "$have_local_torch" == "0" ]]; then
    EXTRA+=(--extra-index-url https://download.pytorch.org/whl/cpu)
fi

# pip on the project machines warns once per package about a configured local index that lacks
# it; drop that noise, keep everything else.
quiet_pip() { "${VPIP[@]}" "$@" 2>&1 | { grep -v "is ignored: it is neither a file nor a directory" || true; }; }

REPORT="$VENV/infinirl-dry-run.json"
echo "setup_rlinf_venv: dry-run resolution of $RLINF_SPEC with $TORCH_SPEC"
quiet_pip install --quiet --dry-run --ignore-installed --report "$REPORT" \
    -c "$CONS" "${EXTRA[@]}" "$RLINF_SPEC" "$TORCH_SPEC"
"$VENV/bin/python" - "$REPORT" <<'EOF'
import json, re, sys
rep = json.load(open(sys.argv[1]))
pkgs = {i["metadata"]["name"].lower(): i["metadata"]["version"] for i in rep["install"]}
bad = [f"{n}=={v}" for n, v in pkgs.items()
       if (n == "torch" and "+cpu" not in v) or re.match(r"nvidia-.*-cu\d+", n)]
print(f"setup_rlinf_venv: resolved {len(pkgs)} packages: torch {pkgs.get('torch')}, "
      f"ray {pkgs.get('ray')}, rlinf {pkgs.get('rlinf')}")
if bad:
    sys.exit(f"setup_rlinf_venv: resolution would pull CUDA packages {bad}; aborting")
EOF

echo "setup_rlinf_venv: installing"
quiet_pip install --quiet -c "$CONS" "${EXTRA[@]}" "$RLINF_SPEC" "$TORCH_SPEC"

"$VENV/bin/python" - <<'EOF'
import importlib.metadata as md
import torch, ray
from rlinf.scheduler import Channel, Cluster, NodePlacementStrategy, Worker  # noqa: F401
assert "+cpu" in torch.__version__, torch.__version__
print(f"setup_rlinf_venv: ok: rlinf {md.version('rlinf')}, torch {torch.__version__}, ray {ray.__version__}")
EOF

end=$(date +%s)
size=$(du -sh "$VENV" 2>/dev/null | cut -f1)
echo "rlinf $("$VENV/bin/python" -c 'import importlib.metadata as m; print(m.version("rlinf"))'), installed $(date -u +%FT%TZ), ${size}, $((end - start))s" > "$STAMP"
echo "setup_rlinf_venv: done in $((end - start))s, venv size $size at $VENV"
