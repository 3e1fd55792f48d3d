#!/usr/bin/env bash
# Re-resolve constraints.txt: install humimic with its dev extras into a fresh temporary venv
# without constraints (so pip picks the newest versions pyproject.toml allows), and write the
# exact versions it got. Then run `bash scripts/test.sh` (it reinstalls .venv from the new file)
# and commit constraints.txt only if the suite passes.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
"$PY" -m venv "$tmp/venv"
"$tmp/venv/bin/python" -m pip install -q --upgrade pip
"$tmp/venv/bin/python" -m pip install -q "torch==2.13.0" "rsl-rl-lib==5.5.1" -e ".[dev]"
{
  echo "# Exact versions of every package the .venv gets (scripts/setup_venv.sh installs with -c)."
  echo "# Regenerate with: bash scripts/update_constraints.sh (a fresh venv, newest allowed versions,"
  echo "# then the whole test suite on them before committing the new file)."
  # The local CPU wheel's version carries +cpu; the constraint names the release.
  "$tmp/venv/bin/python" -m pip freeze --exclude-editable | sed -E 's/^torch==([0-9.]+)\+cpu$/torch==\1/'
} > constraints.txt.new
mv constraints.txt.new constraints.txt
echo "wrote constraints.txt ($(grep -vc '^#' constraints.txt) packages); now run: bash scripts/test.sh"
