#!/usr/bin/env bash
# Set up, then run the linter and the test suite (a few minutes on 2 cores).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
ruff check .
python -m pytest -q -p no:cacheprovider "$@"
