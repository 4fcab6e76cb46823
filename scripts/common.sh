# Shared by scripts/demo, scripts/test and scripts/bench: install what is missing, build.
# Sourced, not run. Requires bash; callers use `set -eo pipefail` (not -u: devel/setup.bash).

NG_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
NG_BUILD="${NG_BUILD:-$NG_ROOT/build}"
export PATH="/usr/bin:$PATH"  # Debian's python3 has catkin_pkg; a pyenv python3 first on PATH lacks it

# Debian packages the suite needs to build, run, test and benchmark (no recommends).
NG_PACKAGES=(
  build-essential cmake pkg-config clang-format
  catkin ros-message-generation ros-message-runtime libroscpp-dev libstd-msgs-dev ros-std-msgs
  libgeometry-msgs-dev ros-geometry-msgs libsensor-msgs-dev ros-sensor-msgs
  libvisualization-msgs-dev ros-visualization-msgs libstd-srvs-dev ros-std-srvs
  libtf2-ros-dev libactionlib-dev libactionlib-msgs-dev ros-actionlib-msgs
  libcv-bridge-dev libimage-transport-dev libopencv-dev libeigen3-dev libompl-dev
  liburdfdom-dev libcgal-dev libgmp-dev libmpfr-dev libyaml-cpp-dev libsuitesparse-dev
  coinor-libclp-dev libdcmtk-dev libbenchmark-dev libgtest-dev
  ros-core ros-robot-state-publisher librostest-dev python3-rostest python3-rospy rosbash
  python3-actionlib python3-geometry-msgs python3-sensor-msgs python3-visualization-msgs
  python3-tf2-msgs python3-std-srvs python3-matplotlib
  rviz
  dicom3tools python3-pydicom  # dciodvfy and pydicom check the DICOM-RT export
  coinor-libcbc-dev python3-dicompylercore  # dose-volume MIP; independent DVH check
  libopenblas0-serial  # optimised single-threaded BLAS/LAPACK behind CHOLMOD (libblas.so.3)
)

ng_install() {
  local missing=()
  local pkg
  for pkg in "${NG_PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
  done
  if [ ${#missing[@]} -eq 0 ]; then
    return 0
  fi
  echo "[needle_guidance] installing ${#missing[@]} Debian packages: ${missing[*]}"
  if [ "$(id -u)" -ne 0 ]; then
    echo "[needle_guidance] error: packages are missing and this is not root; run as root" >&2
    return 1
  fi
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -q >/dev/null
  apt-get install -y -q --no-install-recommends "${missing[@]}" >/dev/null
}

ng_build() {
  local jobs
  jobs="$(nproc)"
  mkdir -p "$NG_BUILD"
  if [ ! -f "$NG_BUILD/CMakeCache.txt" ]; then
    local launcher=()  # ccache, when installed, makes rebuilds of a second checkout cheap
    command -v ccache >/dev/null && launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache)
    cmake -S "$NG_ROOT" -B "$NG_BUILD" -DCMAKE_BUILD_TYPE=Release "${launcher[@]}" \
      -DPYTHON_EXECUTABLE=/usr/bin/python3 -DPython3_EXECUTABLE=/usr/bin/python3 \
      -DCATKIN_ENABLE_TESTING=ON >"$NG_BUILD/configure.log" 2>&1 \
      || { cat "$NG_BUILD/configure.log" >&2; return 1; }
  fi
  echo "[needle_guidance] building in $NG_BUILD"
  cmake --build "$NG_BUILD" -j"$jobs" >"$NG_BUILD/build.log" 2>&1 \
    || { grep -E -B2 -A12 "error|Error" "$NG_BUILD/build.log" | head -150 >&2; return 1; }
}

ng_build_tests() {
  cmake --build "$NG_BUILD" -j"$(nproc)" --target tests >"$NG_BUILD/build_tests.log" 2>&1 \
    || { grep -E -B2 -A12 "error|Error" "$NG_BUILD/build_tests.log" | head -150 >&2; return 1; }
}

ng_source() {
  # shellcheck disable=SC1091
  source "$NG_BUILD/devel/setup.bash"
  export ROS_HOME="${ROS_HOME:-$NG_BUILD/ros_home}"
  export ROS_LOG_DIR="${ROS_LOG_DIR:-$NG_BUILD/ros_log}"
  # Loopback unless the caller says otherwise: ROS 1 has no authentication, and any host that
  # reaches a node's port can command the robot or the afterloader (README.md, "Safety").
  export ROS_IP="${ROS_IP:-127.0.0.1}"
  export ROS_HOSTNAME="${ROS_HOSTNAME:-localhost}"
}
