#!/usr/bin/env bash
# The whole test suite, in the project's own virtual environment (created if missing).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh
exec .venv/bin/python -m pytest -q -p no:cacheprovider "$@"
