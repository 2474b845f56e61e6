#!/usr/bin/env bash
# GPU smoke test: personalize a small MLP on CUDA (unsealed and sealed), run it with and without the key,
# and compare with the same bundle run on the CPU. Skips cleanly (exit 0) where torch sees no CUDA device.
# Uses .venv (scripts/setup.sh); on a GPU machine install a CUDA build of torch there first.
# PROP_SMOKE_DEVICE=cpu runs the same steps on the CPU (to check the script itself).
set -euo pipefail
cd "$(dirname "$0")/.."
. .venv/bin/activate
device=${PROP_SMOKE_DEVICE:-cuda}
if [ "$device" = cuda ] && ! python -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)"; then
  echo "gpu-smoke: skipped: torch sees no CUDA device"
  exit 0
fi
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
python - "$work" <<'PY'
import sys
from pathlib import Path

import numpy as np

from tests.conftest import make_mlp_checkpoint

d = Path(sys.argv[1])
make_mlp_checkpoint(d / "model.safetensors", sizes=(16, 256, 256, 4))
rng = np.random.default_rng(0)
x = rng.uniform(-1, 1, (2000, 16)).astype(np.float32)
np.savez(d / "mine.npz", x=x, y=np.tanh(x[:, :4] * 2).astype(np.float32))
np.save(d / "x.npy", x[:64])
PY
prop keygen "$work/k.bin"
for mode in unsealed sealed; do
  extra=(); [ "$mode" = sealed ] && extra=(--seal)
  prop personalize "$work/model.safetensors" --data "$work/mine.npz" --key-file "$work/k.bin" \
    --out "$work/$mode.prop" --steps 300 --device "$device" "${extra[@]}"
  prop run "$work/$mode.prop" --input "$work/x.npy" --output "$work/$mode-key.npy" --key-file "$work/k.bin"
  prop run "$work/$mode.prop" --input "$work/x.npy" --output "$work/$mode-none.npy"
done
python - "$work" <<'PY'
import sys
from pathlib import Path

import numpy as np

d = Path(sys.argv[1])
for mode in ("unsealed", "sealed"):
    key, none = np.load(d / f"{mode}-key.npy"), np.load(d / f"{mode}-none.npy")
    assert not np.allclose(key, none, atol=1e-3), f"{mode}: the key changes nothing"
    print(f"gpu-smoke: {mode}: key vs no key differ by {np.abs(key - none).mean():.4f} (run on the CPU)")
print("gpu-smoke: passed")
PY
