#!/usr/bin/env bash
# Set up (first time) and run the whole pipeline on the profile in params.yaml: `bash run.sh`.
set -euo pipefail
cd "$(dirname "$0")"
bash scripts/setup.sh
. .venv/bin/activate
dvc repro "$@"
