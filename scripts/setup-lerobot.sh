#!/usr/bin/env bash
# Create .venv-lerobot: prop plus lerobot 0.6.x, for the LeRobot adapter, the LeRobot data source and
# `pytest -m lerobot`. Kept apart from .venv: never part of the default install (.ci/run builds it too).
#
# lerobot 0.6 requires Python >= 3.12, so this environment uses the first of $PYTHON, python3.12, pyenv's
# 3.12 builds, python3.13 or pyenv's 3.13 builds that is >= 3.12, and fails in one line if there is none.
# The torch build is lerobot's own pin (torch 2.11, torchvision 0.26), from the package registry through
# pip's resolver (`pip install -e ".[lerobot]"`). Why not the CPU wheel prop's .venv uses: PyPI has no
# CPU-only torch for Linux x86_64 at any version lerobot 0.6 accepts (every manylinux x86_64 wheel needs
# the CUDA 13 nvidia-* wheels), and the CPU wheel on these machines is built for Python 3.11 only. The
# CUDA build runs on the CPU (measured) and is also what a GPU needs. Everything comes as a wheel: nothing
# compiles (issue 38; panda-gym, whose pybullet has none for cp312, is the opt-in `rl` extra, for the
# paper's PandaReach figures only). Times on a 2-core machine in docs/speed.md ("Setting up LeRobot").
# Each step is said before it starts, with roughly how long it takes.
#
# The last step renders one MuJoCo frame off-screen (the tests' camera task, examples/mujoco_reach.py):
# with MUJOCO_GL=egl unless MUJOCO_GL is set (Mesa's EGL renders on the CPU through llvmpipe; osmesa is
# the other CPU choice). If it cannot, the set-up fails in one line naming the Debian packages to install.
#
# PROP_LEROBOT_RAY=1 adds prop's `ray` extra (Ray Serve, for `prop serve-ray` with a LeRobot policy and
# its tests, tests/serve/test_ray_lerobot.py): ray's manylinux wheels for cp312 and their dependencies,
# resolved together with lerobot's pins, nothing compiled (+~25 s and ~0.3 GB on an existing environment,
# measured: docs/serving.md). .ci/run asks for it; without it, those tests are skipped with the reason.
#
# Usage: [PROP_LEROBOT_RAY=1] scripts/setup-lerobot.sh [VENV_DIR]   (default: .venv-lerobot in the
# repository root)
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${1:-.venv-lerobot}"
. scripts/common.sh  # say, timed, pip_install (pip without the messages this set-up expects, listed there)
timed setup-lerobot
find_python() {
  local c root
  root="$(pyenv root 2>/dev/null || echo "$HOME/.pyenv")"
  # 3.12 first: the version lerobot 0.6 is tested on here.
  for c in "${PYTHON:-}" python3.12 "$root"/versions/3.12*/bin/python python3.13 "$root"/versions/3.13*/bin/python; do
    [ -n "$c" ] || continue
    command -v "$c" >/dev/null 2>&1 || continue
    "$c" -c 'import sys; sys.exit(sys.version_info < (3, 12))' 2>/dev/null && { command -v "$c"; return 0; }
  done
  return 1
}
drop_draccus_tests() {
  # draccus (lerobot's config library) installs its own test suite and demos as top-level packages
  # `tests` and `examples`, which shadow this repository's tests/ under pytest and its examples package
  # (`python -m examples.metaworld` run from another folder); neither is needed to run draccus.
  local site
  site="$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
  if grep -q '^tests/__init__.py' "$site"/draccus-*.dist-info/RECORD 2>/dev/null; then rm -rf "$site/tests"; fi
  if grep -q '^examples/demo.py' "$site"/draccus-*.dist-info/RECORD 2>/dev/null; then rm -rf "$site/examples"; fi
}
# lerobot 0.6.1's own pins of torch, numpy and transformers, given on the command line: otherwise pip's
# resolver first fetches the newest torch that prop's own range allows (555 MB, measured on a cold cache)
# before lerobot's metadata sends it back to 2.11.
LEROBOT_PINS=("torch>=2.7,<2.12" "numpy>=2,<2.3" "transformers>=5.4,<5.6")
EXTRAS="lerobot,lerobot-test"
if [ "${PROP_LEROBOT_RAY:-0}" = 1 ]; then EXTRAS="$EXTRAS,ray"; fi
check_ray() {  # fail here, not in the tests
  if [ "${PROP_LEROBOT_RAY:-0}" = 1 ]; then
    "$VENV/bin/python" -c "import ray.serve, prop_cli.serve.ray_app, lerobot"
  fi
}
drop_mujoco_4() {
  # mujoco 4 comes as three distributions (mujoco, mujoco-core, mujoco-studio); pinning mujoco back to 3.x
  # leaves the other two, and then `import mujoco` fails ("libmujoco.so.4.0.0: cannot open").
  if "$VENV/bin/pip" show -q mujoco-core >/dev/null 2>&1; then
    say "setup-lerobot: removing mujoco 4 (metaworld 3.0.0 needs mujoco 3.16; a few seconds)"
    "$VENV/bin/pip" uninstall -y -q mujoco mujoco-core mujoco-studio >/dev/null
  fi
}
check_rendering() {
  say "setup-lerobot: rendering one MuJoCo frame off-screen (MUJOCO_GL=${MUJOCO_GL:-egl}; ~5 s)"
  "$VENV/bin/python" -m examples.mujoco_reach --check-rendering
}
# The prop serve tests' client (tests/serve), unchanged; --no-deps: its metadata pins numpy<2 and dm-tree
# for modules that client never imports (pyproject.toml, `serve`).
install_openpi_client() {
  say "setup-lerobot: installing openpi-client 0.1.2 without its dependencies (a few seconds)"
  pip_install "$VENV/bin/pip" --no-deps "openpi-client==0.1.2"
}
if [ -x "$VENV/bin/python" ] && "$VENV/bin/python" -c "
import sys, lerobot, peft, prop_cli, onnxruntime
assert sys.version_info >= (3, 12) and lerobot.__version__.startswith('0.6')" 2>/dev/null; then
  drop_mujoco_4
  say "setup-lerobot: $VENV has lerobot 0.6; updating prop in it (~30 s; with [ray] the first time: ~25 s more)"
  pip_install "$VENV/bin/pip" -e ".[$EXTRAS]" "${LEROBOT_PINS[@]}"
  say "setup-lerobot: updating the LeRobot policy plugin lerobot_policy_prop (~5 s)"
  pip_install "$VENV/bin/pip" --no-deps -e plugins/lerobot_policy_prop
  install_openpi_client
  drop_draccus_tests
  check_ray
  check_rendering
  exit 0
fi
PY="$(find_python)" || {
  echo "setup-lerobot: lerobot 0.6 needs Python >= 3.12 and none was found (install one, e.g. 'pyenv install 3.12', or set PYTHON=/path/to/python3.12)" >&2
  exit 1
}
say "setup-lerobot: creating $VENV with $PY ($("$PY" -V 2>&1); a few seconds)"
rm -rf "$VENV"  # an older environment (Python 3.11, lerobot 0.4.4) is replaced, not patched
"$PY" -m venv "$VENV"
PIP="$VENV/bin/pip"
say "setup-lerobot: upgrading pip (~10 s)"
pip_install "$PIP" --upgrade "pip>=24"
# pyproject.toml's `lerobot` extra is lerobot[pi,smolvla,peft,diffusion] 0.6.x plus the dataset
# libraries without torchcodec (prop refuses video features, and without FFmpeg torchcodec makes LeRobot
# log a 60-line traceback per dataset); `lerobot-test` adds the simulators (MuJoCo, MetaWorld) and the
# test tools.
say "setup-lerobot: installing prop, lerobot 0.6 and torch 2.11 (about 6 GB: ~2 min with pip's cache warm, longer cold: docs/speed.md)"
pip_install "$PIP" -e ".[$EXTRAS]" "${LEROBOT_PINS[@]}"
# The LeRobot policy plugin (--policy.type=prop in lerobot-eval, lerobot-record, lerobot-rollout): a
# distribution of its own, since LeRobot imports every one named lerobot_policy_*; its dependencies are
# the two just installed.
say "setup-lerobot: installing the LeRobot policy plugin lerobot_policy_prop (~5 s)"
pip_install "$PIP" --no-deps -e plugins/lerobot_policy_prop
install_openpi_client
drop_draccus_tests
say "setup-lerobot: checking that lerobot's policies and prop import (~30 s)"
"$VENV/bin/python" - <<'PYEOF'
import lerobot, numpy, torch, torchvision, transformers
from lerobot.policies.act.modeling_act import ACTPolicy  # noqa: F401
from lerobot.policies.pi0.modeling_pi0 import PI0Policy  # noqa: F401
from lerobot.policies.pi05.modeling_pi05 import PI05Policy  # noqa: F401
from lerobot.datasets.lerobot_dataset import LeRobotDataset  # noqa: F401
import metaworld, mujoco, prop_cli  # noqa: F401
import lerobot_policy_prop  # noqa: F401 - registers --policy.type=prop
print(f"ok: torch {torch.__version__}, torchvision {torchvision.__version__}, lerobot {lerobot.__version__}, "
      f"transformers {transformers.__version__}, numpy {numpy.__version__}")
PYEOF
check_ray
say "setup-lerobot: $VENV takes $(du -sh "$VENV" | cut -f1) (lerobot 0.6 on $("$VENV/bin/python" -V))"
check_rendering
