#!/usr/bin/env bash
# Create .venv and install pidc with every extra, at the exact versions of constraints.txt (the rendered data depend on
# them). Idempotent: a second run only checks. The installs are skipped while .venv/.pidc-setup holds the sha256 of
# pyproject.toml, constraints.txt and this script (the editable install follows the code).
# torch 2.13.0 first: that exact pin is the registry's CPU build (~200 MB); anything else pulls CUDA (~3.5 GB).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
. .venv/bin/activate
export PIP_DISABLE_PIP_VERSION_CHECK=1
# pip's exit status is kept (pipefail); only the noise of unused local index folders is dropped
pipq() { python -m pip "$@" 2>&1 | { grep -v "^WARNING: Location" || true; }; }
stamp=$(cat pyproject.toml constraints.txt scripts/setup.sh | sha256sum | cut -d' ' -f1)
if [ "$(cat .venv/.pidc-setup 2>/dev/null)" != "$stamp" ]; then
  pipq install -q --upgrade pip
  pipq install -q -c constraints.txt "torch==2.13.0"
  # the rest with uv, at the same exact versions: ~10 s where pip takes ~3 min (an identical `pip freeze`)
  pipq install -q -c constraints.txt uv
  uv pip install -q --python .venv/bin/python -c constraints.txt -e ".[test,carla,pretrained,docs]"
  python -m pip check
  echo "$stamp" > .venv/.pidc-setup
fi
# torch.compile (the long trainings, train.compile_min_steps) builds C++ kernels with g++ (or $CXX): Debian's g++ when
# none is there and apt-get can run as root; otherwise a warning naming the setting that trains without it
if ! command -v "${CXX:-g++}" >/dev/null; then
  if [ "$(id -u)" -eq 0 ]; then SUDO=""; elif command -v sudo >/dev/null && sudo -n true 2>/dev/null; then SUDO=sudo
  else SUDO=none; fi
  if command -v apt-get >/dev/null && [ "$SUDO" != none ]; then
    echo "setup.sh: installing Debian's g++ (torch.compile's C++ kernels for the long trainings)"
    { $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq g++ >/dev/null; } \
      || echo "setup.sh: apt-get install g++ failed" >&2
  fi
  command -v "${CXX:-g++}" >/dev/null || echo "setup.sh: no C++ compiler (g++ or \$CXX): the train stage fails on" \
    "models it compiles; install one or set train.compile_min_steps: null in params.yaml" >&2
fi
python -c "import torch, prefect, mlflow, dvc, zuko, cvxpy, onnxruntime, cv2, components; print('pidc', components.__version__, '| torch', torch.__version__, '| prefect', prefect.__version__)"
