"""Training that fails loudly: a non-finite loss, Q-value or weight stops the run.

A NaN (or an infinity) in a loss spreads through its gradients into the weights and, left
alone, into every policy, buffer and front written after it, where it shows up much later as a
meaningless result. Every training loop therefore checks what it trains with `check_finite`:
its latest losses and its weights, every CHECK_EVERY updates (the only host-device sync the
check costs, so a GPU run is not synchronised at every step), and always before a checkpoint
is saved and before results are returned, so neither a checkpoint nor an artifact ever holds
a diverged state. Once a weight is NaN it stays NaN (Adam's moments keep it), so a check every
CHECK_EVERY updates finds any divergence at most that many updates after it began; the step a
`TrainingDiverged` names is the one of the check that found it.

The checks only read tensors (`torch.isfinite`): they draw no random number and change no
value, so a run that does not diverge is bitwise the run without them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable, Sequence

import torch
from torch import nn

CHECK_EVERY = 100  # updates (gradient steps) between two checks of a training loop

Named = Sequence[tuple[str, torch.Tensor]]  # (what it is, e.g. "critic loss"; the tensor)


class TrainingDiverged(RuntimeError):
    """Training produced a non-finite value: `what` (a loss or a network's weight, e.g.
    "critic loss", "a critic weight") is `problem` ("NaN" or "infinite") at `unit` `step`
    (the check that found it). `seed`, `objective` and `during` (e.g. "iteration 3, child 1")
    say whose run it was, where the run knows; `stage` and `checkpoint` are added by the stage
    that reports it (`within`). str() is the one line a stage prints."""

    def __init__(
        self,
        what: str,
        problem: str,
        step: int,
        unit: str = "step",
        seed: int | None = None,
        objective: int | Sequence[int] | None = None,
        during: str | None = None,
    ) -> None:
        super().__init__(what)
        self.what, self.problem, self.step, self.unit = what, problem, int(step), unit
        self.seed, self.objective, self.during = seed, objective, during
        self.stage: str | None = None
        self.checkpoint: Path | None = None
        self.kept = False

    def about(
        self, seed: int | None = None, objective: int | Sequence[int] | None = None, during: str | None = None
    ) -> "TrainingDiverged":
        """Fill in whose run it was (what is already known stays); `during` goes in front of
        what the run said. Returns self, to re-raise."""
        self.seed = self.seed if self.seed is not None else seed
        self.objective = self.objective if self.objective is not None else objective
        if during:
            self.during = f"{during}, {self.during}" if self.during else during
        return self

    def within(self, stage: str, checkpoint: str | Path | None = None, kept: bool | None = None) -> "TrainingDiverged":
        """Name the stage, and the checkpoint it keeps progress in (if it has one); `kept`:
        whether that file holds a state of this run (default: whether it exists). It was
        written before the divergence (no diverged state is ever saved) and is left there.
        Returns self, to re-raise."""
        self.stage = stage
        if checkpoint is not None:
            self.checkpoint = Path(checkpoint)
            self.kept = self.checkpoint.is_file() if kept is None else kept
        return self

    def __str__(self) -> str:
        who = [self.stage] if self.stage else []
        if self.seed is not None:
            who.append(f"seed {self.seed}")
        if self.objective is not None:
            obj = self.objective if isinstance(self.objective, int) else ", ".join(map(str, self.objective))
            who.append(f"obj {obj}")
        line = f"{self.what} is {self.problem} at {self.unit} {self.step}"
        if self.during:
            line += f", {self.during}"
        if self.checkpoint is not None:
            line += (
                f" (the last good checkpoint is kept: {self.checkpoint})"
                if self.kept
                else " (no checkpoint had been written yet)"
            )
        return f"{' '.join(who)}: {line}" if who else line


def due(count: int) -> bool:
    """Whether the loop should check after its `count`-th update (every CHECK_EVERY)."""
    return count % CHECK_EVERY == 0


def problem_of(t: torch.Tensor) -> str | None:
    """ "NaN" if `t` holds a NaN, else "infinite" if it holds an infinity, else None."""
    if not t.is_floating_point() and not t.is_complex():
        return None
    if bool(torch.isnan(t).any()):
        return "NaN"
    if bool(torch.isinf(t).any()):
        return "infinite"
    return None


def first_nonfinite(named: Named) -> tuple[str, str] | None:
    """The first (what, problem) of `named` whose tensor is not all finite, else None. One
    host sync for all of them when they are finite (the usual case)."""
    floats = [(what, t.detach()) for what, t in named if t.is_floating_point()]
    devices = {t.device for _, t in floats}
    if all(bool(torch.stack([torch.isfinite(t).all() for _, t in floats if t.device == d]).all()) for d in devices):
        return None
    for what, t in floats:
        p = problem_of(t)
        if p is not None:
            return what, p
    return None


def check_finite(named: Named, step: int, unit: str = "step", **about) -> None:
    """Raise TrainingDiverged (with `about`: seed, objective, during) for the first tensor of
    `named` that is not all finite."""
    bad = first_nonfinite(named)
    if bad is not None:
        raise TrainingDiverged(bad[0], bad[1], step, unit, **about)


def weights(what: str, *modules: nn.Module) -> list[tuple[str, torch.Tensor]]:
    """Every parameter of `modules`, each named `what` (e.g. "a critic weight")."""
    return [(what, p) for m in modules for p in m.parameters()]


def tensors(what: str, values: Iterable[torch.Tensor]) -> list[tuple[str, torch.Tensor]]:
    return [(what, t) for t in values]


def optimizer_state(what: str, opt: torch.optim.Optimizer) -> list[tuple[str, torch.Tensor]]:
    """The moment estimates of `opt` (Adam's exp_avg, exp_avg_sq), each named `what`; step
    counters and other non-float entries are skipped."""
    return [(what, v) for state in opt.state.values() for v in state.values() if torch.is_tensor(v) and v.dim() > 0]
