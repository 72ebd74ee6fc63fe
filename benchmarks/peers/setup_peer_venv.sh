#!/usr/bin/env bash
# Create (idempotently) a throw-away venv holding Open3D and OpenPIV, for the peer estimators
# of the benchmarks (benchmarks/peers/open3d_icp.py, open3d_cells.py, openpiv_windef.py).
# Neither is a SlipMap dependency (OpenPIV is GPLv3): the venv lives outside the repository
# and is never imported by the project itself.
#
# Usage: bash benchmarks/peers/setup_peer_venv.sh
#   SLIPMAP_PEER_VENV    where the venv goes (default: ~/.cache/slipmap-peer-venv)
#   SLIPMAP_PEER_PYTHON  the interpreter that creates it (default: python3 on PATH)
# The last line printed is the venv's python.
set -euo pipefail

venv="${SLIPMAP_PEER_VENV:-$HOME/.cache/slipmap-peer-venv}"
base_python="${SLIPMAP_PEER_PYTHON:-python3}"
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"

venv="$(realpath -m "$venv")"
case "$venv/" in
  "$repo"/*) echo "error: the peer venv must not be inside the repository ($venv)" >&2; exit 2 ;;
esac
mkdir -p "$(dirname "$venv")"

py="$venv/bin/python"
if [ ! -x "$py" ]; then
  echo "creating $venv with $(command -v "$base_python")" >&2
  "$base_python" -m venv "$venv"
fi

if ! "$py" -c "import open3d, numpy" >/dev/null 2>&1; then
  "$py" -m pip install --quiet --upgrade pip >&2
  if ! "$py" -m pip install --quiet numpy open3d-cpu >&2; then
    echo "open3d-cpu failed to install; trying open3d" >&2
    "$py" -m pip install --quiet numpy open3d >&2
  fi
fi

# Open3D's Linux wheels link libusb-1.0.so.0 (Azure Kinect support), which minimal systems
# lack. Rather than apt-get (root, outside the venv), take the library from the PyPI package
# libusb-package and link it beside libOpen3D.so, whose RPATH starts with $ORIGIN.
import_error="$("$py" -c "import open3d" 2>&1 || true)"
if [[ "$import_error" == *"libusb-1.0.so.0"* ]]; then
  echo "libusb-1.0.so.0 missing: taking it from the PyPI package libusb-package" >&2
  "$py" -m pip install --quiet libusb-package >&2
  o3d_dir="$("$py" -c "import importlib.util, os; print(os.path.dirname(importlib.util.find_spec('open3d').origin))")"
  usb_lib="$("$py" -c "import importlib.util, os; print(os.path.join(os.path.dirname(importlib.util.find_spec('libusb_package').origin), 'libusb-1.0.so'))")"
  ln -sf "$usb_lib" "$o3d_dir/libusb-1.0.so.0"
fi

# OpenPIV (windef: multi-pass window deformation), the PIV peer of benchmarks/bench_fields.py
if ! "$py" -c "import openpiv.windef" >/dev/null 2>&1; then
  "$py" -m pip install --quiet "openpiv>=0.26" >&2
fi

"$py" -c "import numpy, open3d, openpiv; print('open3d', open3d.__version__, 'openpiv', openpiv.__version__, 'numpy', numpy.__version__)" >&2
echo "$py"
