"""How far a training step is from the CPU's (or GPU's) arithmetic: shared by bench_extract.py
and bench_specialist.py.

A step's work is counted analytically as the FLOPs of its matrix products (GEMMs): a product of
(m x k) by (k x n) is 2mkn FLOPs, and an MLP layer d_in -> d_out on B rows costs 2 B d_in d_out
forward, as much again for its weight gradient and as much again for its input gradient (the
input gradient of a layer whose input needs none, such as a network's first layer fed by data,
is not computed and not counted). Elementwise work (bias, ReLU, tanh, the loss, Adam) is left
out: it is small in FLOPs, though not in time, which is what the percentage shows.

The floor: the same GEMMs (shapes, transposes, dtype) timed back to back on preallocated
operands in the same run; "% of the matmul rate" = the step's GFLOPS (its GEMM FLOPs over its
time) / the floor's GFLOPS. 100% would be a step that is nothing but its products.

Time is wall time, or with --clock cpu the CPU time of the process (`time.process_time`; with
one torch thread, the time the step had a core): on a machine shared with other jobs the CPU
time is the steadier figure, though it still pays for caches the other jobs evict.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Sequence

import torch

from pipeline.core.precision import dtype_of, native_bf16, native_flags
from pipeline.core.provenance import cpu_model

_CLOCK = {"name": "wall", "now": time.perf_counter}


def set_clock(name: str) -> None:
    """Time with the wall clock ("wall") or the process's CPU time ("cpu")."""
    _CLOCK.update(name=name, now=time.perf_counter if name == "wall" else time.process_time)


def now() -> float:
    return _CLOCK["now"]()


def clock_name() -> str:
    return _CLOCK["name"]


@dataclass(frozen=True)
class Gemm:
    """`batch` products of (m x k) by (k x n); ta / tb: the left / right operand is used
    transposed (a weight-gradient or input-gradient product reads its operand so)."""

    batch: int
    m: int
    k: int
    n: int
    ta: bool = False
    tb: bool = False

    @property
    def flops(self) -> int:
        return 2 * self.batch * self.m * self.k * self.n


def mlp_gemms(
    rows: int, dims: Sequence[int], members: int = 1, forward=True, wgrad=False, xgrad=False, first_xgrad=False
):
    """The GEMMs of an MLP (layer widths dims = [d_0, ..., d_L]) of `members` stacked copies on
    `rows` rows each: forward, and if asked the weight gradients and the input gradients (the
    first layer's only with first_xgrad)."""
    out = []
    for i, (d_in, d_out) in enumerate(zip(dims[:-1], dims[1:])):
        if forward:
            out.append(Gemm(members, rows, d_in, d_out))
        if wgrad:  # dW = x^T dy: (d_in x rows) @ (rows x d_out)
            out.append(Gemm(members, d_in, rows, d_out, ta=True))
        if xgrad and (i > 0 or first_xgrad):  # dx = dy W^T: (rows x d_out) @ (d_out x d_in)
            out.append(Gemm(members, rows, d_out, d_in, tb=True))
    return out


def flops(gemms: Sequence[Gemm]) -> int:
    return sum(g.flops for g in gemms)


def floor_seconds(gemms: Sequence[Gemm], dtype: torch.dtype, device: torch.device, min_time: float = 0.5) -> float:
    """Seconds for one pass of `gemms` back to back (operands and outputs preallocated), the
    median of passes repeated for at least `min_time` seconds after a warm-up."""
    ops = []
    for g in gemms:
        a = (
            torch.randn(g.batch, g.k, g.m, device=device).to(dtype).transpose(1, 2)
            if g.ta
            else torch.randn(g.batch, g.m, g.k, device=device).to(dtype)
        )
        b = (
            torch.randn(g.batch, g.n, g.k, device=device).to(dtype).transpose(1, 2)
            if g.tb
            else torch.randn(g.batch, g.k, g.n, device=device).to(dtype)
        )
        out = torch.empty(g.batch, g.m, g.n, device=device, dtype=dtype)
        ops.append((a, b, out))

    def one_pass() -> None:
        for a, b, out in ops:
            torch.bmm(a, b, out=out)

    for _ in range(5):
        one_pass()
    sync(device)
    times = []
    start = time.perf_counter()
    while time.perf_counter() - start < min_time or len(times) < 10:
        t0 = now()
        one_pass()
        sync(device)
        times.append(now() - t0)
    times.sort()
    return times[len(times) // 2]


def headline_rate(dtype: torch.dtype, device: torch.device) -> float:
    """GFLOPS of one batched matmul at the critics' shape, 4 x (256 x 256) @ (256 x 256)."""
    g = [Gemm(4, 256, 256, 256)]
    return flops(g) / floor_seconds(g, dtype, device) / 1e9


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def machine_lines(device: torch.device) -> list[str]:
    """The machine, its native bfloat16 support, torch and the load: the header of every figure."""
    if device.type == "cuda":
        name = torch.cuda.get_device_name(device)
        bf16 = f"CUDA bf16 {'native' if native_bf16(device) else 'not native'}"
    else:
        name = cpu_model()
        flags = native_flags()
        bf16 = f"native bf16: {'yes (' + ', '.join(flags) + ')' if flags else 'no (neither avx512_bf16 nor amx_bf16)'}"
    cuda = torch.cuda.is_available()
    cuda_bf16 = f"; CUDA {'with' if cuda and native_bf16('cuda') else 'without'} bf16" if cuda else "; no CUDA"
    return [
        f"device {device.type}: {name}; {bf16}{cuda_bf16}",
        f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), {os.cpu_count()} cores, {load()}; "
        f"times below: {clock_name()} clock",
    ]


def load() -> str:
    return "load average {:.2f} {:.2f} {:.2f}".format(*os.getloadavg())


def rate_line(what: str, precision: str, ms: float, step_flops: int, floor_s: float) -> str:
    """One benchmark line: ms per step, achieved GFLOPS, the GEMM floor's rate, the percentage."""
    gflops = step_flops / (ms / 1e3) / 1e9
    floor = step_flops / floor_s / 1e9
    return (
        f"{what} [{precision}]: {ms:.3f} ms/step, {step_flops / 1e6:.1f} MFLOP (GEMMs) -> {gflops:.1f} GFLOPS; "
        f"its GEMMs alone {floor_s * 1e3:.3f} ms ({floor:.1f} GFLOPS): {100 * gflops / floor:.0f}% of the matmul rate"
    )


def precisions(choice: str) -> list[str]:
    return ["fp32", "bf16"] if choice == "both" else [choice]


__all__ = [
    "Gemm",
    "dtype_of",
    "flops",
    "floor_seconds",
    "headline_rate",
    "machine_lines",
    "mlp_gemms",
    "precisions",
    "rate_line",
    "load",
    "now",
    "set_clock",
]
