"""The arithmetic precision of training and evaluation: fp32, or bfloat16 where it pays.

Every section that trains or evaluates networks has a `precision` key (`fp32`, `bf16` or
`auto`, beside its `device`; docs/developing.md, "Precision", says why one per section).
A stage resolves it once (`resolve`), computes in what it resolved to and records that in its
provenance record (pipeline/core/provenance.py) and its resume fingerprint.

What bf16 means here (mixed precision, the usual recipe):
- The matmuls of the networks run in bfloat16: the trainable networks' under
  `torch.autocast` (`compute`), which casts their fp32 weights for each forward; frozen
  networks (a child's critics and parents during extraction, a post-hoc fit's target policy,
  the actors evaluated in episodes) are cast to bfloat16 once (`frozen`), not at every step.
- Master weights, optimizer state (Adam's moments), losses, TD targets, advantages, weights
  and every sum stay fp32: the networks return fp32 (pipeline/core/nets.py), so what follows a
  forward pass is fp32 arithmetic.
- `fp32` computes exactly what the code computed before this switch existed, bit for bit.

`auto` is bf16 only where the hardware has bfloat16 arithmetic natively (`native_bf16`: a CPU
with the avx512_bf16 or amx_bf16 flag, or a CUDA device that supports bf16) AND the networks are
wide enough for it to be faster: hidden width >= AUTO_MIN_WIDTH. Below that a step is bound by
per-operation overhead, and bf16's elementwise kernels (slower than fp32's on a CPU) make it
slower (docs/benchmarks.md, "Precision"). Acting in an env (`workload="act"`: the evaluate
stage's episodes, a forward of a few rows per env step) resolves `auto` to fp32 at every width:
measured no faster in bf16. Everywhere else `auto` is fp32.
"""

from __future__ import annotations

import contextlib
import copy
import functools
from pathlib import Path
from typing import Iterator, Literal, TypeVar

import torch
from torch import nn

Precision = Literal["fp32", "bf16"]
PRECISIONS = ("fp32", "bf16", "auto")
# auto: bf16 from this hidden width up, on native-bf16 hardware (docs/benchmarks.md, "Precision":
# on the 2-core Zen 5 a 64-unit TD3 update and child step were slower in bf16, 256-unit ones faster)
AUTO_MIN_WIDTH = 256
NATIVE_CPU_FLAGS = ("avx512_bf16", "amx_bf16")
CPUINFO = Path("/proc/cpuinfo")

M = TypeVar("M", bound=nn.Module)


@functools.lru_cache(maxsize=None)
def cpu_flags(path: Path = CPUINFO) -> frozenset[str]:
    """The CPU's feature flags (the `flags` line of /proc/cpuinfo; empty where there is none)."""
    try:
        for line in path.read_text().splitlines():
            if line.startswith("flags"):
                return frozenset(line.split(":", 1)[1].split())
    except OSError:
        pass
    return frozenset()


def native_bf16(device: torch.device | str) -> bool:
    """Whether `device` has bfloat16 arithmetic in hardware: on a CPU the avx512_bf16 or amx_bf16
    flag, on CUDA `torch.cuda.is_bf16_supported()` (emulation on older GPUs does not count)."""
    device = torch.device(device)
    if device.type == "cuda":
        return bool(torch.cuda.is_available() and torch.cuda.is_bf16_supported(including_emulation=False))
    return any(flag in cpu_flags() for flag in NATIVE_CPU_FLAGS)


def native_flags() -> list[str]:
    """The native-bf16 CPU flags this machine has (for benchmark lines and records)."""
    return [flag for flag in NATIVE_CPU_FLAGS if flag in cpu_flags()]


def resolve(
    requested: str, device: torch.device | str, width: int, workload: Literal["train", "act"] = "train"
) -> Precision:
    """What `precision: requested` computes in on `device` for networks whose widest hidden
    layer is `width`: fp32 and bf16 as asked (bf16 also where it is emulated: slow, but it runs);
    auto as the module docstring says."""
    if requested in ("fp32", "bf16"):
        return requested  # type: ignore[return-value]
    if requested != "auto":
        raise ValueError(f"precision {requested!r}: expected one of {list(PRECISIONS)}")
    if workload == "act":
        return "fp32"
    return "bf16" if native_bf16(device) and width >= AUTO_MIN_WIDTH else "fp32"


def dtype_of(precision: str) -> torch.dtype:
    """The dtype the matmuls of `precision` run in."""
    return torch.bfloat16 if precision == "bf16" else torch.float32


@contextlib.contextmanager
def compute(precision: str, device: torch.device | str) -> Iterator[None]:
    """The region where trainable networks run forward: autocast to bfloat16 for bf16, nothing
    (not even an autocast region) for fp32. The weight-cast cache is off: each weight is used
    once per region here, and CUDA graph capture needs it off."""
    if precision != "bf16":
        yield
        return
    with torch.autocast(torch.device(device).type, dtype=torch.bfloat16, cache_enabled=False):
        yield


def frozen(module: M, precision: str) -> M:
    """A network that is only read (no gradient, no update) in the precision's dtype: for bf16 a
    bfloat16 copy, made once by the caller and reused at every step; for fp32 `module` itself.
    Only the project's own networks (`TAKES_BF16`: Actor, StackedActor, CriticEnsemble) are
    cast; any other module (an imported TorchScript or torch.export policy) is returned as it
    is and computes in fp32."""
    if precision != "bf16" or not getattr(module, "TAKES_BF16", False):
        return module
    if all(p.dtype == torch.bfloat16 for p in module.parameters()):
        return module
    out = copy.deepcopy(module)
    for p in out.parameters():  # the parameters only: buffers (an actor's action bounds) stay fp32
        p.data = p.data.to(torch.bfloat16)
    return out.requires_grad_(False)


def without_fp32(dump: dict) -> dict:
    """A params section as artifacts record it: `precision` left out where it is fp32, so an fp32
    run writes the same bytes as before the key existed (bf16 and auto are recorded)."""
    return {k: v for k, v in dump.items() if not (k == "precision" and v == "fp32")}
