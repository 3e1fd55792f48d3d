#!/usr/bin/env bash
# The whole test suite: lint (ruff), types (pyright), tests (pytest). Sets up .venv itself.
# Extra arguments go to pytest, e.g. `bash scripts/test.sh -m network` for the download tests.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_venv.sh
# The viewer's browser test needs the system's Chromium (Debian package chromium).
if ! command -v chromium >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
  echo "== installing chromium for the browser test (apt-get)"
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium) >/dev/null 2>&1 \
    || echo "   could not install chromium: the browser test will be skipped"
fi
echo "== ruff"
.venv/bin/ruff check src tests benchmarks
.venv/bin/ruff format --check src tests benchmarks
echo "== pyright"
.venv/bin/pyright --project pyproject.toml  # this project's settings, whatever config a parent folder holds
echo "== pytest"
# Two workers (pytest-xdist): 12% faster on the 2-core machine (7:57 -> 6:58), where MuJoCo
# and torch already use both cores part of the time.
# Work stealing: an idle worker takes queued tests from the busy one, so that the long
# diagnosis tests do not end the run on one worker.
# One OpenMP thread per worker: two workers of two spinning torch threads each on two cores
# slowed the residual-network test from 43 s to 156 s.
# The 15 slowest tests are listed at the end: where the 10 minutes go.
if [ $# -eq 0 ]; then set -- -m "not network and not slow" -n 2 --dist worksteal --durations=15; export OMP_NUM_THREADS=1; fi
.venv/bin/python -m pytest -q "$@"
