#!/usr/bin/env bash
# Create .venv (if missing) and install prop, with the extras named in $1 (comma-separated, e.g.
# "test" or "test,rl"; none: prop alone, what the demo needs).
# torch is pinned first: it takes the CPU wheel on these machines, and prop's own range (>=2.2,<3)
# is then already satisfied, so pip pulls no CUDA packages.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
EXTRAS=${1:-}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
. .venv/bin/activate
. scripts/pip-quiet.sh
pip_install .venv/bin/pip "torch==2.13.0"
pip_install .venv/bin/pip -e ".${EXTRAS:+[$EXTRAS]}"
python -c "import torch, prop_cli" # fail here, not later, if the install did not work
