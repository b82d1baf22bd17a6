"""Policy and critics artifacts (torch files loadable with `torch.load(weights_only=True)`).

policy.pt  (format "mapex.policy", version 1)
    meta:          env_id, obs_dim, act_dim, n_objectives, action_low, action_high,
                   hidden_sizes, objective (the specialist's objective, or None for a child), seed, params;
                   an imported policy also architecture ("mlp", "normalized_mlp", "torchscript" or
                   "torch_export") and source (docs/import_export.md)
    actor:         state dict of `nets.Actor` (of `nets.NormalizedActor` where architecture is
                   "normalized_mlp", of `nets.ScriptedActor` where it is "torchscript", of
                   `nets.ExportedActor` where it is "torch_export")
    actor_target:  state dict of the TD3 target actor (absent for extracted children)

critics.pt (format "mapex.critics", version 1)
    meta:          env_id, obs_dim, act_dim, n_objectives, hidden_sizes, seed, params,
                   buffer_objective  k: the specialist whose buffer D_k the critics were trained on,
                   objectives        [m, ...]: the objectives covered, in member order,
                   source            "joint" (trained with the specialist) or "posthoc" (fitted offline)
    online:        state dict of `nets.CriticEnsemble` with 2 * len(objectives) members
    target:        state dict of its target copy

Member 2*j + h of the ensemble is head h of objective meta["objectives"][j]. Jointly trained
and post-hoc critics use exactly this format, so extraction loads either with `load_critics`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from pipeline.core.artifacts import ArtifactError, torch_load_checked, torch_save_atomic
from pipeline.core.nets import Actor, CriticEnsemble, ExportedActor, NormalizedActor, ScriptedActor

POLICY_FORMAT = "mapex.policy"
CRITICS_FORMAT = "mapex.critics"
FORMAT_VERSION = 1

_SPEC_KEYS = ("env_id", "obs_dim", "act_dim", "n_objectives")


def cpu_copy(obj: Any) -> Any:
    """A copy of a (nested) state dict with every tensor detached and cloned on the CPU (dicts,
    lists and tuples are rebuilt, anything else is returned as it is)."""
    if torch.is_tensor(obj):
        return obj.detach().to("cpu", copy=True)
    if isinstance(obj, dict):
        return {k: cpu_copy(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(cpu_copy(v) for v in obj)
    return obj


def _cpu_state(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return cpu_copy(module.state_dict())


def save_policy(path: str | Path, actor: Actor, meta: dict[str, Any], actor_target: Actor | None = None) -> None:
    obj: dict[str, Any] = {
        "format": POLICY_FORMAT,
        "format_version": FORMAT_VERSION,
        "meta": meta,
        "actor": _cpu_state(actor),
    }
    if actor_target is not None:
        obj["actor_target"] = _cpu_state(actor_target)
    torch_save_atomic(obj, path)


def actor_from_meta(meta: dict[str, Any]) -> Actor | ScriptedActor:
    """An empty actor of the architecture `meta` records, to load a state dict into: the MLP
    `Actor` of meta's hidden_sizes, or a `ScriptedActor` where meta["architecture"] is
    "torchscript", an `ExportedActor` where it is "torch_export" (a policy imported as
    TorchScript or as a torch.export program, docs/import_export.md), a `NormalizedActor`
    where it is "normalized_mlp" (one imported with the observation statistics it was trained
    with)."""
    if meta.get("architecture") == "torchscript":
        return ScriptedActor(meta["action_low"], meta["action_high"])
    if meta.get("architecture") == "torch_export":
        return ExportedActor(meta["action_low"], meta["action_high"])
    cls = NormalizedActor if meta.get("architecture") == "normalized_mlp" else Actor
    return cls(meta["obs_dim"], meta["act_dim"], meta["hidden_sizes"], meta["action_low"], meta["action_high"])


def load_policy(path: str | Path, target: bool = False):
    """Load an actor (in eval mode, on CPU) and its metadata: (actor, meta), or with `target`
    (actor, meta, target actor), the target None where the file holds none (a child's)."""
    obj = torch_load_checked(path, POLICY_FORMAT, FORMAT_VERSION)
    meta = obj["meta"]
    nets = []
    for key in ("actor", "actor_target") if target and "actor_target" in obj else ("actor",):
        actor = actor_from_meta(meta)
        try:
            actor.load_state_dict(obj[key])
        except ArtifactError as exc:  # an imported program refused by its inspection (pt2check)
            raise ArtifactError(f"{path}: {key}: {exc}") from None
        except (RuntimeError, KeyError, ValueError) as exc:
            raise ArtifactError(f"{path}: {key} weights do not match its metadata ({exc})") from None
        nets.append(actor.eval())
    if not target:
        return nets[0], meta
    return nets[0], meta, nets[1] if len(nets) > 1 else None


def save_critics(path: str | Path, online: CriticEnsemble, target: CriticEnsemble, meta: dict[str, Any]) -> None:
    if online.n_members != 2 * len(meta["objectives"]):
        raise ValueError("critic ensemble must hold two heads per covered objective")
    obj = {
        "format": CRITICS_FORMAT,
        "format_version": FORMAT_VERSION,
        "meta": meta,
        "online": _cpu_state(online),
        "target": _cpu_state(target),
    }
    torch_save_atomic(obj, path)


def load_critics(path: str | Path) -> tuple[CriticEnsemble, CriticEnsemble, dict[str, Any]]:
    """Load (online, target, meta) of a critics artifact, either source (joint or post-hoc)."""
    obj = torch_load_checked(path, CRITICS_FORMAT, FORMAT_VERSION)
    meta = obj["meta"]
    nets = []
    for key in ("online", "target"):
        net = CriticEnsemble(meta["obs_dim"], meta["act_dim"], meta["hidden_sizes"], 2 * len(meta["objectives"]))
        try:
            net.load_state_dict(obj[key])
        except (RuntimeError, KeyError) as exc:
            raise ArtifactError(f"{path}: {key} critic weights do not match its metadata ({exc})") from None
        nets.append(net.eval())
    return nets[0], nets[1], meta


def check_matches(path: str | Path, meta: dict[str, Any], ref: dict[str, Any], ref_name: str) -> None:
    """Raise ArtifactError if `meta` (of artifact `path`) disagrees with `ref` on env and dims."""
    for key in _SPEC_KEYS:
        if meta.get(key) != ref.get(key):
            raise ArtifactError(
                f"{path}: {key} = {meta.get(key)!r} does not match {ref_name} ({key} = {ref.get(key)!r})"
            )
