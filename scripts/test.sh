#!/usr/bin/env bash
# The whole test suite: lint (ruff), types (pyright), tests (pytest). Sets up .venv itself.
# Extra arguments go to pytest, e.g. `bash scripts/test.sh -m network` for the download tests.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_venv.sh
echo "== ruff"
.venv/bin/ruff check src tests benchmarks
.venv/bin/ruff format --check src tests benchmarks
echo "== pyright"
.venv/bin/pyright
echo "== pytest"
if [ $# -eq 0 ]; then set -- -m "not network and not slow"; fi
.venv/bin/python -m pytest -q "$@"
