#!/usr/bin/env bash
# Set-up for convbki_ros (`make setup`): a virtual environment .venv/ at the repo root
# with every dependency, then `colcon build` of the package into install/.
#
# ROS 2: when a ROS 2 install is sourced (ROS_DISTRO set) or /opt/ros/jazzy exists (it is
# then sourced), the venv sees that install's packages (--system-site-packages) and uses
# its rclpy, message packages and numpy; otherwise ROS 2 comes from PyPI wheels
# (requirements-ros-wheels.txt). With the wheels, set-up also builds the two interface
# packages they lack (tf2_msgs, composition_interfaces: scripts/interfaces/) into install/,
# installs ros2cli and launch from a tarball of their Jazzy sources where one is at hand, and
# makes the venv this workspace's underlay, so that `source install/setup.bash` alone gives
# `ros2 run`, `ros2 launch` and `ros2 interface` (see "--- 4." below).
#
# Idempotent and quick: packages are reinstalled only when the requirement files change
# (sha256 stamp), and colcon runs only when a package file changed since the last build.
#
# Environment:
#   PYTHON           interpreter for the venv when no ROS 2 install is used (default python3)
#   TORCH_INDEX_URL  extra package index for torch, e.g. https://download.pytorch.org/whl/cpu
#   PIP_EXTRA_ARGS   extra arguments for every `pip install` (word-split)
#   CONVBKI_ROS2_TOOLS  the ros2cli + launch sources tarball (wheels only; default
#                    ../shared/vendor/ros2-jazzy-python-tools.tar.gz beside the repo; skipped
#                    when absent)
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
[[ "$MODE" == wheels ]] && req_files+=(requirements-ros-wheels.txt requirements-ros-build.txt)
REQ_HASH="$( { cat "${req_files[@]}"; echo "$MODE ${TORCH_INDEX_URL:-} ${PIP_EXTRA_ARGS:-}"; } \
    | sha256sum | cut -d' ' -f1)"
pip_args=(install --no-input --quiet --progress-bar off)
[[ -n "${TORCH_INDEX_URL:-}" ]] && pip_args+=(--extra-index-url "$TORCH_INDEX_URL")
# shellcheck disable=SC2206
[[ -n "${PIP_EXTRA_ARGS:-}" ]] && pip_args+=($PIP_EXTRA_ARGS)
if [[ ! -f "$STAMPS/requirements.sha256" || "$(cat "$STAMPS/requirements.sha256")" != "$REQ_HASH" \
      || ! -x "$VENV/bin/colcon" ]]; then
    log "installing Python packages (${req_files[*]}); the first time takes a few minutes"
    reqs=(-r requirements.txt)
    [[ "$MODE" == wheels ]] && reqs+=(-r requirements-ros-wheels.txt -r requirements-ros-build.txt)
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

# --- 3b. ros2cli and launch (wheels only) ----------------------------------------------
# PyPI has no ros2cli or launch; their Jazzy sources (pure Python) may be at hand as a tarball.
# Each package folder is installed with --no-deps (their dependencies are the wheels' and
# requirements-ros2-tools.txt's), so pip never looks for ROS packages on the index.
if [[ "$MODE" == wheels ]]; then
    TOOLS_TARBALL="${CONVBKI_ROS2_TOOLS:-$ROOT/../shared/vendor/ros2-jazzy-python-tools.tar.gz}"
    if [[ ! -f "$TOOLS_TARBALL" ]]; then
        [[ -n "${CONVBKI_ROS2_TOOLS:-}" ]] && die "CONVBKI_ROS2_TOOLS=$CONVBKI_ROS2_TOOLS is not a file"
        if [[ -x "$VENV/bin/ros2" ]]; then
            log "no ros2cli/launch sources at $TOOLS_TARBALL: keeping the ros2cli and launch installed before"
        else
            log "no ros2cli/launch sources at $TOOLS_TARBALL (set CONVBKI_ROS2_TOOLS): the ros2 command is not installed"
        fi
    else
        # Not installed: launch_testing, launch_pytest and launch_testing_ros register pytest
        # plugins that every pytest run in the venv loads, and launch_testing 3.4.3's fails
        # under pytest 9 (a hook argument pytest removed), which stops the whole suite.
        TOOLS_SKIP='^(launch_testing|launch_pytest|launch_testing_ros)$'
        TOOLS_HASH="$( { sha256sum < "$TOOLS_TARBALL"; cat requirements-ros2-tools.txt; echo "$TOOLS_SKIP"; } \
            | sha256sum | cut -d' ' -f1)"
        if [[ -x "$VENV/bin/ros2" && "$(cat "$STAMPS/ros2_tools.sha256" 2>/dev/null || true)" == "$TOOLS_HASH" ]]; then
            log "ros2cli and launch up to date"
        else
            log "installing ros2cli and launch from $TOOLS_TARBALL"
            t_tools=$SECONDS
            TOOLS_SRC="$ROOT/build/ros2_tools"
            rm -rf "$TOOLS_SRC" && mkdir -p "$TOOLS_SRC"
            tar -xzf "$TOOLS_TARBALL" -C "$TOOLS_SRC" || die "could not unpack $TOOLS_TARBALL"
            # Package folders: those holding a setup.py (not the copies under a build/ folder).
            mapfile -t tool_dirs < <(cd "$TOOLS_SRC" && find . -name setup.py -not -path '*/build/*' -printf '%h\n' \
                | while read -r d; do [[ "$(basename "$d")" =~ $TOOLS_SKIP ]] || echo "$TOOLS_SRC/${d#./}"; done \
                | LC_ALL=C sort)
            ((${#tool_dirs[@]})) || die "$TOOLS_TARBALL holds no Python package (no setup.py)"
            # --no-build-isolation: build with the venv's pinned setuptools instead of fetching one.
            "$VPY" -m pip "${pip_args[@]}" --no-deps --no-build-isolation "${tool_dirs[@]}" \
                2> >(grep -v 'is ignored: it is neither a file nor a directory' >&2) \
                || die "installing ros2cli and launch from $TOOLS_TARBALL failed (see above)"
            "$VPY" -m pip "${pip_args[@]}" -r requirements-ros2-tools.txt \
                2> >(grep -v 'is ignored: it is neither a file nor a directory' >&2) \
                || die "pip install -r requirements-ros2-tools.txt failed (see above)"
            rm -rf "$TOOLS_SRC"
            echo "$TOOLS_HASH" > "$STAMPS/ros2_tools.sha256"
            log "installed ${#tool_dirs[@]} packages (ros2cli, ros2interface, launch, launch_ros, ros2launch, ...) in $((SECONDS - t_tools)) s"
        fi
    fi
fi

# Make `.venv/bin/python -m convbki_core.X` / `-m convbki_ros.X` work from any directory.
SITE="$("$VPY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
if [[ "$(cat "$SITE/convbki_ros_repo.pth" 2>/dev/null || true)" != "$ROOT" ]]; then
    printf '%s\n' "$ROOT" > "$SITE/convbki_ros_repo.pth"
    log "added the repo to .venv's import path ($SITE/convbki_ros_repo.pth)"
fi

# --- 4. the venv as underlay, and the interface packages the wheels lack (wheels only) --
# A ROS 2 install is an underlay: its local_setup.* puts its prefix on AMENT_PREFIX_PATH (the
# ament index: `ros2 interface`, `ros2 pkg`, launch's package lookups) and its bin/ on PATH,
# and colcon chains every prefix on AMENT_PREFIX_PATH at build time that holds a
# local_setup.* into install/setup.*. The wheels lay the venv out like such a prefix
# (share/ament_index, share/<pkg>, lib), so the venv gets the same two files and is on
# AMENT_PREFIX_PATH during the builds: `source install/setup.bash` then sources the venv
# first, as it would /opt/ros/jazzy. (install/local_setup.bash stays the overlay alone.)
UNDERLAY=""
if [[ "$MODE" == wheels ]]; then
    underlay_sh="$(cat <<EOF
# Written by convbki_ros's scripts/setup.sh: this venv holds ROS 2 Jazzy from the PyPI wheels
# and is the underlay of $ROOT/install (its setup.sh / setup.bash source this file).
case ":\${AMENT_PREFIX_PATH:-}:" in *":$VENV:"*) ;; *) export AMENT_PREFIX_PATH="$VENV\${AMENT_PREFIX_PATH:+:\$AMENT_PREFIX_PATH}" ;; esac
case ":\${PATH:-}:" in *":$VENV/bin:"*) ;; *) export PATH="$VENV/bin\${PATH:+:\$PATH}" ;; esac
EOF
)"
    if [[ "$(cat "$VENV/local_setup.sh" 2>/dev/null || true)" != "$underlay_sh" ]]; then
        printf '%s\n' "$underlay_sh" > "$VENV/local_setup.sh"
        printf '%s\n' "# Written by convbki_ros's scripts/setup.sh (see local_setup.sh)." \
            ". \"$VENV/local_setup.sh\"" > "$VENV/local_setup.bash"
    fi
    UNDERLAY="$VENV"
    export AMENT_PREFIX_PATH="$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"

    # The message wheels' exported CMake targets name the wheel builder's Python and numpy
    # include folders (/opt/python/cp3XX-cp3XX/...), and CMake's generate step fails on a
    # folder that does not exist: point them at this venv's. Idempotent, and after every
    # pip install (one may bring those files back).
    PYINC="$("$VPY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
    NPINC="$("$VPY" -c 'import numpy; print(numpy.get_include())')"
    mapfile -t bad_cmake < <(grep -rlE '/opt/python/cp[0-9]+-cp[0-9]+' "$VENV/share" --include='*.cmake' || true)
    if ((${#bad_cmake[@]})); then
        sed -i -E \
            -e "s#/opt/python/cp[0-9]+-cp[0-9]+/include/python3\.[0-9]+#$PYINC#g" \
            -e "s#/opt/python/cp[0-9]+-cp[0-9]+/lib/python3\.[0-9]+/site-packages/numpy/_core/include#$NPINC#g" \
            "${bad_cmake[@]}"
        log "pointed ${#bad_cmake[@]} CMake export files of the wheels at this venv's Python and numpy"
    fi

    # tf2_msgs and composition_interfaces from scripts/interfaces/ (Jazzy's definitions, so
    # the type hashes are Jazzy's), built with ament_cmake and rosidl from the wheels into
    # install/ beside convbki_ros. Their own --base-paths: colcon does not look below the
    # repo root, which is a package itself, so the main build never sees them.
    IFC_STAMP="$ROOT/build/.convbki_interfaces_stamp"
    IFC_FP="$( { find scripts/interfaces -type f -printf '%p %T@ %s\n' | LC_ALL=C sort
                 echo "$REQ_HASH $VENV $PY_PATH"; } | sha256sum | cut -d' ' -f1)"
    ifc_built=true
    for pkg in tf2_msgs composition_interfaces; do
        [[ -f "$ROOT/install/$pkg/share/ament_index/resource_index/packages/$pkg" ]] || ifc_built=false
    done
    if [[ "$ifc_built" == true && "$(cat "$IFC_STAMP" 2>/dev/null || true)" == "$IFC_FP" ]]; then
        log "interface packages up to date (tf2_msgs, composition_interfaces)"
    else
        for tool in cmake make cc c++; do
            command -v "$tool" >/dev/null 2>&1 \
                || die "$tool not found: building tf2_msgs and composition_interfaces from the ROS 2 wheels needs CMake, make and a C/C++ compiler (Debian/Ubuntu: sudo apt install cmake build-essential)"
        done
        log "building tf2_msgs and composition_interfaces (ROS 2 wheels have none) -> install/; about 30 s"
        t_ifc=$SECONDS
        # A fresh build folder: its CMake caches name the venv's and Python's paths.
        rm -rf "$ROOT/build/interfaces"
        mkdir -p "$ROOT/build/interfaces"
        IFC_LOG="$ROOT/build/interfaces/colcon_build.log"
        # PATH: CMake's find_package and FindPython3 look beside the venv's python;
        # CMAKE_PREFIX_PATH: the wheels' CMake configs; one job at a time on small machines
        # (colcon-cmake runs make -j<cores> otherwise, and the generators are memory-hungry).
        if ! PATH="$VENV/bin:$PATH" CMAKE_PREFIX_PATH="$VENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}" MAKEFLAGS=-j1 \
                "$VENV/bin/colcon" build --base-paths scripts/interfaces --build-base build/interfaces \
                --install-base install --executor sequential \
                --cmake-args -DBUILD_TESTING=OFF -DPython3_EXECUTABLE="$VPY" \
                </dev/null >"$IFC_LOG" 2>&1; then
            tail -n 40 "$IFC_LOG" >&2
            die "building the interface packages failed (full output: build/interfaces/colcon_build.log)"
        fi
        echo "$IFC_FP" > "$IFC_STAMP"
        log "built tf2_msgs and composition_interfaces in $((SECONDS - t_ifc)) s"
    fi
fi

# --- 4b. colcon build ----------------------------------------------------------------
# colcon copies the sources into install/, so any change to a package file must rebuild.
# The fingerprint lists every package file with its mtime and size (catches edits,
# additions and deletions).
fingerprint() {
    local paths=() p
    for p in setup.py setup.cfg package.xml config launch rviz convbki_core convbki_ros resource; do
        [[ -e "$p" ]] && paths+=("$p")
    done
    {
        find "${paths[@]}" \( -name __pycache__ -o -name '*.pyc' -o -name '*.egg-info' \) -prune \
            -o -type f -printf '%p %T@ %s\n' | LC_ALL=C sort
        echo "$MODE $REQ_HASH $UNDERLAY"
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
# way; with --tools also the kernels of synth (the demo), label_noise and evaluate. Only after a
# package file changed (the cache itself notices which kernels changed).
WARM_STAMP="$ROOT/build/.convbki_warm_stamp"
if [[ -f "$WARM_STAMP" && "$(cat "$WARM_STAMP")" == "$FP" ]]; then
    log "compiled kernels up to date"
else
    log "compiling the kernels into numba's cache (a minute the first time)"
    scripts/venv_exec.sh "$VPY" -m convbki_core.tools.warm_up --tools | sed 's/^/[setup] /' \
        || die "compiling the kernels failed (see above)"
    echo "$FP" > "$WARM_STAMP"
fi

log "done in $((SECONDS - T0)) s. Next: make test | make demo | source install/setup.bash"
