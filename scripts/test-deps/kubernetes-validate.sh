#!/bin/sh
# Installs kubernetes-validate (PyPI), which validates the Kubernetes
# manifests against the API's schemas with --strict (unknown fields are
# errors; tests/service/deploy.rs). Does nothing when it is on PATH.
set -eu
if command -v kubernetes-validate >/dev/null 2>&1; then
    exit 0
fi
python3 -m pip install --quiet --disable-pip-version-check kubernetes-validate >/dev/null 2>&1 \
    || python3 -m pip install --quiet --disable-pip-version-check --break-system-packages kubernetes-validate
kubernetes-validate --version
