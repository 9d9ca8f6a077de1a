#!/usr/bin/env bash
# Create or update .venv with everything BRAVE-6D needs, on a fresh Linux machine (CPU).
# --with-ros2 also makes .venv-ros2 (brave6d ros2 and its tests; scripts/test.sh asks for it).
# Idempotent: a second run with an unchanged pyproject.toml only checks and returns.
set -euo pipefail
cd "$(dirname "$0")/.."

# open3d needs libusb-1.0 (ImportError: libusb-1.0.so.0 otherwise)
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "setup: installing the Debian package libusb-1.0-0 (needed by open3d)" >&2
  $SUDO apt-get update -qq && $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi

PYTHON="${PYTHON:-python3}"

# Refuse early, naming the folder and the shortfall, when the disk cannot hold the install (pip would
# stop half way with "No space left on device"). .venv takes 3.3 GB, pip unpacks wheels beside it.
need_free_space() {  # need_free_space DIR MB
  local free_mb
  free_mb=$(df -Pm "$1" | awk 'NR == 2 {print $4}')
  if [ -n "$free_mb" ] && [ "$free_mb" -lt "$2" ]; then
    echo "setup: $(cd "$1" && pwd) has ${free_mb} MB free; the install needs about $2 MB there" \
         "(BRAVE6D_SETUP_FREE_MB sets the check). Free some space and run this again." >&2
    exit 1
  fi
}

stamp=".venv/.brave6d-installed"
want="$(sha256sum pyproject.toml | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  need_free_space . "${BRAVE6D_SETUP_FREE_MB:-4000}"
  [ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
  echo "setup: installing into .venv (about 3.3 GB; a few minutes the first time)" >&2
  # --no-cache-dir: pip's cache would hold a second copy of every downloaded wheel (about 1 GB).
  .venv/bin/python -m pip install -q --no-cache-dir --upgrade pip
  # The CPU wheel of torch first, pinned: an unpinned torch would pull the multi-GB CUDA build.
  .venv/bin/python -m pip install -q --no-cache-dir "torch==2.13.0"
  .venv/bin/python -m pip install -q --no-cache-dir -e ".[test]"
  echo "$want" > "$stamp"
fi

# ROS 2 (brave6d ros2 and its tests) in its own venv layered over .venv: the rclpy wheels put ROS 2's
# std_msgs, geometry_msgs ... at the top level, where they would shadow Debian's ROS 1 packages that
# the ROS 1 node appends to sys.path. .venv-ros2 sees its own site-packages first, then .venv's.
[ "${1:-}" = "--with-ros2" ] || exit 0
want_ros2="$want-ros2"
stamp_ros2=".venv-ros2/.brave6d-installed"
if [ ! -f "$stamp_ros2" ] || [ "$(cat "$stamp_ros2")" != "$want_ros2" ]; then
  t0=$(date +%s%N)
  # brave6d_msgs is compiled from rosidl's C/C++ sources at install
  if ! command -v gcc >/dev/null 2>&1 || ! command -v g++ >/dev/null 2>&1; then
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    echo "setup: installing the Debian packages gcc g++ (brave6d_msgs is built from rosidl's sources)" >&2
    $SUDO apt-get update -qq && $SUDO apt-get install -y -qq gcc g++ >/dev/null
  fi
  need_free_space . "${BRAVE6D_SETUP_FREE_MB_ROS2:-400}"
  [ -x .venv-ros2/bin/python ] || "$PYTHON" -m venv .venv-ros2
  main_site="$(.venv/bin/python -c 'import sysconfig; print(sysconfig.get_path("purelib"))')"
  ros2_site="$(.venv-ros2/bin/python -c 'import sysconfig; print(sysconfig.get_path("purelib"))')"
  echo "import site; site.addsitedir('$main_site')" > "$ros2_site/_brave6d_main_venv.pth"
  .venv-ros2/bin/python -m pip install -q --no-cache-dir -e ".[ros2]"
  .venv-ros2/bin/python -m brave6d.ros_interface.ros2.interfaces
  echo "setup: ROS 2 (rclpy wheels, brave6d_msgs) in .venv-ros2 in $(( ($(date +%s%N) - t0) / 1000000 )) ms" >&2
  echo "$want_ros2" > "$stamp_ros2"
fi
