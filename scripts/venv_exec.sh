#!/usr/bin/env bash
# Run a command in the environment scripts/setup.sh prepared: sources the ROS 2 install
# that set-up found in /opt/ros (when it had to source one itself), then runs "$@".
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
ros_setup="$(cat "$ROOT/.venv/.convbki/ros_setup" 2>/dev/null || true)"
if [[ -z "${ROS_DISTRO:-}" && -n "$ros_setup" && -f "$ros_setup" ]]; then
    set +u
    # shellcheck disable=SC1090
    source "$ros_setup"
    set -u
fi
exec "$@"
