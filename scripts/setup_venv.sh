#!/usr/bin/env bash
# Create or reuse the virtual environment .venv in the repository root and install humimic.
# torch is pinned in the same pip command as rsl-rl-lib: pip then takes the CPU wheel
# (torch==2.13.0) instead of pulling a multi-GB CUDA build. Every package's version comes from
# constraints.txt, so a new clone gets the set CI tested (scripts/update_constraints.sh renews it).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-}
if [ -z "$PY" ]; then
  for cand in python3.11 python3.12 python3.13 python3; do
    if command -v "$cand" >/dev/null 2>&1 && "$cand" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
      PY=$cand; break
    fi
  done
fi
[ -n "$PY" ] || { echo "setup: Python >= 3.11 is required" >&2; exit 2; }
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $PY"
  "$PY" -m venv .venv
fi
stamp=.venv/.humimic-install-stamp
stubs_stamp=typings/.humimic-stubs-stamp
want=$(cat pyproject.toml constraints.txt scripts/setup_venv.sh | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ] || ! .venv/bin/python -c 'import humimic' 2>/dev/null; then
  echo "setup: installing dependencies into .venv (first run takes a few minutes)"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -c constraints.txt "torch==2.13.0" "rsl-rl-lib==5.5.1" -e ".[dev]"
  echo "$want" > "$stamp"
  rm -f "$stubs_stamp"
fi
# Type stubs for mujoco (compiled, so pyright sees none of MjModel, MjData, mj_*), written from the
# installed module into the git-ignored typings/ (pyright's stubPath) after every install and when
# missing. A partial stub package (PEP 561): pyright reads mujoco's Python modules (rollout, ...)
# from the package itself. pybind11-stubgen writes `...` for the few C++ types it cannot name
# (the element views of model.joint(name) and the like); --ignore-all-errors keeps those quiet.
if [ ! -f "$stubs_stamp" ] || [ "$(cat "$stubs_stamp")" != "$want" ]; then
  echo "setup: writing mujoco type stubs into typings/"
  rm -rf typings/.new
  .venv/bin/python -m pybind11_stubgen --ignore-all-errors --root-suffix=-stubs -o typings/.new mujoco
  printf 'partial\n' > typings/.new/mujoco-stubs/py.typed
  rm -rf typings/mujoco-stubs
  mv typings/.new/mujoco-stubs typings/mujoco-stubs
  rmdir typings/.new
  echo "$want" > "$stubs_stamp"
fi
