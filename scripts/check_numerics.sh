#!/usr/bin/env bash
# Run the test suite with this CPU's numerical libraries set to take other code paths, as another x86-64
# machine would: one thread for torch and OpenBLAS, OpenBLAS's AVX kernels without FMA, torch's
# non-vectorised kernels, OpenCV without its AVX/AVX2/FMA paths. A test that passes only with the
# native settings pins one machine's rounding, not what its construction guarantees.
#   scripts/check_numerics.sh [pytest arguments]
set -euo pipefail
cd "$(dirname "$0")/.."
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1
export OPENBLAS_CORETYPE=Sandybridge ATEN_CPU_CAPABILITY=default OPENCV_CPU_DISABLE=AVX,AVX2,FMA3
scripts/setup.sh --dev && .venv/bin/python -m pytest "$@"
