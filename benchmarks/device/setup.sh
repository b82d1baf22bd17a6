# Source on the GPU machine, in the repository root, after carrying the wheels of
# benchmarks/device/fetch_wheels.sh:   source benchmarks/device/setup.sh [WHEELS]   (default .whl)
# Installs them into /tmp/site (no index, no deps: the versions are .venv's), puts that and the
# repository on PYTHONPATH (exported, so the tests' subprocesses see it too) and says which
# module is still missing, if any.
WHEELS=${1:-.whl}
[ -d /tmp/site ] || python3 -m pip install -q --no-index --no-deps --target /tmp/site "$WHEELS"/*.whl
export PYTHONPATH=/tmp/site:$PWD${PYTHONPATH:+:$PYTHONPATH}
export PATH=/tmp/site/bin:$PATH
python3 - <<'PY'
import importlib, sys
missing = []
for m in ("torch", "numpy", "yaml", "matplotlib", "scipy", "mujoco", "gymnasium", "mo_gymnasium", "zarr",
          "pydantic", "pymoo", "typer", "tqdm", "pygame", "pytest", "hypothesis", "stable_baselines3"):
    try:
        importlib.import_module(m)
    except Exception as exc:  # noqa: BLE001
        missing.append(f"{m} ({type(exc).__name__}: {exc})")
import torch
print(f"python {sys.version.split()[0]}, torch {torch.__version__}, cuda {torch.cuda.is_available()}",
      torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")
print("missing:", "; ".join(missing) if missing else "nothing")
PY
