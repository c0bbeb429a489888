#!/usr/bin/env bash
# One idempotent set-up of mapf_fleet on Debian 12 / Python 3.11:
#   1. Debian tools (cmake, make, g++, python3.11 venv + headers) via apt-get, only when missing;
#      then Debian's chromium + chromium-driver (the live view's headless-browser test), when
#      missing and apt-get can run (root or sudo); without them set-up only warns, except under
#      CI (CI=true), whose suite needs the browser;
#   2. the venv (<repo>/.venv, or $MAPF_FLEET_VENV) with python3.11;
#   3. pinned PyPI packages (requirements.txt + constraints.txt); 3b. POGEMA (requirements-pogema.txt)
#      into <venv>/pogema, a folder of its own (MAPF_FLEET_POGEMA=0 skips it);
#   4. the repair of the ROS wheels' CMake export files (DESIGN.md section 2);
#   5. mapf_fleet_interfaces built with CMake (out of tree in build/) into the venv prefix;
#   6. mapf_fleet installed in editable mode.
# Steps 1b, 3, 3b, 5 and 6 leave a hash stamp in <venv>/.mapf_fleet_setup/ and are skipped while their
# inputs are unchanged, so a second run takes seconds. Downloads come only from PyPI and Debian.
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${MAPF_FLEET_VENV:-$REPO/.venv}"
PYTHON_FOR_VENV="${MAPF_FLEET_PYTHON:-python3.11}"
STAMPS="$VENV/.mapf_fleet_setup"
BUILD_DIR="$REPO/build/mapf_fleet_interfaces"
SETUP_START=$SECONDS

say() { printf '[setup %3ds] %s\n' "$((SECONDS - SETUP_START))" "$*"; }
die() { printf 'setup: error: %s\n' "$*" >&2; exit 1; }

# Hash of files (content and name) plus extra strings, to decide whether a step must re-run.
inputs_hash() {
  local extra="$1"; shift
  { printf '%s\n' "$extra"; for f in "$@"; do printf '%s\n' "$f"; cat "$f"; done; } \
    | sha256sum | cut -d' ' -f1
}
# pip, with the warnings of this machine's pip configuration about index locations that do not
# hold a package filtered out (hundreds of lines of noise in a fresh install).
run_pip() {
  { "$PY" -m pip --disable-pip-version-check "$@" 2>&1 1>&3 \
      | { grep -v "is ignored: it is neither a file nor a directory" || true; } >&2; } 3>&1
}
stamp_matches() { [ -f "$STAMPS/$1" ] && [ "$(cat "$STAMPS/$1")" = "$2" ]; }
write_stamp() { mkdir -p "$STAMPS"; printf '%s\n' "$2" > "$STAMPS/$1"; }

# ---- 1. Debian tools -------------------------------------------------------------------------
apt_install() {
  local runner=()
  if [ "$(id -u)" -ne 0 ]; then
    command -v sudo >/dev/null || die "need root or sudo to apt-get install $*"
    runner=(sudo)
  fi
  say "apt-get install $*"
  "${runner[@]}" env DEBIAN_FRONTEND=noninteractive apt-get update -qq
  "${runner[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "$@"
}

missing=()
command -v cmake >/dev/null || missing+=(cmake)
command -v make >/dev/null || missing+=(make)
command -v g++ >/dev/null || missing+=(g++)
if ! command -v "$PYTHON_FOR_VENV" >/dev/null; then
  missing+=(python3.11 python3.11-venv python3.11-dev)
else
  # Debian splits venv (ensurepip) and the C headers (Python.h, needed by the generated
  # interface extension) out of the interpreter package.
  "$PYTHON_FOR_VENV" -c 'import ensurepip, venv' 2>/dev/null || missing+=(python3.11-venv)
  "$PYTHON_FOR_VENV" -c 'import os, sysconfig, sys; sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))' \
    || missing+=(python3.11-dev)
fi
if [ ${#missing[@]} -gt 0 ]; then
  command -v apt-get >/dev/null || die "missing ${missing[*]} and no apt-get to install them"
  apt_install "${missing[@]}"
fi
"$PYTHON_FOR_VENV" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' \
  || die "$PYTHON_FOR_VENV is not Python 3.11 (the ROS 2 Jazzy wheels are cp311); set MAPF_FLEET_PYTHON"

# ---- 1b. headless browser for the live view's screenshot test -------------------------------
# `mapf-fleet view` is tested in a real browser (test/ros/test_live_view.py); Debian's chromium
# is the one CI can install. Set MAPF_FLEET_BROWSER=0 to skip this step.
BROWSER_PACKAGES=(chromium chromium-driver)
browser_present() { command -v chromium >/dev/null && command -v chromedriver >/dev/null; }
if [ "${MAPF_FLEET_BROWSER:-1}" = "0" ]; then
  say "MAPF_FLEET_BROWSER=0: not checking for chromium"
elif browser_present && [ -f "$STAMPS/browser" ]; then
  say "chromium present: $(chromium --version 2>/dev/null | head -1)"
elif browser_present; then
  write_stamp browser "$(chromium --version 2>/dev/null | head -1)"
  say "chromium present: $(cat "$STAMPS/browser")"
elif command -v apt-get >/dev/null && { [ "$(id -u)" -eq 0 ] || sudo -n true 2>/dev/null; }; then
  if apt_install "${BROWSER_PACKAGES[@]}" && browser_present; then
    write_stamp browser "$(chromium --version 2>/dev/null | head -1)"
    say "installed $(cat "$STAMPS/browser")"
  elif [ "${CI:-}" = "true" ]; then
    die "could not install ${BROWSER_PACKAGES[*]} (the live view's browser test needs them under CI)"
  else
    say "warning: could not install ${BROWSER_PACKAGES[*]}; the live view's browser test will skip"
  fi
elif [ "${CI:-}" = "true" ]; then
  die "chromium is missing and apt-get cannot run here (root or sudo needed); CI's browser test needs it"
else
  say "warning: no chromium and no apt-get/sudo to install it; the live view's browser test will skip"
fi

# ---- 2. venv ---------------------------------------------------------------------------------
if [ -x "$VENV/bin/python" ] && "$VENV/bin/python" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
  say "venv $VENV exists"
else
  say "creating venv $VENV with $PYTHON_FOR_VENV"
  rm -rf "$VENV"
  "$PYTHON_FOR_VENV" -m venv "$VENV"
fi
PY="$VENV/bin/python"

# ---- 3. pinned packages ----------------------------------------------------------------------
REQ_HASH="$(inputs_hash "$VENV" "$REPO/requirements.txt" "$REPO/constraints.txt")"
if stamp_matches requirements "$REQ_HASH"; then
  say "requirements unchanged: skipping pip"
else
  say "pip install -r requirements.txt -c constraints.txt"
  run_pip install -q -r "$REPO/requirements.txt" -c "$REPO/constraints.txt"
  write_stamp requirements "$REQ_HASH"
fi

# ---- 3b. POGEMA, the field's benchmark environment (mapf_fleet/evaluation/pogema_bench.py) ---
# Into <venv>/pogema with --no-deps: a folder of its own that only the benchmark puts on
# sys.path, so its old pins (numpy<=1.26.4, pydantic 1) change nothing in the venv. Set
# MAPF_FLEET_POGEMA=0 to skip (the benchmark and its test then say how to install it).
POGEMA_DIR="$VENV/pogema"
POGEMA_HASH="$(inputs_hash "$VENV" "$REPO/requirements-pogema.txt")"
if [ "${MAPF_FLEET_POGEMA:-1}" = "0" ]; then
  say "MAPF_FLEET_POGEMA=0: not installing POGEMA"
elif stamp_matches pogema "$POGEMA_HASH" && [ -d "$POGEMA_DIR/pogema" ]; then
  say "POGEMA unchanged: skipping pip"
else
  say "pip install --no-deps --target $POGEMA_DIR -r requirements-pogema.txt"
  rm -rf "$POGEMA_DIR"
  run_pip install -q --no-deps --target "$POGEMA_DIR" -r "$REPO/requirements-pogema.txt"
  write_stamp pogema "$POGEMA_HASH"
fi

# From here on, run the venv as a ROS prefix (and without the bootstrapper's re-exec).
# shellcheck source=env.sh
source "$REPO/scripts/env.sh"

# ---- 4. CMake export repair ------------------------------------------------------------------
# The ROS wheels were built under /opt/python/cp311-cp311; their CMake exports name that
# interpreter's include directories, which do not exist here. Point them at this venv's.
PY_INCLUDE="$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
NUMPY_INCLUDE="$("$PY" -c 'import numpy; print(numpy.get_include())')"
BAD_NUMPY=/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include
BAD_PY=/opt/python/cp311-cp311/include/python3.11
mapfile -t broken < <(grep -rlF -e "$BAD_NUMPY" -e "$BAD_PY" "$VENV/share" --include='*.cmake' || true)
if [ ${#broken[@]} -gt 0 ]; then
  say "repairing ${#broken[@]} CMake export files (python: $PY_INCLUDE, numpy: $NUMPY_INCLUDE)"
  sed -i -e "s|$BAD_NUMPY|$NUMPY_INCLUDE|g" -e "s|$BAD_PY|$PY_INCLUDE|g" "${broken[@]}"
else
  say "CMake export files already repaired"
fi

# ---- 5. mapf_fleet_interfaces ----------------------------------------------------------------
IFACE="$REPO/mapf_fleet_interfaces"
mapfile -t iface_files < <(cd "$IFACE" && find CMakeLists.txt package.xml msg srv action -type f \( -name '*.msg' -o -name '*.srv' -o -name '*.action' -o -name 'CMakeLists.txt' -o -name 'package.xml' \) 2>/dev/null | LC_ALL=C sort)
IFACE_HASH="$(cd "$IFACE" && inputs_hash "$VENV $REQ_HASH" "${iface_files[@]}")"
if stamp_matches interfaces "$IFACE_HASH" && "$PY" -c 'import mapf_fleet_interfaces.msg' 2>/dev/null; then
  say "mapf_fleet_interfaces unchanged: skipping build"
else
  say "building mapf_fleet_interfaces (${#iface_files[@]} files) into $VENV"
  # A cache made for another venv or source tree cannot be reused.
  if [ -f "$BUILD_DIR/CMakeCache.txt" ] && \
     ! grep -qxF "CMAKE_INSTALL_PREFIX:PATH=$VENV" "$BUILD_DIR/CMakeCache.txt"; then
    rm -rf "$BUILD_DIR"
  fi
  # Remove what the previous build installed, so a deleted .msg leaves no stale module.
  if [ -f "$BUILD_DIR/install_manifest.txt" ]; then
    xargs -d '\n' rm -f < "$BUILD_DIR/install_manifest.txt"
  fi
  mkdir -p "$BUILD_DIR"
  cmake -S "$IFACE" -B "$BUILD_DIR" -Wno-dev \
    -DCMAKE_BUILD_TYPE=Release \
    -DCMAKE_PREFIX_PATH="$VENV" \
    -DCMAKE_INSTALL_PREFIX="$VENV" \
    -DPython3_EXECUTABLE="$PY" \
    -DBUILD_TESTING=OFF > "$BUILD_DIR.configure.log" 2>&1 \
    || { tail -40 "$BUILD_DIR.configure.log" >&2; die "cmake configure failed (log: $BUILD_DIR.configure.log)"; }
  cmake --build "$BUILD_DIR" -j "$(nproc)" > "$BUILD_DIR.build.log" 2>&1 \
    || { tail -40 "$BUILD_DIR.build.log" >&2; die "interface build failed (log: $BUILD_DIR.build.log)"; }
  cmake --install "$BUILD_DIR" > "$BUILD_DIR.install.log" 2>&1 \
    || { tail -40 "$BUILD_DIR.install.log" >&2; die "interface install failed (log: $BUILD_DIR.install.log)"; }
  "$PY" -c 'import mapf_fleet_interfaces.msg, mapf_fleet_interfaces.srv' \
    || die "mapf_fleet_interfaces was built but does not import"
  write_stamp interfaces "$IFACE_HASH"
fi

# ---- 6. mapf_fleet (editable) ----------------------------------------------------------------
PKG_HASH="$(inputs_hash "$VENV $REPO" "$REPO/setup.py" "$REPO/setup.cfg" "$REPO/package.xml")"
if stamp_matches package "$PKG_HASH" && (cd / && "$PY" -c 'import mapf_fleet') 2>/dev/null; then  # from /: not through the cwd
  say "mapf_fleet already installed (editable)"
else
  say "pip install -e . (mapf_fleet)"
  # No build isolation: the build uses the pinned setuptools already in the venv (offline-safe).
  run_pip install -q --no-deps --no-build-isolation -e "$REPO"
  write_stamp package "$PKG_HASH"
fi

# An editable wheel does not install setup.py's data_files, so register the package in the
# venv's ament index by hand, as symlinks into the work tree: get_package_share_directory(
# "mapf_fleet") then finds package.xml, config/, models/ and launch/ exactly as a colcon install would,
# and edits to config/ show up without re-installing.
SHARE="$VENV/share/mapf_fleet"
mkdir -p "$SHARE" "$VENV/share/ament_index/resource_index/packages"
: > "$VENV/share/ament_index/resource_index/packages/mapf_fleet"
for item in package.xml config models launch; do
  ln -sfn "$REPO/$item" "$SHARE/$item"
done

# ---- 7. the compiled kernels ------------------------------------------------------------------
# numba compiles a kernel on its first call and caches it beside its source: compiled here once,
# so the first tick of the first run does not wait for it (the windowed plan's search alone took
# about 6 s on a fresh clone).
KERNEL_HASH="$(inputs_hash "$VENV" "$REPO"/mapf_fleet/coordination/lns.py "$REPO"/mapf_fleet/grid/search_kernel.py "$REPO"/mapf_fleet/grid/guided_kernel.py)"
if stamp_matches kernels "$KERNEL_HASH"; then
  say "compiled kernels cached"
else
  say "compiling the kernels (numba, cached beside their sources)"
  (cd "$REPO" && "$PY" - <<'PYEOF'
import numpy as np
from mapf_fleet.coordination.factory import make_shield
from mapf_fleet.grid.guidance_made import highways

grid = np.zeros((6, 6), dtype=np.uint8)
for guidance in (None, highways(grid)):
    shield = make_shield("pibt_anchor_swap_lns", grid, [[5, 5], [0, 0]], guidance=guidance)
    shield.step(np.array([[0, 0], [5, 5]]), np.tile(np.arange(5), (2, 1)))
PYEOF
  ) || die "compiling the kernels failed"
  write_stamp kernels "$KERNEL_HASH"
fi

say "done: source scripts/env.sh to use $VENV"
