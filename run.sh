#!/usr/bin/env bash
# Set up (first time) and run the whole pipeline on the profile in params.yaml: `bash run.sh`.
# Extra arguments go to `dvc repro` (e.g. `bash run.sh generate`, `bash run.sh --force`).
#
# Unless PREFECT_API_URL already points at a Prefect server, one local server (state in .prefect/)
# runs for the duration of the pipeline, so the stages do not each start a temporary one.
set -euo pipefail
cd "$(dirname "$0")"
bash scripts/setup.sh
. .venv/bin/activate
export PREFECT_HOME="${PREFECT_HOME:-$PWD/.prefect}" PREFECT_SERVER_ANALYTICS_ENABLED=false DO_NOT_TRACK=1
if [ -z "${PREFECT_API_URL:-}" ]; then
  port="${PIDC_PREFECT_PORT:-4200}"
  url="http://127.0.0.1:$port/api"
  if ! python -c "import urllib.request,sys; urllib.request.urlopen('$url/health', timeout=2)" 2>/dev/null; then
    mkdir -p "$PREFECT_HOME"
    prefect server start --host 127.0.0.1 --port "$port" >"$PREFECT_HOME/server.log" 2>&1 &
    server=$!
    trap 'kill $server 2>/dev/null; wait $server 2>/dev/null || true' EXIT
    for _ in $(seq 120); do
      python -c "import urllib.request; urllib.request.urlopen('$url/health', timeout=2)" 2>/dev/null && break
      kill -0 $server 2>/dev/null || { echo "the Prefect server failed to start; see $PREFECT_HOME/server.log" >&2; exit 1; }
      sleep 1
    done
  fi
  export PREFECT_API_URL="$url"
  echo "Prefect API: $url (UI: http://127.0.0.1:$port)"
fi
dvc repro "$@"
