#!/usr/bin/env bash
# The test suite's browser (not needed by the pipeline, so run by .ci/run, not by run.sh): a headless Chromium for
# tests/test_mlflow_ui.py and scripts/mlflow_screenshot.py. Idempotent: does nothing when one is there.
set -euo pipefail
# headless Chromium for tests/test_mlflow_ui.py and scripts/mlflow_screenshot.py: Playwright drives the system's browser
# and downloads none. Debian's package when none is there (PIDC_CHROMIUM may name another Chromium instead).
if [ -z "${PIDC_CHROMIUM:-}" ] && ! command -v chromium >/dev/null && ! command -v chromium-browser >/dev/null \
  && ! command -v google-chrome >/dev/null; then
  if [ "$(id -u)" -eq 0 ]; then SUDO=""; elif command -v sudo >/dev/null && sudo -n true 2>/dev/null; then SUDO=sudo
  else SUDO=none; fi
  if command -v apt-get >/dev/null && [ "$SUDO" != none ]; then
    echo "setup.sh: installing Debian's chromium (a headless browser for tests/test_mlflow_ui.py)"
    { $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; } \
      || echo "setup.sh: apt-get install chromium failed: tests/test_mlflow_ui.py will fail until a Chromium is installed" >&2
  else
    echo "setup.sh: no Chromium, and no apt-get to run as root: install Chromium (or set PIDC_CHROMIUM to one);" \
      "tests/test_mlflow_ui.py fails without it" >&2
  fi
fi
