#!/usr/bin/env bash
# `make test-debian13`: the README's two commands in a Debian 13 (trixie) root, as a new user
# would run them there (QGIS 3.40, numpy 2, GDAL 3.10, Python 3.13).
#
#  1. once: debootstrap a minimal trixie root into a cache folder outside the repository
#     (SLIPMAP_DEBIAN13_CACHE, default ~/.cache/slipmap-debian13; the .deb files stay in
#     its debs/ folder), from the Debian mirror the host's apt uses (read from the host's apt
#     configuration, or SLIPMAP_DEBIAN_MIRROR);
#  2. every run: the host's CA certificates, apt settings (apt.conf.d, auth.conf.d), DNS and pip
#     settings (pip.conf files, the local folders they name, PIP_*/proxy variables) are made
#     visible inside, so apt and pip reach the registries as they do on the host; the working
#     tree (what git tracks or would track, and .git) is copied to /srv/slipmap in the root,
#     keeping the venvs made there by an earlier run;
#  3. inside: `make demo`, then `make test` (or the command given).
# /proc, /sys and /dev are mounted in a private mount namespace (unshare), so they vanish with
# the process however it ends; a trap unmounts them too on exit, Ctrl-C or TERM.
#
# Usage: bash scripts/debian13.sh [test|shell|run CMD...|clean]
#   test   (default) make demo && make test inside the root
#   shell  an interactive shell in the root's copy of the tree
#   run    run CMD (a shell command line) in the root's copy of the tree
#   clean  delete the root (the .deb cache stays)
# Needs root (re-runs itself with sudo otherwise). SLIPMAP_DEBIAN13_NO_SYS=1 leaves /sys out
# (to check that the suite survives a root without it).
set -euo pipefail

REPO=$(cd "$(dirname "$0")/.." && pwd)
SUITE=trixie
CACHE=${SLIPMAP_DEBIAN13_CACHE:-${SUDO_USER:+$(getent passwd "$SUDO_USER" | cut -d: -f6)/.cache/slipmap-debian13}}
CACHE=${CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/slipmap-debian13}
ROOT=$CACHE/root
DEST=/srv/slipmap
what=${1:-test}
[ $# -gt 0 ] && shift

if [ "$(id -u)" != 0 ]; then
  command -v sudo >/dev/null || { echo "debian13: needs root (debootstrap, chroot, mount)" >&2; exit 1; }
  exec sudo --preserve-env=SLIPMAP_DEBIAN13_CACHE,SLIPMAP_DEBIAN_MIRROR,SLIPMAP_DEBIAN13_NO_SYS \
    SLIPMAP_DEBIAN13_CACHE="$CACHE" bash "$0" "$what" "$@"
fi

case "$REPO" in "$CACHE"/* | "$CACHE") echo "debian13: the cache must lie outside the repository" >&2; exit 2 ;; esac
case "$CACHE" in "$REPO"/*) echo "debian13: the cache must lie outside the repository" >&2; exit 2 ;; esac

if [ "$what" = clean ]; then
  rm -rf "$ROOT" "$ROOT.partial"
  echo "debian13: removed $ROOT (the .deb cache in $CACHE/debs stays)"
  exit 0
fi

# A private mount namespace: every mount below disappears with this process, even on SIGKILL.
if [ -z "${SLIPMAP_DEBIAN13_NS:-}" ] && command -v unshare >/dev/null; then
  exec unshare --mount --propagation private env SLIPMAP_DEBIAN13_NS=1 bash "$0" "$what" "$@"
fi

# --------------------------------------------------------------------------- host settings
# The Debian mirror and security mirror the host's apt uses (no host is written in here).
apt_uri() {  # $1 = awk test on the suite codename
  command -v apt-get >/dev/null || return 0
  apt-get indextargets --format '$(ORIGIN)|$(CODENAME)|$(REPO_URI)' 2>/dev/null |
    awk -F'|' -v want="$1" '$1 == "Debian" && (want == "security") == ($2 ~ /-security$/) {print $3; exit}'
}
MIRROR=${SLIPMAP_DEBIAN_MIRROR:-$(apt_uri main)}
SECURITY=${SLIPMAP_DEBIAN_SECURITY_MIRROR:-$(apt_uri security)}
if [ -z "$MIRROR" ]; then
  echo "debian13: no Debian mirror in the host's apt configuration; set SLIPMAP_DEBIAN_MIRROR" >&2
  exit 2
fi

MOUNTS=()  # mount points inside the root, in mount order
CHILD=""   # the process group running inside the root
cleanup() {
  local i
  if [ -n "$CHILD" ]; then  # stop what runs inside first: it holds the mounts
    kill -TERM -- "-$CHILD" 2>/dev/null || true
    sleep 1
    kill -KILL -- "-$CHILD" 2>/dev/null || true
    CHILD=""
  fi
  for ((i = ${#MOUNTS[@]} - 1; i >= 0; i--)); do
    umount -R "${MOUNTS[$i]}" 2>/dev/null || umount -lR "${MOUNTS[$i]}" 2>/dev/null || true
  done
  MOUNTS=()
}
trap cleanup EXIT
trap 'cleanup; exit 130' INT
trap 'cleanup; exit 143' TERM HUP

# ------------------------------------------------------------------------------ the root
if [ ! -f "$ROOT/.slipmap-debootstrap" ]; then
  command -v debootstrap >/dev/null || {
    echo "debian13: installing debootstrap on the host"
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q debootstrap
  }
  mkdir -p "$CACHE/debs"
  rm -rf "$ROOT.partial"
  echo "debian13: debootstrap $SUITE from $MIRROR into $ROOT (once)"
  debootstrap --variant=minbase --include=ca-certificates,make \
    --cache-dir="$CACHE/debs" "$SUITE" "$ROOT.partial" "$MIRROR"
  touch "$ROOT.partial/.slipmap-debootstrap"
  mv "$ROOT.partial" "$ROOT"
fi

# apt: the host's mirror for trixie, the host's apt settings that the root's packages do not own
{
  echo "Types: deb"
  echo "URIs: $MIRROR"
  echo "Suites: $SUITE $SUITE-updates"
  echo "Components: main"
  echo "Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg"
  if [ -n "$SECURITY" ]; then
    echo
    echo "Types: deb"
    echo "URIs: $SECURITY"
    echo "Suites: $SUITE-security"
    echo "Components: main"
    echo "Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg"
  fi
} >"$ROOT/etc/apt/sources.list.d/debian.sources"
rm -f "$ROOT/etc/apt/sources.list"
for dir in apt.conf.d auth.conf.d; do
  [ -d "/etc/apt/$dir" ] || continue
  mkdir -p "$ROOT/etc/apt/$dir"
  for f in "/etc/apt/$dir"/*; do
    [ -f "$f" ] || continue
    grep -qxF "$f" "$ROOT"/var/lib/dpkg/info/*.list 2>/dev/null || cp -p "$f" "$ROOT$f"
  done
done
# no daemon starts inside the root
printf '#!/bin/sh\nexit 101\n' >"$ROOT/usr/sbin/policy-rc.d" && chmod 755 "$ROOT/usr/sbin/policy-rc.d"
cp -L /etc/resolv.conf "$ROOT/etc/resolv.conf" 2>/dev/null || true
cp -L /etc/hosts "$ROOT/etc/hosts" 2>/dev/null || true

# CA certificates: the host's bundle, split into the root's local certificates, so the root's
# bundle (rebuilt by update-ca-certificates whenever apt touches it) holds them too.
HOST_CA=${SSL_CERT_FILE:-/etc/ssl/certs/ca-certificates.crt}
if [ -f "$HOST_CA" ]; then
  local_ca="$ROOT/usr/local/share/ca-certificates/host"
  rm -rf "$local_ca" && mkdir -p "$local_ca"
  awk -v dir="$local_ca" '
    /-----BEGIN CERTIFICATE-----/ {n++; f = sprintf("%s/host-%04d.crt", dir, n)}
    f {print > f}
    /-----END CERTIFICATE-----/ {close(f); f = ""}' "$HOST_CA"
  chroot "$ROOT" update-ca-certificates >/dev/null 2>&1 ||
    cp "$HOST_CA" "$ROOT/etc/ssl/certs/ca-certificates.crt"
fi

# --------------------------------------------------------------------------------- mounts
bind_ro() {  # $1 = host path (file or folder), bound read-only at the same path in the root
  local src=$1 dst=$ROOT$1
  [ -e "$src" ] || return 0
  if [ -d "$src" ]; then mkdir -p "$dst"; else mkdir -p "$(dirname "$dst")" && touch "$dst"; fi
  mount --bind "$src" "$dst"
  MOUNTS+=("$dst")
  mount -o remount,bind,ro "$dst" 2>/dev/null || true
}

mount -t proc proc "$ROOT/proc" && MOUNTS+=("$ROOT/proc")
if [ -z "${SLIPMAP_DEBIAN13_NO_SYS:-}" ]; then
  mount --rbind /sys "$ROOT/sys" && mount --make-rslave "$ROOT/sys" && MOUNTS+=("$ROOT/sys")
fi
mount --rbind /dev "$ROOT/dev" && mount --make-rslave "$ROOT/dev" && MOUNTS+=("$ROOT/dev")

# pip: the host's configuration files and the local folders they name (find-links, indexes,
# constraint files given as paths or file:// URLs)
PIP_FILES=(/etc/pip.conf /etc/xdg/pip "$HOME/.config/pip" "$HOME/.pip")
for p in "${PIP_FILES[@]}"; do bind_ro "$p"; done
for p in "${PIP_FILES[@]}"; do
  [ -e "$p" ] || continue
  find "$p" -maxdepth 1 -type f -name '*.conf' -exec cat {} + 2>/dev/null
done | sed -n 's/^[[:space:]]*\(find-links\|index-url\|extra-index-url\|constraint\|requirement\)[[:space:]]*=//p' |
  tr ' ' '\n' | sed -n 's#^file://##p; t; s#^\(/.*\)#\1#p' >"$CACHE/.pip-paths"
env | sed -n 's/^PIP_\(FIND_LINKS\|INDEX_URL\|EXTRA_INDEX_URL\|CONSTRAINT\)=//p' | tr ' ' '\n' |
  sed -n 's#^file://##p; t; s#^\(/.*\)#\1#p' >>"$CACHE/.pip-paths"
while read -r p; do
  case "$p" in /etc/pip.conf | /etc/xdg/pip* | "$HOME"/.config/pip* | "$HOME"/.pip*) continue ;; esac
  p=${p%/simple}; p=${p%/}
  if [ -n "$p" ] && [ -e "$p" ] && ! mountpoint -q "$ROOT$p"; then bind_ro "$p"; fi
done < <(sort -u "$CACHE/.pip-paths")

# -------------------------------------------------------------------------- the tree
mkdir -p "$ROOT$DEST"
# keep the root's venvs and outputs (ignored paths), replace everything else by the host's tree
find "$ROOT$DEST" -mindepth 1 -maxdepth 1 ! -name .venv ! -name .venv-np2 -exec rm -rf {} +
(
  cd "$REPO"
  { git ls-files -z --cached --others --exclude-standard; find .git -type f -print0; } |
    while IFS= read -r -d '' f; do [ -f "$f" ] && printf '%s\0' "$f"; done |
    tar --null -T - -cf -
) | tar -xf - -C "$ROOT$DEST"

# ------------------------------------------------------------------------------ run
ENV=(HOME=/root LANG=C.UTF-8 PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
  TERM="${TERM:-dumb}" DEBIAN_FRONTEND=noninteractive)
while IFS= read -r -d '' kv; do
  case "$kv" in
    PIP_* | http_proxy=* | https_proxy=* | no_proxy=* | HTTP_PROXY=* | HTTPS_PROXY=* | NO_PROXY=* | \
      SSL_CERT_FILE=* | SSL_CERT_DIR=* | REQUESTS_CA_BUNDLE=* | CURL_CA_BUNDLE=* | PYTEST_ARGS=*)
      ENV+=("$kv") ;;
  esac
done < <(env -0)

inside() {  # $1 = shell command line, run in the tree inside the root
  # in its own process group, waited for in the background, so a signal to this script runs
  # the trap at once and the trap can stop everything inside; a background job of a script
  # starts with SIGINT and SIGQUIT ignored, which the tests of Ctrl-C would inherit: env puts
  # their default action back
  setsid chroot "$ROOT" /usr/bin/env -i --default-signal=INT,QUIT "${ENV[@]}" \
    /bin/bash -c "cd $DEST && $1" &
  CHILD=$!
  local rc=0
  wait "$CHILD" || rc=$?
  CHILD=""
  return "$rc"
}

case "$what" in
  test)
    inside 'make demo'
    inside 'make test'
    inside 'echo "debian13: Debian $(cat /etc/debian_version), Python $(python3 -V | cut -d" " -f2),'\
' QGIS $(python3 -c "from qgis.core import Qgis; print(Qgis.QGIS_VERSION)" 2>/dev/null),'\
' numpy $(python3 -c "import numpy; print(numpy.__version__)"),'\
' GDAL $(python3 -c "from osgeo import gdal; print(gdal.__version__)" 2>/dev/null)"'
    ;;
  run) inside "$*" ;;
  shell) chroot "$ROOT" /usr/bin/env -i "${ENV[@]}" /bin/bash -c "cd $DEST && exec bash -i" ;;
  *) echo "usage: $0 [test|shell|run CMD...|clean]" >&2; exit 2 ;;
esac
