#!/usr/bin/env bash
# Run pytest (PYTHON ARGS...) with PyTorch's, oneDNN's and MKL's kernels forced to their SSE4 code paths,
# which no machine of the project's kind takes by itself (AVX2 or AVX-512 there): outputs stored on one
# machine then differ in their last bits, as they do on another CPU, and a test that compares them bit for
# bit fails here first (issue 41: a fresh AMD EPYC without AVX-512 failed 8 such tests). Usage:
#   scripts/kernel-switch.sh PYTHON PYTEST_ARGS...
set -euo pipefail
py=$1
shift
echo "kernel-switch: the compatibility tests on SSE4 kernels (ATEN_CPU_CAPABILITY=default, ONEDNN_MAX_CPU_ISA=SSE41, MKL_ENABLE_INSTRUCTIONS=SSE4_2)" >&2
export ATEN_CPU_CAPABILITY=default ONEDNN_MAX_CPU_ISA=SSE41 MKL_ENABLE_INSTRUCTIONS=SSE4_2
# A switch that stopped working would make this run pass for nothing: PyTorch must say it took it.
"$py" -c "import torch, sys; c = torch.backends.cpu.get_cpu_capability(); sys.exit(c != 'DEFAULT' and f'kernel-switch: PyTorch still runs {c} kernels')"
"$py" -m pytest -q -p no:cacheprovider "$@"
