#!/usr/bin/env bash
# Install everything (scripts/setup.sh) and run the whole test suite (what CI runs).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
scripts/setup.sh
export OMP_WAIT_POLICY=PASSIVE
# A plain `pytest` runs the fast tests only (pyproject.toml); this runs every test: sim, slow and browser too.
exec .venv/bin/python -m pytest -q -m "slow or not slow" "$@"
