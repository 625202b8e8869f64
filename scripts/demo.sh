#!/usr/bin/env bash
# Install Locus into .venv and start it with the demo site and simulated devices.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/pip install --quiet --upgrade pip
.venv/bin/pip install --quiet -e .
exec .venv/bin/locus demo "$@"
