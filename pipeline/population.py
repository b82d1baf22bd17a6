"""The population artifact of an extraction run: every policy with its record.

population.pt (format "mapex.population", version 1), loadable with torch.load(weights_only=True):

    meta:     env_id, obs_dim, act_dim, n_objectives, action_low, action_high, seed,
              variant, params (the env and extract params, seed and variant the run used),
              provenance (pipeline.provenance: git commit, library versions, device, threads)
    members:  list, in the order policies joined the population (index = policy id):
        origin         "specialist" or "child"
        objective      the specialist's objective (None for a child)
        iteration      0 for specialists, i >= 1 for the children made in iteration i
                       (extract.children_per_iteration of them, consecutive ids)
        parents        policy ids of the parents ([] for specialists)
        target_weight  the unit target weight vector the child was trained for (None for specialists)
        returns        mean undiscounted return vector over the evaluation episodes
        returns_std    its per-objective standard deviation over those episodes
        eval_episodes  number of evaluation episodes
        env_samples    cumulative env samples spent on evaluation once this policy was evaluated
        hidden_sizes   the actor's hidden widths
        actor          state dict of pipeline.nets.Actor

history.csv, one row per iteration (iteration 0 = specialists alone): iteration, population,
front_size, env_samples. No hypervolume: it needs env.reference_point, which is not an input of
extraction; it is computed downstream from the members' iteration and returns.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch

from pipeline.artifacts import ArtifactError, torch_load_checked, torch_save_atomic
from pipeline.nets import Actor

FORMAT = "mapex.population"
FORMAT_VERSION = 1


@dataclass
class Member:
    origin: str
    objective: int | None
    iteration: int
    parents: list[int]
    target_weight: list[float] | None
    returns: list[float]
    returns_std: list[float]
    eval_episodes: int
    env_samples: int
    hidden_sizes: list[int]
    actor: dict[str, torch.Tensor] = field(repr=False)


def member_actor(member: Member, meta: dict[str, Any]) -> Actor:
    """Rebuild a member's actor (eval mode, CPU)."""
    actor = Actor(meta["obs_dim"], meta["act_dim"], member.hidden_sizes, meta["action_low"], meta["action_high"])
    actor.load_state_dict(member.actor)
    return actor.eval()


def actor_state(actor: Actor) -> dict[str, torch.Tensor]:
    return {k: v.detach().cpu().clone() for k, v in actor.state_dict().items()}


def save_population(path: str | Path, members: list[Member], meta: dict[str, Any]) -> None:
    torch_save_atomic({"format": FORMAT, "format_version": FORMAT_VERSION, "meta": meta, "members": [asdict(m) for m in members]}, path)


def load_population(path: str | Path) -> tuple[list[Member], dict[str, Any]]:
    """Load (members, meta); raises ArtifactError naming the file if it is not a valid population."""
    obj = torch_load_checked(path, FORMAT, FORMAT_VERSION)
    try:
        members = [Member(**m) for m in obj["members"]]
    except TypeError as exc:
        raise ArtifactError(f"{path}: malformed member record ({exc})") from None
    n_obj = obj["meta"]["n_objectives"]
    for i, m in enumerate(members):
        if len(m.returns) != n_obj:
            raise ArtifactError(f"{path}: member {i} has {len(m.returns)} returns, expected {n_obj}")
    return members, obj["meta"]
