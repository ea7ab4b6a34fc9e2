#!/bin/sh
# Installs Debian's python3-openvdb, the independent reader the bake's round
# trip (tests/render/vdb.rs) reads OpenVDB files back with, under the system Python
# (/usr/bin/python3). Does nothing when it imports already. Needs root
# (apt-get) when it installs.
set -eu
if /usr/bin/python3 -c 'import pyopenvdb' >/dev/null 2>&1; then
    exit 0
fi
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq python3-openvdb >/dev/null
/usr/bin/python3 -c 'import pyopenvdb; print("pyopenvdb", pyopenvdb.LIBRARY_VERSION)'
