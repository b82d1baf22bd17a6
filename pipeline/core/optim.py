"""Adam without `torch.optim.Optimizer`'s per-call bookkeeping, for small networks trained one
step at a time (TD3 specialists, post-hoc critics, MAPEX children).

`adam_step(opt)` is `opt.step()` for a fused Adam on a CPU minus the bookkeeping around the
kernel, bit for bit; `clear_grads(opt)` is `opt.zero_grad(set_to_none=True)` minus its profiler
range. `child_adam` builds a child's optimizer: the plain (single-tensor) Adam in fp32, as every
child before the precision switch, and the fused one for bf16 (its kernel is one pass over each
tensor instead of about ten: on a 256-unit actor 0.1 ms a step instead of 0.4; it rounds
differently, so it is used only where nothing earlier exists to stay equal to).
"""

from __future__ import annotations

import torch
import torch.optim.optimizer as torch_optimizer


def adam_step(opt: torch.optim.Optimizer) -> None:
    """opt.step() for the stacked update's fused Adam on a CPU, minus Optimizer.step's per-call
    bookkeeping (hooks, profiler ranges, the dynamo guard, per-parameter state checks and the
    regrouping of tensors by device), which at the quickstart's 64-unit widths cost about a
    tenth of a training step. It makes the calls opt.step() ends in for this case (the step
    counters' increment, then torch._fused_adam_ with the group's hyperparameters), so the
    bits are the same (tests/test_nets_td3.py). Any other case (not fused, not on the CPU,
    capturable, AMSGrad, AdamW, a parameter without a gradient, no state yet) is opt.step()."""
    groups = opt.param_groups
    g = groups[0]
    if (
        len(groups) != 1
        or not g.get("fused")
        or g.get("capturable")
        or g.get("amsgrad")
        or g.get("differentiable")
        or g.get("decoupled_weight_decay")
        or type(opt) is not torch.optim.Adam
        or opt._optimizer_step_pre_hooks
        or opt._optimizer_step_post_hooks
        or getattr(torch_optimizer, "_global_optimizer_pre_hooks", None)
        or getattr(torch_optimizer, "_global_optimizer_post_hooks", None)
    ):
        opt.step()
        return
    params = g["params"]
    states = [opt.state.get(p) for p in params]
    if not all(states) or any(p.grad is None or p.device.type != "cpu" or p.dtype != torch.float32 for p in params):
        opt.step()
        return
    steps = [st["step"] for st in states]
    beta1, beta2 = g["betas"]
    with torch.no_grad():  # as Optimizer.step
        torch._foreach_add_(steps, 1)
        torch._fused_adam_(
            params,
            [p.grad for p in params],
            [st["exp_avg"] for st in states],
            [st["exp_avg_sq"] for st in states],
            [],
            steps,
            amsgrad=False,
            lr=g["lr"],
            beta1=float(beta1),
            beta2=float(beta2),
            weight_decay=g["weight_decay"],
            eps=g["eps"],
            maximize=g["maximize"],
            grad_scale=None,
            found_inf=None,
        )


def clear_grads(opt: torch.optim.Optimizer) -> None:
    """opt.zero_grad(set_to_none=True) without its profiler range."""
    for g in opt.param_groups:
        for p in g["params"]:
            p.grad = None


def child_adam(params, lr: float, precision: str) -> torch.optim.Adam:
    """A MAPEX child's Adam (see the module docstring): fused for bf16, plain for fp32."""
    return torch.optim.Adam(params, lr=lr, fused=True) if precision == "bf16" else torch.optim.Adam(params, lr=lr)
