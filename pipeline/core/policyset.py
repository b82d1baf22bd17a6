"""Policy-set artifacts: every starting policy a specialist run hands to extraction.

A PDERL specialist ends with a population of actors plus its RL actor; the paper's
Algorithm 1 starts from the set of all of them ("a policy set with at least N policies").
A TD3 specialist is the special case of a set of one. Loadable with weights_only=True.

policies.pt (format "mapex.policy_set", version 1)
    meta:     as policy.pt's meta (env_id, obs_dim, act_dim, n_objectives, action_low,
              action_high, hidden_sizes, objective, seed, params ...)
    names:    one label per actor ("rl", "pop3", ...), unique
    fitness:  one float per actor (mean return of the specialist's objective when last
              evaluated), or None where never evaluated
    actors:   state dicts of `nets.Actor`, all with meta's architecture
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple, Sequence

from pipeline.core.artifacts import ArtifactError, torch_load_checked, torch_save_atomic
from pipeline.core.checkpoint import FORMAT_VERSION, POLICY_FORMAT, actor_from_meta
from pipeline.core.nets import Actor

POLICY_SET_FORMAT = "mapex.policy_set"
POLICY_SET_VERSION = 1
_META_KEYS = ("env_id", "obs_dim", "act_dim", "n_objectives", "action_low", "action_high", "hidden_sizes", "objective")


class PolicySet(NamedTuple):
    actors: list[Actor]  # eval mode, on CPU
    names: list[str]
    fitness: list[float | None]
    meta: dict[str, Any]


def _state(actor: Actor) -> dict:
    return {k: v.detach().cpu().clone() for k, v in actor.state_dict().items()}


def save_policy_set(
    path: str | Path,
    actors: Sequence[Actor],
    names: Sequence[str],
    fitness: Sequence[float | None],
    meta: dict[str, Any],
) -> None:
    if not actors:
        raise ValueError("a policy set holds at least one actor")
    if not len(actors) == len(names) == len(fitness):
        raise ValueError(f"{len(actors)} actors, {len(names)} names and {len(fitness)} fitness values")
    if len(set(names)) != len(names):
        raise ValueError(f"policy names must be unique, got {list(names)}")
    missing = [k for k in _META_KEYS if k not in meta]
    if missing:
        raise ValueError(f"policy-set meta lacks {missing}")
    obj = {
        "format": POLICY_SET_FORMAT,
        "format_version": POLICY_SET_VERSION,
        "meta": dict(meta),
        "names": list(names),
        "fitness": [None if f is None else float(f) for f in fitness],
        "actors": [_state(a) for a in actors],
    }
    torch_save_atomic(obj, path)


def load_policy_set(path: str | Path) -> PolicySet:
    """Load a policies.pt; a policy.pt (format "mapex.policy") loads as a set of one named "policy".

    Raises ArtifactError naming the file for a missing file, a wrong format, a metadata key
    missing, or weights that do not fit the metadata's architecture.
    """
    path = Path(path)
    if path.is_file() and path.name == "policy.pt":
        obj = torch_load_checked(path, POLICY_FORMAT, FORMAT_VERSION)
        obj = {"meta": obj.get("meta"), "names": ["policy"], "fitness": [None], "actors": [obj.get("actor")]}
    else:
        obj = torch_load_checked(path, POLICY_SET_FORMAT, POLICY_SET_VERSION)
    meta = obj.get("meta")
    if not isinstance(meta, dict):
        raise ArtifactError(f"{path}: no 'meta' dict")
    missing = [k for k in _META_KEYS if k not in meta]
    if missing:
        raise ArtifactError(f"{path}: metadata lacks {missing}")
    names, fitness, states = obj.get("names"), obj.get("fitness"), obj.get("actors")
    if not (isinstance(names, list) and isinstance(fitness, list) and isinstance(states, list)):
        raise ArtifactError(f"{path}: 'names', 'fitness' and 'actors' must be lists")
    if not states or not len(states) == len(names) == len(fitness):
        raise ArtifactError(
            f"{path}: {len(states)} actors, {len(names)} names, {len(fitness)} fitness values (need equal, >= 1)"
        )
    actors = []
    for name, state in zip(names, states):
        actor = actor_from_meta(meta)
        try:
            actor.load_state_dict(state)
        except ArtifactError as exc:  # an imported program refused by its inspection (pt2check)
            raise ArtifactError(f"{path}: actor {name!r}: {exc}") from None
        except (RuntimeError, KeyError, TypeError) as exc:
            raise ArtifactError(f"{path}: weights of actor {name!r} do not match its metadata ({exc})") from None
        actors.append(actor.eval())
    return PolicySet(actors, list(names), list(fitness), meta)
