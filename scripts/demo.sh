#!/usr/bin/env bash
# Install Locus into .venv (the first time, and again when pyproject.toml changes) and start
# it with the demo site and simulated devices. Arguments go to `locus demo` (--port, ...).
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/locus ] || [ pyproject.toml -nt .venv/bin/locus ]; then
  python3 -m venv .venv
  .venv/bin/pip install --quiet --upgrade pip
  .venv/bin/pip install --quiet -e .
  touch .venv/bin/locus
fi
exec .venv/bin/locus demo "$@"
