"""The state of stacked TD3 networks under training, for checkpoints and finiteness checks:
networks and optimizers (`nets_state`, `load_nets_state`), the replay buffer (`buffer_state`,
`check_buffer_state`, `load_buffer_state`), and what `check_finite` looks at (`finite_named`,
`diverged_specialist`). Shared by the lockstep specialists (pipeline/specialists/td3_training.py)
and the TD3 agent of PDERL and MOPDERL (pipeline/specialists/td3_learner.py)."""

from __future__ import annotations

from typing import Any

import torch

from pipeline.core.buffer import StackedReplay
from pipeline.core.checkpoint import cpu_copy
from pipeline.core.finite import first_nonfinite, optimizer_state, weights
from pipeline.specialists.td3 import StackedTD3, Updater


def _copy_optimizer_state_(opt: torch.optim.Optimizer, saved: dict[str, Any]) -> None:
    """Copy a saved optimizer state into `opt`'s existing state tensors, in place (captured
    CUDA graphs read those very tensors, so load_state_dict, which replaces them, cannot be used)."""
    params = [p for group in opt.param_groups for p in group["params"]]
    if sorted(saved["state"]) != list(range(len(params))):
        raise ValueError(f"optimizer state for {len(saved['state'])} parameters, the optimizer has {len(params)}")
    with torch.no_grad():
        for i, p in enumerate(params):
            for key, value in saved["state"][i].items():
                opt.state[p][key].copy_(value)


def nets_state(st: StackedTD3) -> dict[str, Any]:
    """The networks and optimizers of a stacked set, as CPU tensors."""
    return cpu_copy(
        {
            "actor": st.actor.state_dict(),
            "actor_target": st.actor_target.state_dict(),
            "critic": st.critic.state_dict(),
            "critic_target": st.critic_target.state_dict(),
            "actor_opt": st.actor_opt.state_dict(),
            "critic_opt": st.critic_opt.state_dict(),
        }
    )


def load_nets_state(update: Updater, nets: dict[str, Any], n_updates: int) -> None:
    """Restore `nets_state` into the networks `update` trains (fresh, never updated)."""
    st = update.state
    for name in ("actor", "actor_target", "critic", "critic_target"):
        getattr(st, name).load_state_dict(nets[name])
    if update.graphs and n_updates > 0:
        # The captured graphs read the optimizers' own state tensors: capture them now (on
        # fresh optimizers, with the restored networks and buffer), then fill those tensors in
        # place.
        update.graph()
        _copy_optimizer_state_(st.actor_opt, nets["actor_opt"])
        _copy_optimizer_state_(st.critic_opt, nets["critic_opt"])
    else:
        for opt, saved in ((st.actor_opt, nets["actor_opt"]), (st.critic_opt, nets["critic_opt"])):
            # load_state_dict also takes the saved param-group flags: keep this optimizer's
            # capturable/fused (a state saved eagerly may be resumed under CUDA graphs)
            flags = [{k: g[k] for k in ("capturable", "fused") if k in g} for g in opt.param_groups]
            opt.load_state_dict(saved)
            for g, f in zip(opt.param_groups, flags):
                g.update(f)


def buffer_state(b: StackedReplay) -> dict[str, Any]:
    """A StackedReplay's rows and pointers as CPU tensors. The rows are not copied when a full
    ring already lies on the CPU: they are the live ring, so save (or copy) the state before
    the next row is added."""
    size = b.size
    if size == b.capacity and b.rows.device.type == "cpu":
        rows, host = b.rows.detach(), {k: torch.from_numpy(v) for k, v in b.host.items()}
    else:  # the rows written so far, copied to the CPU
        rows = b.rows[:, :size].to("cpu", copy=True)
        host = {k: torch.from_numpy(v[:, :size].copy()) for k, v in b.host.items()}
    return {"capacity": b.capacity, "ptr": b.ptr, "size": size, "rows": rows, **host}


def check_buffer_state(b: StackedReplay, saved: dict[str, Any]) -> None:
    """ValueError unless `saved` (a `buffer_state`) fits buffer `b`."""
    if saved["capacity"] != b.capacity:
        raise ValueError(f"state's buffer capacity {saved['capacity']} != {b.capacity}")
    size = saved["size"]
    if tuple(saved["rows"].shape) != (b.n, size, b.rows.shape[2]) or not 0 <= saved["ptr"] < b.capacity:
        raise ValueError(
            f"state's buffer rows {tuple(saved['rows'].shape)} do not fit ({b.n}, {size}, {b.rows.shape[2]})"
        )


def load_buffer_state(b: StackedReplay, saved: dict[str, Any]) -> None:
    """Restore a `buffer_state` (checked by `check_buffer_state`) into `b`."""
    size = int(saved["size"])
    with torch.no_grad():
        b.rows[:, :size].copy_(saved["rows"])
    for k, v in b.host.items():
        v[:, :size] = saved[k].numpy()
    b.ptr, b.size = int(saved["ptr"]), size


def finite_named(update: Updater, full: bool) -> list[tuple[str, torch.Tensor]]:
    """What `check_finite` looks at in stacked networks under training: the latest losses
    (eager updates; Q-values enter both, so a non-finite Q-value shows there) and the online
    weights; with `full` (before a checkpoint or the results) also the target networks, the
    optimizers' moments and the replay buffer rows."""
    st, b = update.state, update.buffer
    named = [(name.replace("_", " "), v) for name, v in update.metrics.items()]  # "critic loss", "actor loss"
    named += weights("a critic weight", st.critic) + weights("an actor weight", st.actor)
    if full:
        named += weights("a target critic weight", st.critic_target)
        named += weights("a target actor weight", st.actor_target)
        named += optimizer_state("a critic optimizer moment", st.critic_opt)
        named += optimizer_state("an actor optimizer moment", st.actor_opt)
        named.append(("a replay buffer value", b.rows[:, : b.size]))
    return named


def diverged_specialist(update: Updater) -> int | None:
    """The first specialist s of a stacked set whose networks, optimizer moments or replay
    buffer hold a non-finite value, else None (only called once a check has failed)."""
    st, b = update.state, update.buffer
    e = st.critic.n_members // st.n

    def moments(opt) -> list[torch.Tensor]:
        return [v for state in opt.state.values() for v in state.values() if torch.is_tensor(v) and v.dim() > 0]

    for s in range(st.n):
        parts = [p[s * e : (s + 1) * e] for m in (st.critic, st.critic_target) for p in m.parameters()]
        parts += [v[s * e : (s + 1) * e] for v in moments(st.critic_opt)]
        parts += [p[s] for m in (st.actor, st.actor_target) for p in m.parameters()]
        parts += [v[s] for v in moments(st.actor_opt)]
        parts.append(b.rows[s, : b.size])
        if first_nonfinite([("", t) for t in parts]) is not None:
            return s
    return None
