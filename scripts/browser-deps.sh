#!/usr/bin/env bash
# Debian packages the tests need: chromium for the browser tests (playwright cannot download its
# own browser here) and libusb for pyrealsense2 (the RealSense stream-client tests).
# Skipped quietly where apt is not usable; those tests then skip with a reason.
set -u
need=()
[ -x /usr/bin/chromium ] || need+=(chromium)
dpkg -s libusb-1.0-0 >/dev/null 2>&1 || need+=(libusb-1.0-0)
if [ ${#need[@]} -eq 0 ]; then exit 0; fi
if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need[@]}" >/dev/null) \
    || echo "browser-deps: could not install ${need[*]}; the tests that need them will skip"
else
  echo "browser-deps: no root apt; tests needing ${need[*]} will skip"
fi
