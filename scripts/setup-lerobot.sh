#!/usr/bin/env bash
# Create .venv-lerobot: prop plus lerobot 0.4.4 on the CPU torch wheel, for the LeRobot adapter, the
# LeRobot data source and `pytest -m lerobot`. Kept apart from .venv: never part of the default install
# (.ci/run builds it too, for the LeRobot tests).
#
# Why not `pip install lerobot`: lerobot 0.4.4 pins torch<2.11, and PyPI serves only CUDA builds of torch
# 2.10 for Linux (with ~4.3 GB of nvidia-* wheels and triton: an 8.3 GB environment, measured). So torch
# 2.13.0 (CPU) goes in first, lerobot with --no-deps, torchcodec 0.13.0 (the build for torch 2.13), then
# lerobot's other dependencies. Measured: 70-112 s, 2.8 GB. Video datasets also need the system FFmpeg
# (apt-get install -y ffmpeg); image and state-only datasets do not.
#
# Usage: scripts/setup-lerobot.sh [VENV_DIR]   (default: .venv-lerobot in the repository root)
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${1:-.venv-lerobot}"
PY="${PYTHON:-python3.11}"
. scripts/pip-quiet.sh  # pip_install: pip without the messages this set-up expects (listed there)
drop_draccus_tests() {
  # draccus 0.10.0 (lerobot's config library) installs its own test suite as a top-level package
  # `tests`, which shadows this repository's tests/ under pytest; it is not needed to run draccus.
  local site
  site="$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
  if grep -q '^tests/__init__.py' "$site"/draccus-*.dist-info/RECORD 2>/dev/null; then rm -rf "$site/tests"; fi
}
# prop's own requirements are met by what is installed (torch 2.13 is in its range), so `pip install -e .`
# with dependencies adds only what prop needs beyond lerobot (e.g. cryptography) and never touches torch.
if [ -x "$VENV/bin/python" ] && "$VENV/bin/python" -c "import lerobot, peft, num2words, prop_cli" 2>/dev/null; then
  pip_install "$VENV/bin/pip" -e .
  drop_draccus_tests
  exit 0
fi
start=$(date +%s)
"$PY" -m venv "$VENV"
PIP="$VENV/bin/pip"
pip_install "$PIP" --upgrade "pip>=24"
# torchvision 0.28.0 is the release for torch 2.13 (2.13.0+cpu satisfies its torch==2.13.0).
pip_install "$PIP" "torch==2.13.0" "torchvision==0.28.0"
"$VENV/bin/python" -c 'import torch; assert "+cpu" in torch.__version__, torch.__version__'
# PyPI's torchvision is built against CUDA torch: its C ops do not load under CPU torch, and import then
# fails on the two meta registrations (nms, qnms) that torchvision does not guard with _has_ops().
# Guard them like the others; ACT and Diffusion use only torchvision's Python parts.
TV_META="$("$VENV/bin/python" -c 'import importlib.util as u; print(u.find_spec("torchvision").submodule_search_locations[0])')/_meta_registrations.py"
sed -i -E 's/^@torch\.library\.register_fake\("torchvision::(q?nms)"\)$/@(torch.library.register_fake("torchvision::\1") if torchvision.extension._has_ops() else (lambda f: f))/' "$TV_META"
[ "$(grep -c '_has_ops() else (lambda f: f)' "$TV_META")" = 2 ] || { echo "torchvision patch did not apply" >&2; exit 1; }
pip_install "$PIP" --no-deps "lerobot==0.4.4" "torchcodec==0.13.0"
# lerobot 0.4.4's base requirements (its METADATA) minus torch/torchvision/torchcodec; its `peft` extra
# (peft >=0.18,<1 with transformers >=4.57.1,<5: LeRobot's own pins, which keep huggingface-hub <0.36);
# the simulator for the example and tests (panda-gym); prop itself and its test tools.
pip_install "$PIP" \
  "datasets>=4.0.0,<5.0.0" "diffusers>=0.27.2,<0.36.0" "huggingface-hub[cli,hf-transfer]>=0.34.2,<0.36.0" \
  "accelerate>=1.10.0,<2.0.0" "setuptools>=71.0.0,<81.0.0" "cmake>=3.29.0.1,<4.2.0" "einops>=0.8.0,<0.9.0" \
  "opencv-python-headless>=4.9.0,<4.13.0" "av>=15.0.0,<16.0.0" "jsonlines>=4.0.0,<5.0.0" \
  "packaging>=24.2,<26.0" "pynput>=1.7.7,<1.9.0" "pyserial>=3.5,<4.0" "wandb>=0.24.0,<0.25.0" \
  "draccus==0.10.0" "gymnasium>=1.1.1,<2.0.0" "rerun-sdk>=0.24.0,<0.27.0" "deepdiff>=7.0.1,<9.0.0" \
  "imageio[ffmpeg]>=2.34.0,<3.0.0" "termcolor>=2.4.0,<4.0.0" \
  "safetensors>=0.4" "typer>=0.12" "rich>=13" "panda-gym==3.0.7" "pytest>=8" "ruff>=0.5" \
  "peft>=0.18,<1.0" "transformers>=4.57.1,<5.0.0" "num2words>=0.5.14"
pip_install "$VENV/bin/pip" -e .
drop_draccus_tests
"$VENV/bin/python" - <<'PYEOF'
import lerobot, numpy, torch, torchvision
from lerobot.policies.act.modeling_act import ACTPolicy  # noqa: F401
from lerobot.datasets.lerobot_dataset import LeRobotDataset  # noqa: F401
import prop_cli  # noqa: F401
print(f"ok: torch {torch.__version__}, torchvision {torchvision.__version__}, lerobot {lerobot.__version__}, numpy {numpy.__version__}")
PYEOF
echo "setup-lerobot: $(( $(date +%s) - start )) s, $(du -sh "$VENV" | cut -f1) (lerobot 0.4.4 on CPU torch 2.13: pip's notice that lerobot pins torch<2.11 is expected and not shown)" >&2
