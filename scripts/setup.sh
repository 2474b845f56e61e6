#!/usr/bin/env bash
# Create .venv (if missing) and install prop, with the extras named in $1 (comma-separated, e.g.
# "test" or "test,rl"; none: prop alone, what the demo needs). Says each step before it starts, with
# roughly how long it takes (docs/speed.md), and the total at the end.
# torch is pinned first: it takes the CPU wheel on these machines, and prop's own range (>=2.2,<3)
# is then already satisfied, so pip pulls no CUDA packages.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/common.sh  # say, timed, pip_install
timed setup
PY=${PYTHON:-python3}
EXTRAS=${1:-}
TORCH=2.13.0
if [ ! -x .venv/bin/python ]; then
  say "setup: creating .venv with $PY ($("$PY" -V 2>&1); a few seconds)"
  "$PY" -m venv .venv
fi
. .venv/bin/activate
# Reads the installed versions without importing anything (importing torch takes seconds).
installed() { python -c "from importlib.metadata import version; print(version('$1').split('+')[0])" 2>/dev/null || true; }
if [ "$(installed torch)" != "$TORCH" ]; then
  say "setup: installing torch $TORCH (the largest step, about 190 MB: ~1 min on a fresh machine)"
  pip_install .venv/bin/pip "torch==$TORCH"
fi
if [ -n "$(installed prop-keys)" ]; then
  say "setup: updating prop in .venv${EXTRAS:+ with [$EXTRAS]} (~10 s when no new package is needed)"
elif [ -n "$EXTRAS" ]; then
  say "setup: installing prop with [$EXTRAS] and its dependencies (~1 min on a fresh machine)"
else
  say "setup: installing prop and its dependencies (~20 s on a fresh machine)"
fi
pip_install .venv/bin/pip -e ".${EXTRAS:+[$EXTRAS]}"
if [[ ",$EXTRAS," == *,test,* ]]; then
  # The prop serve tests connect with openpi-client's WebsocketClientPolicy, unchanged. --no-deps: its
  # metadata pins numpy<2 and dm-tree for modules that client never imports (pyproject.toml, `serve`).
  say "setup: installing openpi-client 0.1.2 without its dependencies (a few seconds)"
  pip_install .venv/bin/pip --no-deps "openpi-client==0.1.2"
fi
python -c "import torch, prop_cli" # fail here, not later, if the install did not work
