# Source to work in the built workspace: the project venv, the colcon install space, and the
# DDS settings every process of this project uses on one machine.
# Usage: . tools/env.sh   (from the repository root; on a ROS 2 Jazzy install, after
# /opt/ros/jazzy/setup.bash)
# The venv: $COOP_VENV if set (relative to the repository root unless absolute), else .venv
# (make's pinned venv), else .venv-jazzy (the ROS 2 Jazzy install's, docs/install.md).
_coop_root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
_coop_venv=${COOP_VENV:-.venv}
if [ -z "${COOP_VENV:-}" ] && [ ! -d "$_coop_root/.venv" ] && [ -d "$_coop_root/.venv-jazzy" ]; then
  _coop_venv=.venv-jazzy
fi
case $_coop_venv in /*) ;; *) _coop_venv="$_coop_root/$_coop_venv" ;; esac
export VIRTUAL_ENV="$_coop_venv"
export PATH="$VIRTUAL_ENV/bin:$PATH"
# make's venv holds the ROS 2 Jazzy wheels, an ament prefix; a Jazzy install's venv does not
if [ -d "$VIRTUAL_ENV/share/ament_index" ]; then
  export AMENT_PREFIX_PATH="$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
  export CMAKE_PREFIX_PATH="$VIRTUAL_ENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
fi
if [ -f "$_coop_root/install/setup.bash" ]; then
  # shellcheck disable=SC1091
  COLCON_CURRENT_PREFIX="$_coop_root/install" . "$_coop_root/install/setup.bash"
fi
# make's venv: the real ros2cli and launch, when `make ros2-tools` put them there (the mission
# starts its launch file through launch)
if [ -f "$_coop_root/.ros2-tools/install/local_setup.bash" ]; then
  # shellcheck disable=SC1091
  . "$_coop_root/.ros2-tools/install/local_setup.bash"
fi
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
# A 16 MB Fast DDS shared-memory segment (default 0.5 MB): a 640x480 stereo pair fills the default
# one and every best-effort sample queued behind it is dropped, 200 Hz IMU included
# (bench/bag_rate.py measures both); 8192 messages per receiving port (default 512), which a
# process starved of CPU for 0.3 s overflows (bench/dds_stall.py). Graph-wide, so every process
# uses it.
export FASTRTPS_DEFAULT_PROFILES_FILE="${FASTRTPS_DEFAULT_PROFILES_FILE:-$_coop_root/src/rover_bag/config/fastdds_large_shm.xml}"
# Two BLAS threads on two cores make small solves 5-20x slower (platform.md).
export OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
export MPLBACKEND=Agg
unset _coop_root _coop_venv
