#!/usr/bin/env bash
# Build the ElastoID bundle on Linux and check it: dist/elastoid/elastoid.
#
#   packaging/build_linux.sh                 # venv in .venv-build/, output in dist/ and build/
#   VENV=/path/to/venv packaging/build_linux.sh
#   DIST=/tmp/out WORK=/tmp/work packaging/build_linux.sh
#
# Creates (or reuses) a virtual environment, installs the project with its
# `build` extra (PyInstaller), runs PyInstaller on packaging/elastoid.spec, then
# runs the bundle's self-test (and, when an X display or xvfb-run is available,
# the self-test of the window with its 3-D view). Exits non-zero if any step fails.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
VENV="${VENV:-$ROOT/.venv-build}"
DIST="${DIST:-$ROOT/dist}"
WORK="${WORK:-$ROOT/build}"
PYTHON="${PYTHON:-python3}"

if [ ! -x "$VENV/bin/python" ]; then
  echo "== creating $VENV"
  "$PYTHON" -m venv "$VENV"
fi
echo "== installing .[build] into $VENV"
"$VENV/bin/python" -m pip install --quiet --upgrade pip
"$VENV/bin/python" -m pip install --quiet -e ".[build]"

echo "== PyInstaller (onedir): $DIST/elastoid"
t0=$(date +%s)
"$VENV/bin/python" -m PyInstaller --noconfirm --clean --log-level WARN \
  --distpath "$DIST" --workpath "$WORK" packaging/elastoid.spec
t1=$(date +%s)
echo "== built in $((t1 - t0)) s; bundle size $(du -sh "$DIST/elastoid" | cut -f1)"

EXE="$DIST/elastoid/elastoid"
# a scratch mesh cache, so the self-test neither reads nor fills the user's
CACHE="$(mktemp -d)"
trap 'rm -rf "$CACHE"' EXIT

echo "== self-test (offscreen, no display needed)"
(cd "$CACHE" && env -u PYTHONPATH ELASTOID_CACHE_DIR="$CACHE" "$EXE" --selftest)

if [ -n "${DISPLAY:-}" ]; then
  echo "== self-test of the window with its 3-D view (DISPLAY=$DISPLAY)"
  (cd "$CACHE" && env -u PYTHONPATH ELASTOID_CACHE_DIR="$CACHE" "$EXE" selftest --only window-3d)
elif command -v xvfb-run >/dev/null 2>&1; then
  echo "== self-test of the window with its 3-D view (xvfb-run)"
  (cd "$CACHE" && env -u PYTHONPATH ELASTOID_CACHE_DIR="$CACHE" xvfb-run -a "$EXE" selftest --only window-3d)
else
  echo "== no X display and no xvfb-run: the 3-D view was not checked (apt-get install xvfb)"
fi
echo "== done: $EXE"
