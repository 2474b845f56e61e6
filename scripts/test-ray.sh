#!/usr/bin/env bash
# Build (or reuse) .venv-ray (scripts/setup-ray.sh) and run the prop serve-ray tests,
# tests/serve/test_ray.py, slow ones included. .ci/run runs it after the LeRobot tests. Measured on the
# 2-core shared machine: set-up ~3 min fresh, the tests ~1.5-2 min (a local Ray instance starts twice).
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/common.sh  # say, timed
timed test-ray
bash scripts/setup-ray.sh
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
say "test-ray: pytest tests/serve/test_ray.py, slow tests included (~1.5-2 min on 2 cores)"
.venv-ray/bin/python -m pytest -q -p no:cacheprovider -m "slow or not slow" tests/serve/test_ray.py "$@"
