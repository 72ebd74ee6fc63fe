#!/usr/bin/env bash
# Build an installable QGIS plugin zip: slipmap-<version>.zip holding the folder slipmap/ with
# the files of the plugin and package that git tracks or would track (untracked files that
# .gitignore does not exclude are in, so a new module or style is not lost before its commit;
# no .git, __pycache__, tests, benchmarks, CI).
# Usage: bash scripts/plugin_zip.sh [OUTPUT.zip]   (default: slipmap-<version>.zip in the
# repository root; a relative OUTPUT is taken from the current directory)
set -euo pipefail
out="${1:-}"
case "$out" in "" | /*) ;; *) out="$PWD/$out" ;; esac
cd "$(dirname "$0")/.."
version=$(sed -n 's/^version = "\(.*\)"/\1/p' pyproject.toml | head -1)
out="${out:-slipmap-${version}.zip}"
stage=$(mktemp -d)
trap 'rm -rf "$stage"' EXIT
mkdir -p "$stage/slipmap"
{ git ls-files --cached; git ls-files --others --exclude-standard; } | sort -u | grep -vE '^(tests/|benchmarks/|\.ci/|\.gitignore$|Makefile$|scripts/|constraints.txt$)' \
  | while read -r f; do [ -f "$f" ] || continue; mkdir -p "$stage/slipmap/$(dirname "$f")"; cp "$f" "$stage/slipmap/$f"; done
rm -f "$out"
python3 - "$stage" "$out" <<'PY'
import os, sys, zipfile
stage, out = sys.argv[1], sys.argv[2]
with zipfile.ZipFile(out + ".tmp", "w", zipfile.ZIP_DEFLATED) as z:
    for root, _, files in os.walk(stage):
        for f in sorted(files):
            p = os.path.join(root, f)
            z.write(p, os.path.relpath(p, stage))
os.replace(out + ".tmp", out)
PY
echo "wrote $out"
