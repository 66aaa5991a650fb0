#!/usr/bin/env bash
# Debian chromium for the browser tests (playwright cannot download its own browser here).
# Skipped quietly where apt is not usable; the browser tests then skip with a reason.
set -u
if [ -x /usr/bin/chromium ]; then exit 0; fi
if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
    || echo "browser-deps: could not install chromium; browser tests will skip"
else
  echo "browser-deps: no root apt; browser tests will skip unless /usr/bin/chromium exists"
fi
