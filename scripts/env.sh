# shellcheck shell=bash
# Source this file (do not execute it) to get the project's ROS 2 environment:
#
#     source scripts/env.sh        # after scripts/setup
#
# It activates .venv (ROS 2 Jazzy from PyPI wheels), sources the colcon install space
# install/setup.bash (so ament_index finds orbit_tracking and its executables), and sets:
#
#   RMW_IMPLEMENTATION=rmw_fastrtps_cpp      (unless already set)
#   ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST  (always: DDS discovery stays on this machine)
#   ROS_DOMAIN_ID=<1..100 from the PID>      (only when unset, so parallel runs don't cross-talk)
#   AMENT_PREFIX_PATH += .venv               (the ROS wheels' own ament index, like /opt/ros/jazzy)
#   ORBIT_TRACKING_ROOT=<project root>
#
# Safe to source from scripts running with `set -euo pipefail`; the caller's `set -u` state is
# restored afterwards.

_ot_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

if [[ ! -x "$_ot_root/.venv/bin/python" || ! -f "$_ot_root/install/setup.bash" ]]; then
    echo "[env] $_ot_root is not set up: run scripts/setup first" >&2
    unset _ot_root
    return 1 2>/dev/null || exit 1
fi

if [[ ":${PYTHONPATH:-}:" == *:/opt/ros/* ]]; then
    echo "[env] WARNING: a system ROS installation is sourced (PYTHONPATH=$PYTHONPATH);" \
        "its modules may shadow the venv's. Use a fresh shell." >&2
fi

# venv's activate and colcon's setup.bash read unset variables: relax `set -u` around them.
case $- in *u*) _ot_had_u=1 ;; *) _ot_had_u=0 ;; esac
set +u
# shellcheck disable=SC1091
source "$_ot_root/.venv/bin/activate"
# shellcheck disable=SC1091
source "$_ot_root/install/setup.bash"
if [[ "$_ot_had_u" == 1 ]]; then set -u; fi

# The ROS wheels install an ament index under .venv/share (std_msgs, rclpy, ...); make it
# visible as the underlay, after this package's install space.
case ":${AMENT_PREFIX_PATH:-}:" in
    *":$VIRTUAL_ENV:"*) ;;
    *) export AMENT_PREFIX_PATH="${AMENT_PREFIX_PATH:+$AMENT_PREFIX_PATH:}$VIRTUAL_ENV" ;;
esac

export ORBIT_TRACKING_ROOT="$_ot_root"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
if [[ -z "${ROS_DOMAIN_ID:-}" ]]; then
    # 1..100: never the default domain 0, and inside the 0..101 range ROS documents as safe.
    ROS_DOMAIN_ID=$(($$ % 100 + 1))
    export ROS_DOMAIN_ID
fi

unset _ot_root _ot_had_u
