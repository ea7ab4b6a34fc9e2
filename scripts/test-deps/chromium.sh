#!/bin/sh
# Installs Debian's Chromium for the studio's browser test (tests/service/studio.rs),
# which drives it headless over the DevTools pipe. Does nothing when
# /usr/bin/chromium exists. Needs root (apt-get) when it installs.
set -eu
if [ -x /usr/bin/chromium ]; then
    exit 0
fi
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq chromium >/dev/null
/usr/bin/chromium --version
