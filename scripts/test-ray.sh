#!/usr/bin/env bash
# Build (or reuse) .venv-ray and run the prop serve-ray tests (tests/serve/test_ray.py, slow ones
# included): prop with the `ray` extra (Ray Serve 2.60 here), kept apart from .venv so the default install
# and its test environment never pull Ray (~200 MB with its dependencies). .ci/run runs it after the
# default suite. Install ~1 min on a fresh machine; the tests ~1-1.5 min on 2 busy cores (a local Ray
# instance starts twice, ~25-50 s each).
#
# Usage: scripts/test-ray.sh [pytest args]   (PYTHON: the interpreter of the venv; default python3)
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/common.sh  # say, timed, pip_install
timed test-ray
VENV=.venv-ray
TORCH=2.13.0
if [ ! -x "$VENV/bin/python" ]; then
  say "test-ray: creating $VENV with ${PYTHON:-python3} (a few seconds)"
  "${PYTHON:-python3}" -m venv "$VENV"
fi
say "test-ray: installing torch $TORCH, prop with [ray] and the test tools (~1 min on a fresh machine)"
pip_install "$VENV/bin/pip" "torch==$TORCH"
pip_install "$VENV/bin/pip" -e ".[ray]" "pytest>=8"
# openpi-client without its dependencies, as scripts/setup.sh installs it (pyproject.toml, `serve`).
pip_install "$VENV/bin/pip" --no-deps "openpi-client==0.1.2"
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
say "test-ray: pytest tests/serve/test_ray.py, slow tests included (~1-1.5 min on 2 cores)"
"$VENV/bin/python" -m pytest -q -p no:cacheprovider -m "slow or not slow" tests/serve/test_ray.py "$@"
