#!/usr/bin/env bash
# The README's two commands in a new clone of this repository's HEAD with a new virtual
# environment (from constraints.txt): what a new user gets. Uses ../shared/data beside the
# clone the way CI does (a link), and the network for the demo's download.
# Usage: bash scripts/check_fresh_clone.sh [--tests-only]
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
git clone -q "$root" "$tmp/x"
if [ -d "$root/../shared" ]; then ln -s "$(cd "$root/../shared" && pwd)" "$tmp/shared"; fi
cd "$tmp/x"
if [ "${1:-}" != "--tests-only" ]; then
  echo "== README command 1: bash scripts/setup_venv.sh && .venv/bin/humimic demo"
  bash scripts/setup_venv.sh && .venv/bin/humimic demo --quiet --out "$tmp/demo" >"$tmp/demo.log"
  tail -n 3 "$tmp/demo.log"
fi
echo "== README command 2: bash scripts/test.sh"
bash scripts/test.sh
