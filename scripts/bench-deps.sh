#!/usr/bin/env bash
# The classical peer (Open3D) for benchmarks only: needs Debian's libusb and libgl.
set -u
if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
  dpkg -s libgl1 libusb-1.0-0 >/dev/null 2>&1 || \
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libgl1 libusb-1.0-0 libgomp1 >/dev/null)
fi
.venv/bin/python -c "import open3d" 2>/dev/null || .venv/bin/pip install -q open3d
