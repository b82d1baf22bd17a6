"""Print the environment that makes this machine compute with other kernels than its own, as
shell assignments for `make test-kernels` (Makefile): an OpenBLAS core type this CPU does not
pick, and, where the CPU has AVX-512, torch's (ATen's, MKL's, oneDNN's) AVX2 code paths.

A test that compares two different float computations bit for bit passes on the machine it
was written on and fails on a CPU of another generation; run under these kernels, it fails on
the developer's own machine first. Every choice below runs on any x86-64 CPU that has the
kernels the machine picked: a machine that picks an AVX-512 OpenBLAS kernel gets Haswell
(AVX2), one that picks an AVX2 or older kernel gets Prescott (SSE3)."""

from __future__ import annotations

import numpy as np  # noqa: F401  (loads OpenBLAS, so threadpoolctl can read its core type)
import torch
from threadpoolctl import threadpool_info

AVX512_KERNELS = {"skylakex", "cooperlake", "sapphirerapids", "zen4", "zen5"}


def main() -> None:
    picked = [i.get("architecture") or "" for i in threadpool_info() if i.get("internal_api") == "openblas"]
    own = picked[0] if picked else ""
    other = "Haswell" if own.lower() in AVX512_KERNELS else "Prescott"
    env = {"OPENBLAS_CORETYPE": other}
    if torch.backends.cpu.get_cpu_capability().startswith("AVX512"):
        env |= {"ATEN_CPU_CAPABILITY": "avx2", "MKL_ENABLE_INSTRUCTIONS": "AVX2", "ONEDNN_MAX_CPU_ISA": "AVX2"}
    print(" ".join(f"{k}={v}" for k, v in env.items()))


if __name__ == "__main__":
    main()
