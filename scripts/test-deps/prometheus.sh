#!/bin/sh
# Installs Debian's Prometheus for the metrics tests (tests/service/limits.rs): its
# `promtool check metrics` lints the service's `/metrics`, and its server
# scrapes the service on loopback. Does nothing when both are on PATH.
# Needs root (apt-get) when it installs.
set -eu
if command -v promtool >/dev/null 2>&1 && command -v prometheus >/dev/null 2>&1; then
    exit 0
fi
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq --no-install-recommends prometheus >/dev/null
promtool --version
