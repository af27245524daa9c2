#!/usr/bin/env bash
# Run a command in the environment scripts/setup.sh prepared: sources the ROS 2 install
# that set-up found in /opt/ros (when it had to source one itself), then runs "$@".
#
# With ROS 2 from the PyPI wheels: adds the venv as underlay (.venv/local_setup.sh, as
# `source install/setup.bash` does) and the environment of the interface packages set-up
# built into install/ (tf2_msgs, composition_interfaces: their Python modules, and their
# libraries on LD_LIBRARY_PATH, which the typesupport loads them from). Not install/'s
# convbki_ros: the tests and `python -m ...` use the source tree.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
ros_setup="$(cat "$ROOT/.venv/.convbki/ros_setup" 2>/dev/null || true)"
set +u
if [[ -z "${ROS_DISTRO:-}" && -n "$ros_setup" && -f "$ros_setup" ]]; then
    # shellcheck disable=SC1090
    source "$ros_setup"
elif [[ -z "${ROS_DISTRO:-}" && -f "$ROOT/.venv/local_setup.sh" ]]; then
    # shellcheck disable=SC1091
    . "$ROOT/.venv/local_setup.sh"
    for pkg in tf2_msgs composition_interfaces; do
        if [[ -f "$ROOT/install/$pkg/share/$pkg/package.sh" ]]; then
            COLCON_CURRENT_PREFIX="$ROOT/install/$pkg"
            # shellcheck disable=SC1090
            . "$ROOT/install/$pkg/share/$pkg/package.sh"
        fi
    done
    unset COLCON_CURRENT_PREFIX
fi
set -u
exec "$@"
