#!/usr/bin/env bash
# Build (or reuse) .venv-lerobot and run the LeRobot tests: pytest -m lerobot. .ci/run runs it after the
# default suite, with PROP_LEROBOT_RAY=1 (scripts/setup-lerobot.sh then adds the `ray` extra, and
# tests/serve/test_ray_lerobot.py, `prop serve-ray` with a LeRobot ACT, runs instead of being skipped).
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/common.sh  # say, timed
timed test-lerobot
bash scripts/setup-lerobot.sh
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} HF_HUB_OFFLINE=1
say "test-lerobot: pytest -m lerobot (~5-13 min on 2 cores)"
.venv-lerobot/bin/python -m pytest -q -p no:cacheprovider -m lerobot "$@"
# The LeRobot compatibility tests again on other CPU kernels (issue 41; scripts/kernel-switch.sh).
if [ $# -eq 0 ]; then
  bash scripts/kernel-switch.sh .venv-lerobot/bin/python -m lerobot tests/adapters/test_lerobot_old_bundles.py
fi
