#!/usr/bin/env bash
# Set up .venv with the CPU build of torch and sgf-pipeline installed editable.
#   scripts/setup.sh          runtime
#   scripts/setup.sh --dev    plus the test, lint and sweep tools and the Rerun viewer SDK
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
TORCH_VERSION=${TORCH_VERSION:-2.13.0}
extras=""
[ "${1:-}" = "--dev" ] && extras="[dev,sweeps,viz]"

[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
pip_install() {
  .venv/bin/python -m pip install -q --disable-pip-version-check "$@" \
    2> >(grep -v "is ignored: it is neither a file nor a directory" >&2)
}

# torch first, and the CPU build: a bare `torch` requirement resolves to a multi-GB CUDA build.
if ! .venv/bin/python -c "import torch" >/dev/null 2>&1; then
  pip_install "torch==${TORCH_VERSION}+cpu" \
    || pip_install "torch==${TORCH_VERSION}" --index-url https://download.pytorch.org/whl/cpu
fi
.venv/bin/python -W ignore::UserWarning -c "import sys, torch; sys.exit(0 if torch.version.cuda is None else \
'a CUDA build of torch is in .venv: remove .venv and run scripts/setup.sh again')"

# Reinstall only when pyproject.toml changed since the last setup with the same extras.
stamp=".venv/.sgf-setup${extras}"
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  pip_install -e ".${extras}"
  touch "$stamp"
fi
