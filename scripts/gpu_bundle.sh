#!/usr/bin/env bash
# Pack what benchmarks/gpu_tracking.sh needs on a lent GPU machine that reaches no package index
# (Python 3.12 there, torch already installed) into two folders of the checkout, each under the
# device tool's 64 MiB per call: .gpuA (the wheels and the first part of warp.so) and .gpuB (the
# rest of warp.so, warp's Python files, the G1 model files, the reference motion). warp-lang's
# wheel alone is 149 MB (warp.so 299 MB unpacked); xz brings warp.so to 81 MB, split in two.
# warp-clang.so (warp's CPU compiler) and mujoco-studio (rendering) are left out: the GPU run
# needs neither.
#
# Usage: bash scripts/gpu_bundle.sh MOTION.npz      (then see benchmarks/gpu_tracking.sh)
set -euo pipefail
cd "$(dirname "$0")/.."
motion=${1:?usage: scripts/gpu_bundle.sh MOTION.npz}
[ -f "$motion" ] || { echo "gpu_bundle: $motion: no such file" >&2; exit 2; }
py=.venv/bin/python
[ -x $py ] || { echo "gpu_bundle: no .venv here (bash scripts/setup_venv.sh)" >&2; exit 2; }
# Built in a temporary folder and moved in at the end: a failure leaves no half-made bundle.
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
A=$tmp/.gpuA B=$tmp/.gpuB
mkdir -p $A/whl $B
grep -qx '/.gpuA/' .git/info/exclude 2>/dev/null || printf '/.gpuA/\n/.gpuB/\n' >> .git/info/exclude
plat=""
for p in manylinux_2_28 manylinux_2_27 manylinux_2_17 manylinux2014 manylinux1 manylinux_2_24 manylinux_2_31 manylinux_2_34; do
  plat="$plat --platform ${p}_x86_64"
done
ver() { $py -m pip show "$1" 2>/dev/null | sed -n 's/^Version: //p'; }
for n in mujoco mujoco-core mujoco-warp rsl-rl-lib tensordict pyvers mink qpsolvers daqp tyro \
         docstring_parser typeguard mcap GitPython gitdb smmap glfw PyOpenGL; do
  v=$(ver "$n"); [ -n "$v" ] || { echo "gpu_bundle: $n is not in .venv" >&2; exit 2; }
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp $plat -d $A/whl "$n==$v"
done
wv=$(ver warp-lang)
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
  --implementation cp $plat -d "$tmp" "warp-lang==$wv"
(cd "$tmp" && unzip -q warp_lang-*.whl && xz -T2 -6 -c warp/bin/warp.so > warp.so.xz \
  && tar --exclude=warp/bin/warp.so --exclude=warp/bin/warp-clang.so --exclude=warp/examples \
       -cJf warp_py.tar.xz warp warp_lang-*.dist-info)
head -c 40000000 "$tmp/warp.so.xz" > $A/warp.so.xz.a
tail -c +40000001 "$tmp/warp.so.xz" > $B/warp.so.xz.b
cp "$tmp/warp_py.tar.xz" $B/
g1=$($py -c "from humimic.robots.assets import envpool_menagerie_root as r; print(r())")
tar -C "$g1" -cf - unitree_g1 | xz -T2 -6 > $B/g1.tar.xz
cp "$motion" $B/motion.npz
rm -rf .gpuA .gpuB && mv $A $B .
du -sh .gpuA .gpuB
