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
# the runtime closure of pipeline/ and stages/ below torch, numpy, matplotlib and PyYAML, and
# pytest with what tests/conftest.py imports (for the CUDA tests)
PACKAGES="mujoco mujoco-core glfw absl-py etils gymnasium farama-notifications cloudpickle imageio pillow mo-gymnasium pygame
zarr numcodecs donfig google-crc32c cffi pycparser typing-extensions
pydantic pydantic-core annotated-types typing-inspection
pymoo moocore platformdirs autograd cma alive-progress about-time graphemeu dill deprecated wrapt
typer click shellingham rich markdown-it-py mdurl pygments annotated-doc tqdm
pytest pluggy iniconfig packaging hypothesis sortedcontainers ${EXTRA:-}"
mkdir -p "$DEST"
for name in $PACKAGES; do
  version=$($PIP show "$name" 2>/dev/null | awk '/^Version:/{print $2}' || true)
  if [ -z "$version" ]; then
    echo "skip $name: not installed in .venv (so not needed)"; continue
  fi
  $PIP download -q --no-deps --only-binary=:all: --python-version "$PYVER" \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    -d "$DEST" "$name==$version"
done
du -sh "$DEST"
