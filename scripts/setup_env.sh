#!/usr/bin/env bash
# Set up everything SlipMap needs on Debian 12 or 13 (or any Linux whose packages give QGIS,
# GDAL and PyOpenCL to /usr/bin/python3).
#  1. apt packages of design.md's recipe, only those missing (sudo when not root);
#  2. .venv from /usr/bin/python3 with --system-site-packages (QGIS, GDAL, PyOpenCL from the
#     distribution), editable install; when the system's GDAL or QGIS bindings are there, numpy
#     is pinned to the system's own version (whatever its major version: 1.24 on Debian 12,
#     2.2 on Debian 13), read from the machine at set-up time, since those bindings are built
#     against it;
#  3. .venv-np2: a plain PyPI venv from the default python3 with numpy>=2, for the core/io tests
#     (conda PDAL users run numpy 2).
# A second run does nothing that is already done.
set -euo pipefail
cd "$(dirname "$0")/.."

# qgis (the desktop), xvfb and xauth (xvfb-run needs it): the desktop tests drive the real
# QGIS application's dialogs under a virtual X server (tests/qgis/test_desktop.py); git:
# scripts/plugin_zip.sh lists the plugin's files with it.
APT_PACKAGES=(python3-qgis qgis-providers qgis python3-gdal gdal-bin python3-pyopencl pocl-opencl-icd
  python3-numpy python3-scipy python3-pyproj proj-data python3-matplotlib python3-venv python3-pip
  xvfb xauth git)

what=${1:-all}

apt_missing() {
  local missing=()
  for p in "${APT_PACKAGES[@]}"; do
    if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
      missing+=("$p")
    fi
  done
  echo "${missing[@]:-}"
}

install_apt() {
  command -v dpkg-query >/dev/null || { echo "setup: not a Debian-like system; install QGIS, GDAL, PyOpenCL yourself" >&2; return 0; }
  local missing
  missing=$(apt_missing)
  [ -z "$missing" ] && return 0
  echo "setup: installing apt packages: $missing"
  local sudo=""
  if [ "$(id -u)" != 0 ]; then
    if command -v sudo >/dev/null; then sudo="sudo"; else
      echo "setup: need root to run: apt-get install -y $missing" >&2; exit 1; fi
  fi
  export DEBIAN_FRONTEND=noninteractive
  $sudo apt-get update -q
  # shellcheck disable=SC2086
  $sudo apt-get install -y -q --no-install-recommends $missing
}

stamp_ok() {  # $1 = stamp file; up to date when newer than pyproject.toml, constraints.txt and
  # this script (a new extra or pin here re-runs the install)
  [ -f "$1" ] && [ "$1" -nt pyproject.toml ] && [ "$1" -nt constraints.txt ] && [ "$1" -nt "$0" ]
}

# The pins the system's Python packages impose on .venv, one per line: numpy == the system's
# numpy when the system's GDAL or QGIS bindings (compiled against that numpy) are importable;
# nothing otherwise. Read from the machine, so any distribution release satisfies them.
system_pins() {
  [ -x /usr/bin/python3 ] || return 0
  /usr/bin/python3 - <<'PY'
import importlib.metadata as md
import importlib.util as iu

if any(iu.find_spec(m) is not None for m in ("osgeo", "qgis")):
    try:
        print(f"numpy=={md.version('numpy')}")
    except md.PackageNotFoundError:
        pass
PY
}

install_venv() {
  local pins
  pins=$(system_pins)
  if stamp_ok .venv/.slipmap-installed && [ "$pins" = "$(cat .venv/.slipmap-system-pins 2>/dev/null)" ]; then
    return 0
  fi
  [ -x .venv/bin/python ] || /usr/bin/python3 -m venv --system-site-packages .venv
  # Debian's pyproj looks for its PROJ database under sys.prefix: point the venv at the system one.
  if [ -f /usr/share/proj/proj.db ] && [ ! -e .venv/share/proj ]; then
    mkdir -p .venv/share && ln -s /usr/share/proj .venv/share/proj
  fi
  printf '%s\n' "$pins" >.venv/.slipmap-system-pins
  [ -n "$pins" ] && echo "setup: .venv keeps the system's $(echo "$pins" | paste -sd' ')"
  .venv/bin/python -m pip install -q --upgrade "pip>=23" -c constraints.txt
  .venv/bin/python -m pip install -q --disable-pip-version-check -c constraints.txt \
    -c .venv/.slipmap-system-pins -e '.[dev,dask,fast]'
  touch .venv/.slipmap-installed
}

install_np2() {
  if stamp_ok .venv-np2/.slipmap-installed; then return 0; fi
  # The machine's default python3 (first on PATH), not the Debian one with its numpy 1.24.
  local py
  py=$(PATH=$(echo "$PATH" | tr ':' '\n' | grep -v "/\.venv" | paste -sd:) command -v python3)
  [ -x .venv-np2/bin/python ] || "$py" -m venv .venv-np2
  .venv-np2/bin/python -m pip install -q --upgrade "pip>=23"
  .venv-np2/bin/python -m pip install -q -e '.[test,dask]' "numpy>=2"
  touch .venv-np2/.slipmap-installed
}

case "$what" in
  all) install_apt; install_venv; install_np2 ;;
  main) install_apt; install_venv ;;
  np2) install_np2 ;;
  *) echo "usage: $0 [all|main|np2]" >&2; exit 2 ;;
esac
