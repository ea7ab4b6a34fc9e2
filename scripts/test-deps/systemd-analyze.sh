#!/bin/sh
# Installs systemd-analyze, which scores the systemd units' hardening
# (`systemd-analyze security --offline=true`, tests/service/deploy.rs). Debian ships it
# in the `systemd` package; it runs without a running systemd. Does nothing
# when it is on PATH. Needs root (apt-get) when it installs.
#
# Installing `systemd` does not make it the init system (that is
# `systemd-sysv`, not installed here), so a container's PID 1 is untouched;
# --no-install-recommends keeps out the rest (dbus, libpam-systemd, ...).
set -eu
if command -v systemd-analyze >/dev/null 2>&1; then
    exit 0
fi
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq --no-install-recommends systemd >/dev/null
systemd-analyze --version | head -n 1
