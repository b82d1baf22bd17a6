"""Deriving independent, reproducible seeds for every source of randomness in a run."""

from __future__ import annotations

import numpy as np
import torch


def derive_seeds(*key: int, n: int) -> list[int]:
    """`n` independent 32-bit seeds derived from the integer tuple `key` (e.g. (seed, objective))."""
    return [int(s) for s in np.random.SeedSequence(list(key)).generate_state(n)]


def torch_generator(seed: int, device: torch.device | str = "cpu") -> torch.Generator:
    """A torch generator on `device` seeded with `seed`."""
    g = torch.Generator(device=device)
    g.manual_seed(seed)
    return g


def select_device(choice: str) -> torch.device:
    """'auto' -> cuda when available, else cpu; 'cuda' without a GPU is an error."""
    if choice == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if choice == "cuda" and not torch.cuda.is_available():
        from pipeline.params import ParamsError

        raise ParamsError("device = 'cuda' but no CUDA device is available; use 'auto' or 'cpu'")
    return torch.device(choice)
