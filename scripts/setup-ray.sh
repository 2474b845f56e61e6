#!/usr/bin/env bash
# Create .venv-ray: prop with the `ray` extra (Ray Serve; `prop serve-ray`), pytest and openpi-client, for
# tests/serve/test_ray.py. Kept apart from .venv, so the default install and its test environment never
# pull Ray (~200 MB with its dependencies). torch is pinned first, as scripts/setup.sh does (the CPU wheel
# on these machines, for Python 3.11). Each step is said before it starts, with roughly how long it takes.
#
# Usage: scripts/setup-ray.sh   (PYTHON: the venv's interpreter; default python3)
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/common.sh  # say, timed, pip_install
timed setup-ray
VENV=.venv-ray
TORCH=2.13.0
if [ ! -x "$VENV/bin/python" ]; then
  say "setup-ray: creating $VENV with ${PYTHON:-python3} (a few seconds)"
  "${PYTHON:-python3}" -m venv "$VENV"
fi
say "setup-ray: torch $TORCH (~1 min on a fresh machine; seconds when it is there)"
pip_install "$VENV/bin/pip" "torch==$TORCH"
say "setup-ray: prop with [ray] and pytest (Ray 2.60 is an 80 MB wheel: ~1-2 min on a fresh machine)"
pip_install "$VENV/bin/pip" -e ".[ray]" "pytest>=8"
# openpi-client without its dependencies, as scripts/setup.sh installs it (pyproject.toml, `serve`).
say "setup-ray: openpi-client 0.1.2 without its dependencies (a few seconds)"
pip_install "$VENV/bin/pip" --no-deps "openpi-client==0.1.2"
"$VENV/bin/python" -c "import ray.serve, prop_cli.serve.ray_app"  # fail here, not in the tests
