#!/usr/bin/env bash
# Set up (prop alone, no extras), then run the imitation-learning example end to end through the `prop` CLI.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/common.sh  # say, timed
timed demo
bash scripts/setup.sh
. .venv/bin/activate
# One thread: these models are small, and a 2-thread pool stalls when the machine is shared.
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
say "demo: training a base policy, then personalizing it unsealed and sealed (~1 min on 2 cores)"
python -m examples.demo "$@"
