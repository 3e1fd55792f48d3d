#!/usr/bin/env bash
# Issue 25, "GPU, when one is available": the default tracking recipe against BeyondMimic's on
# MuJoCo Warp at 4096 envs, equal wall time each, on a lent GPU machine. The machine trains only
# (checkpoints come back); the curves and the evaluations run here afterwards on the CPU backend,
# as `humimic eval` always does, with benchmarks/tracking_recipes.py --reuse.
#
# Here: bash scripts/gpu_bundle.sh walk.npz   (packs .gpuA and .gpuB)
# There, call 1 (carry .gpuA):  bash benchmarks/gpu_tracking.sh setup
# There, call 2 (carry .gpuB):  bash benchmarks/gpu_tracking.sh run SECONDS
#   SECONDS: the whole call's budget; each recipe gets min(3 minutes, its share of what the
#   install and the compile warm-up leave).
# Back here (the run folders' config.yaml name /tmp/runs/RECIPE/reference.npz, so unpack there):
#   for r in default beyondmimic; do cat FILES/$r.tar.* | tar -x -C /tmp/runs; done
#   .venv/bin/python benchmarks/tracking_recipes.py --motion walk.npz --out /tmp/runs --reuse ...
set -uo pipefail
site=/tmp/site stash=/root/stash
export PYTHONPATH=$site:$PWD/src PYTHONUNBUFFERED=1 MENAGERIE_ROOT=/tmp/menagerie
out=${OUT:-/tmp/out}; mkdir -p "$out"
dev=${GPU_DEVICE:-cuda} envs=${GPU_ENVS:-4096}  # Overridable for a dry run on a CPU.
case ${1:-} in
setup)
  mkdir -p $stash && cp -r .gpuA/. $stash/ || exit 1
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target $site $stash/whl/*.whl || exit 1
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
  python3 -c "import sys, torch, mujoco, rsl_rl, tensordict, mink; print(sys.version.split()[0], \
torch.__version__, torch.cuda.get_device_name(), 'mujoco', mujoco.__version__)" || exit 1
  python3 -c "import humimic.tracking.train, humimic.tracking.evaluate; print('humimic imports')" || exit 1
  python3 -m humimic.cli.main train --help > /dev/null && echo "humimic train --help: ok"
  touch $stash/installed; ls -la $stash ;;
run)
  budget=${2:-}
  [[ $budget =~ ^[0-9]+$ ]] || { echo "gpu_tracking.sh run SECONDS: a whole number of seconds"; exit 2; }
  [ -f $stash/installed ] || { echo "no stash: run setup first"; exit 1; }
  mkdir -p $site && tar -xJf .gpuB/warp_py.tar.xz -C $site || exit 1
  cat $stash/warp.so.xz.a .gpuB/warp.so.xz.b | xz -d -T0 > $site/warp/bin/warp.so || exit 1
  mkdir -p /tmp/menagerie && tar -xJf .gpuB/g1.tar.xz -C /tmp/menagerie || exit 1
  python3 -c "import warp as wp; wp.init(); print('warp', wp.__version__, wp.get_cuda_device_count(), 'cuda devices')" || exit 1
  runs=/tmp/runs; mkdir -p $runs
  # MJWarp's kernels compile once per machine (warp's kernel cache); a one-iteration run pays
  # that here so neither recipe's budget does.
  w0=$SECONDS
  timeout 300 python3 -m humimic.cli.main train --motion .gpuB/motion.npz --out $runs/warmup \
    --backend warp --device $dev --num-envs $envs --task.action-base default --max-iterations 1 \
    --quiet
  echo "warmup rc $? in $((SECONDS - w0)) s"
  n=2
  for recipe in default beyondmimic; do
    left=$((budget - SECONDS - 40))
    minutes=$(python3 -c "print(round(min(3.0, max(0.5, $left / $n / 60 - 0.3)), 2))")
    echo "== $recipe: $minutes minutes (at $SECONDS s)"
    python3 benchmarks/tracking_recipes.py --motion .gpuB/motion.npz --out $runs \
      --minutes "$minutes" --recipes $recipe --train-only \
      --train-flags="--backend warp --device $dev --num-envs $envs --checkpoint-every 25" \
      | tee -a "$out/train.jsonl"
    n=$((n - 1))
    # Intermediate checkpoints without Adam's moments (a third the size; evaluation loads the
    # optimizer's param groups only); the newest one whole.
    python3 - "$runs/$recipe" <<'PY'
import sys, torch
from pathlib import Path
cks = sorted(Path(sys.argv[1], "checkpoints").glob("model_*.pt"), key=lambda p: int(p.stem[6:]))
for p in cks[:-1]:
    b = torch.load(p, weights_only=False, map_location="cpu")
    b["optimizer_state_dict"] = {"state": {}, "param_groups": b["optimizer_state_dict"]["param_groups"]}
    torch.save(b, p)
PY
    tar -C $runs -cf - --exclude=tensorboard $recipe | split -b 15M -d - "$out/$recipe.tar."
  done
  ls -la "$out" ;;
*) echo "usage: gpu_tracking.sh setup | run SECONDS"; exit 2 ;;
esac
