#!/usr/bin/env bash
# Download, on this machine, the wheels a bare GPU machine lacks for the CUDA checks and
# benchmarks, at exactly the versions installed in .venv, for the GPU machine's Python.
#
#   bash benchmarks/device/fetch_wheels.sh [DEST] [PYTHON_VERSION]     (default .whl, 3.12)
#
# The GPU machines lent to this project run python3.12 with a CUDA torch, but without mujoco,
# gymnasium, mo-gymnasium, zarr, pydantic or pymoo, and reach no package index. Carry DEST to the
# machine (git-ignored; 64 MiB at most) and run benchmarks/device/setup.sh there. torch is never
# downloaded (the machine's CUDA build is used), nor mujoco-studio (not needed headless).
# EXTRA="numpy scipy ..." adds packages if the machine turns out to lack them (setup.sh says).
set -euo pipefail
cd "$(dirname "$0")/../.."
DEST=${1:-.whl}
PYVER=${2:-3.12}
PIP=${PIP:-.venv/bin/pip}
# The runtime closure of pipeline/ and stages/ that the lent GPU machines' image lacks (the
# library's device/KINDS.md lists what it holds: numpy, scipy, matplotlib, pandas, pillow,
# imageio, PyYAML, tqdm, rich, pytest, hypothesis, ... are there). typer and click are carried
# anyway (small, and the CLI depends on their behaviour), and stable-baselines3 for
# bench_specialist.py's comparison (pandas, its one import beyond ours, is there).
PACKAGES="mujoco mujoco-core glfw gymnasium farama-notifications mo-gymnasium pygame
zarr numcodecs donfig google-crc32c cffi pycparser
pydantic pydantic-core annotated-types typing-inspection
pymoo moocore platformdirs autograd cma alive-progress about-time graphemeu deprecated
typer click ${EXTRA:-}"
SB3_VERSION=${SB3_VERSION:-2.9.2}   # when .venv has none (pip install -e ".[bench]" gives one)
fetch() {
  $PIP download -q --no-deps --only-binary=:all: --python-version "$PYVER" --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 -d "$DEST" "$1==$2"
}
mkdir -p "$DEST"
for name in $PACKAGES; do
  version=$($PIP show "$name" 2>/dev/null | awk '/^Version:/{print $2}' || true)
  if [ -z "$version" ]; then
    echo "skip $name: not installed in .venv (so not needed)"; continue
  fi
  fetch "$name" "$version"
done
sb3=$($PIP show stable-baselines3 2>/dev/null | awk '/^Version:/{print $2}' || true)
fetch stable-baselines3 "${sb3:-$SB3_VERSION}"
du -sh "$DEST"
