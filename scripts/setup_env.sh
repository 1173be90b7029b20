#!/usr/bin/env bash
# Creates (or updates) the project's virtual environment in .venv and installs the project
# with its training and test dependencies. Safe to run repeatedly: pip skips what is there.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.installed-$(sha1sum pyproject.toml | cut -c1-12)
if [ ! -f "$stamp" ]; then
  # torch first and pinned: an unpinned resolution pulls several GB of CUDA packages.
  .venv/bin/pip install --disable-pip-version-check -q "torch==2.13.0" 2> >(grep -v "is ignored: it is neither" >&2)
  .venv/bin/pip install --disable-pip-version-check -q -e ".[dev]" 2> >(grep -v "is ignored: it is neither" >&2)
  touch "$stamp"
fi
