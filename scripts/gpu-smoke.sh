#!/usr/bin/env bash
# GPU smoke test: personalize a small MLP on CUDA (unsealed and sealed, --precision fp32 and bf16), run
# each bundle on the CPU with and without the key, and check the key changes the outputs. Skips cleanly
# (exit 0) where torch sees no CUDA device.
# Uses .venv (scripts/setup.sh); on a GPU machine install a CUDA build of torch there first, or set
# PROP_SMOKE_PYTHON to a python that has torch and prop's dependencies (prop then runs from this source
# tree as `python -m prop_cli.cli.main`, no install needed).
# PROP_SMOKE_DEVICE=cpu runs the same steps on the CPU (to check the script itself).
# PROP_SMOKE_STEPS (default 300): training steps per personalize.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ -n "${PROP_SMOKE_PYTHON:-}" ]; then
  py=$PROP_SMOKE_PYTHON
  prop() { "$py" -m prop_cli.cli.main "$@"; }
else
  . .venv/bin/activate
  py=python
fi
device=${PROP_SMOKE_DEVICE:-cuda}
steps=${PROP_SMOKE_STEPS:-300}
if [ "$device" = cuda ] && ! "$py" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)"; then
  echo "gpu-smoke: skipped: torch sees no CUDA device"
  exit 0
fi
"$py" -c "import torch; print('gpu-smoke: torch', torch.__version__, 'on', \
torch.cuda.get_device_name() if '$device'.startswith('cuda') else 'the CPU')"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
"$py" - "$work" <<'PY'
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
runs=()
for precision in fp32 bf16; do
  for mode in unsealed sealed; do
    extra=(); [ "$mode" = sealed ] && extra=(--seal)
    name=$mode-$precision
    runs+=("$name")
    prop personalize "$work/model.safetensors" --data "$work/mine.npz" --key-file "$work/k.bin" \
      --out "$work/$name.prop" --steps "$steps" --device "$device" --precision "$precision" --json \
      "${extra[@]}" >"$work/$name.json" 2>"$work/$name.log" || { cat "$work/$name.log"; exit 1; }
    # `prop run` computes on the CPU: a bundle trained on the GPU must run there.
    prop run "$work/$name.prop" --input "$work/x.npy" --output "$work/$name-key.npy" --key-file "$work/k.bin"
    prop run "$work/$name.prop" --input "$work/x.npy" --output "$work/$name-none.npy"
  done
done
"$py" - "$work" "$steps" "${runs[@]}" <<'PY'
import json
import re
import sys
from pathlib import Path

import numpy as np
from safetensors.torch import load_file

d, steps = Path(sys.argv[1]), int(sys.argv[2])
dtypes = {v.dtype for v in load_file(d / "model.safetensors").values()}
for name in sys.argv[3:]:
    precision = name.split("-")[1]
    key, none = np.load(d / f"{name}-key.npy"), np.load(d / f"{name}-none.npy")
    assert not np.allclose(key, none, atol=1e-3), f"{name}: the key changes nothing"
    manifest = json.loads((d / f"{name}.prop" / "manifest.json").read_text())
    assert manifest["config"]["precision"] == precision, manifest["config"]
    assert {v.dtype for v in load_file(d / f"{name}.prop" / "base.safetensors").values()} == dtypes
    report = json.loads((d / f"{name}.json").read_text())["metrics"][0]
    took = re.findall(rf"step {steps}/{steps} \(([0-9.]+) s\)", (d / f"{name}.log").read_text())
    print(
        f"gpu-smoke: {name}: personalization {report['personalization']:.4f}, {steps} steps in "
        f"{took[-1] if took else '?'} s; run on the CPU: key vs no key differ by {np.abs(key - none).mean():.4f}"
    )
print("gpu-smoke: passed")
PY
