# Environment of the project's venv as a ROS 2 prefix. Source it (scripts/run.sh does):
#   source scripts/env.sh
# MAPF_FLEET_VENV overrides the venv location (default: <repo>/.venv).

_mapf_fleet_repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export MAPF_FLEET_REPO="$_mapf_fleet_repo"
export MAPF_FLEET_VENV="${MAPF_FLEET_VENV:-$_mapf_fleet_repo/.venv}"
export VIRTUAL_ENV="$MAPF_FLEET_VENV"
case ":$PATH:" in
  *":$MAPF_FLEET_VENV/bin:"*) ;;
  *) export PATH="$MAPF_FLEET_VENV/bin:$PATH" ;;
esac

# The venv is the ROS prefix: get_package_share_directory() and rosidl look here.
export AMENT_PREFIX_PATH="$MAPF_FLEET_VENV"
export RMW_IMPLEMENTATION=rmw_fastrtps_cpp
# Nothing the project starts talks beyond loopback.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST

# ros-wheels-bootstrapper (a .pth file run at every interpreter start) re-executes Python once
# with LD_LIBRARY_PATH pointing at <venv>/lib and site-packages/ros_*.libs, unless
# _ROS_WHEELS_BOOTSTRAP_COMPLETE is set. Setting both up front avoids the re-exec, which
# would otherwise happen in every subprocess (pytest workers, ROS node processes).
_mapf_fleet_site="$MAPF_FLEET_VENV/lib/python3.11/site-packages"
_mapf_fleet_ld="$MAPF_FLEET_VENV/lib"
for _mapf_fleet_libs in "$_mapf_fleet_site"/ros_*.libs; do
  [ -d "$_mapf_fleet_libs" ] && _mapf_fleet_ld="$_mapf_fleet_ld:$_mapf_fleet_libs"
done
# Drop entries of this venv from an earlier sourcing (the set of ros_*.libs may have changed),
# then put the current ones first.
_mapf_fleet_old=""
IFS=: read -r -a _mapf_fleet_parts <<< "${LD_LIBRARY_PATH:-}"
for _mapf_fleet_part in "${_mapf_fleet_parts[@]}"; do
  case "$_mapf_fleet_part" in
    ""|"$MAPF_FLEET_VENV"/*) ;;
    *) _mapf_fleet_old="${_mapf_fleet_old:+$_mapf_fleet_old:}$_mapf_fleet_part" ;;
  esac
done
export LD_LIBRARY_PATH="$_mapf_fleet_ld${_mapf_fleet_old:+:$_mapf_fleet_old}"
export _ROS_WHEELS_BOOTSTRAP_COMPLETE=1
unset _mapf_fleet_repo _mapf_fleet_site _mapf_fleet_ld _mapf_fleet_libs _mapf_fleet_old \
  _mapf_fleet_parts _mapf_fleet_part
