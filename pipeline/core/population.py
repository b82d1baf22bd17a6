"""The population artifact of an extraction run: every policy with its record.

population.pt (format "mapex.population", version 3), loadable with torch.load(weights_only=True):

    meta:     env_id, obs_dim, act_dim, n_objectives, action_low, action_high, seed,
              method (pipeline/params/methods.py: mapex_td3, mopderl, ...), params (the params
              the run used; for extraction also its --variant and --kind); no provenance
              (git commit, library versions, device: a file of its own, pipeline.core.provenance)
    members:  list, in the order policies joined the population (index = policy id): first
              the starting policies (every policy of specialist 0's policy set, in the set's
              order, then specialist 1's, ...), then the children
        origin         "specialist" (a starting policy) or "child"
        objective      the objective of the specialist the starting policy came from (None for a child)
        policy_name    its name in that specialist's policy set ("rl", "pop3", ...; "policy" when
                       the specialist gave a single policy.pt), None for a child
        init           (optional: only a child of the hybrid extraction, extract.init interpolate, has
                       it) "interpolated" (started from its parents' mixed weights) or "warmup" (fell
                       back to the paper's warm-up; meta "init_fallbacks" says why)
        iteration      0 for starting policies, i >= 1 for the children made in iteration i
                       (extract.children_per_iteration of them, consecutive ids)
        parents        policy ids of the parents ([] for starting policies)
        target_weight  the unit target weight vector the child was trained for (None for starting policies)
        returns        mean undiscounted return vector over the evaluation episodes
        returns_std    its per-objective standard deviation over those episodes
        eval_episodes  number of evaluation episodes
        env_samples    cumulative env samples spent on evaluation once this policy was evaluated
        hidden_sizes   the actor's hidden widths
        actor          state dict of pipeline.core.nets.Actor (with obs_mean, obs_std and obs_clip, of
                       nets.NormalizedActor, for a starting policy imported with observation
                       statistics; of nets.ScriptedActor, {"torchscript":
                       the file's bytes}, for a starting policy imported as TorchScript; of
                       nets.ExportedActor, {"torch_export": the .pt2 file's bytes}, for one
                       imported as a torch.export program; its hidden_sizes are then [])

Older versions still load: version 2 named the method `variant` in its meta (read as
`method`); version 1 (before policy sets) also lacks `policy_name`, its starting policies
named "policy" (each came from a policy.pt) and its children None.

history.csv, one row per iteration (iteration 0 = the starting policies alone): iteration,
population, front_size, env_samples. No hypervolume: it needs env.reference_point, which is not
an input of extraction; it is computed downstream from the members' iteration and returns.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Sequence

import torch

from pipeline.core.artifacts import ArtifactError, torch_load_checked, torch_save_atomic
from pipeline.core.nets import NORMALIZED_KEYS, Actor, ExportedActor, NormalizedActor, ScriptedActor

FORMAT = "mapex.population"
FORMAT_VERSION = 3
READABLE = (3, 2, 1)  # 2: the method under meta "variant"; 1: also no policy_name


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
    policy_name: str | None = None  # the starting policy's name in its specialist's policy set; None for a child
    # Only a child of the hybrid extraction (extract.init interpolate, not in the paper) has it: "interpolated"
    # (started from its parents' mixed weights) or "warmup" (fell back to the paper's start). An optional key:
    # saved only where set, so every other population keeps its bytes (OPTIONAL_KEYS).
    init: str | None = None


MEMBER_KEYS = tuple(f.name for f in fields(Member))
OPTIONAL_KEYS = ("init",)  # member keys saved only when not None; a population without them still loads


def member_record(member: Member) -> dict[str, Any]:
    """A member as population.pt stores it: its fields, the OPTIONAL_KEYS only where set."""
    return {k: v for k, v in asdict(member).items() if k not in OPTIONAL_KEYS or v is not None}


def member_actor(member: Member, meta: dict[str, Any]) -> Actor | ScriptedActor:
    """Rebuild a member's actor (eval mode, CPU): an `Actor`; a `NormalizedActor` for a
    starting policy imported with observation statistics (its state dict holds them); or a
    `ScriptedActor` (an `ExportedActor`) for one imported as TorchScript (as a torch.export
    program): its state dict holds the file."""
    for cls in (ScriptedActor, ExportedActor):
        if cls.KEY in member.actor:
            data = member.actor[cls.KEY].numpy().tobytes()
            try:
                return cls.from_bytes(data, meta.get("action_low"), meta.get("action_high")).eval()
            except ArtifactError as exc:  # a program refused by its inspection (pt2check)
                raise ArtifactError(f"a {member.origin} member (iteration {member.iteration}): {exc}") from None
    cls = NormalizedActor if NORMALIZED_KEYS[0] in member.actor else Actor
    actor = cls(meta["obs_dim"], meta["act_dim"], member.hidden_sizes, meta["action_low"], meta["action_high"])
    actor.load_state_dict(member.actor)
    return actor.eval()


def actor_state(actor: Actor) -> dict[str, torch.Tensor]:
    return {k: v.detach().cpu().clone() for k, v in actor.state_dict().items()}


def save_population(path: str | Path, members: list[Member], meta: dict[str, Any]) -> None:
    torch_save_atomic(
        {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "meta": meta,
            "members": [member_record(m) for m in members],
        },
        path,
    )


def _load_any_version(path: str | Path) -> tuple[dict[str, Any], int]:
    """The population's dict and its format version (one of READABLE)."""
    try:
        return torch_load_checked(path, FORMAT, FORMAT_VERSION), FORMAT_VERSION
    except ArtifactError as current:
        for version in READABLE[1:]:
            try:
                return torch_load_checked(path, FORMAT, version), version
            except ArtifactError:
                pass
        raise current from None  # missing, unreadable, another format or an unknown version


def load_population(path: str | Path, meta_keys: Sequence[str] = ()) -> tuple[list[Member], dict[str, Any]]:
    """Load (members, meta) of a population.pt of the current format or an older readable one.

    Raises ArtifactError naming the file (never a KeyError) when it is not a valid population:
    no `meta` or `members`, a metadata key of `meta_keys` (or `n_objectives`) missing, a member
    lacking a key or holding an unknown one, or returns of the wrong length.
    """
    obj, version = _load_any_version(path)
    for key, kind in (("meta", dict), ("members", list)):
        if key not in obj:
            raise ArtifactError(f"{path}: not a complete population artifact: no {key!r} key")
        if not isinstance(obj[key], kind):
            raise ArtifactError(f"{path}: {key!r} is a {type(obj[key]).__name__}, expected a {kind.__name__}")
    meta = obj["meta"]
    if version < 3 and "variant" in meta:  # the method was called a variant before version 3
        meta = {("method" if k == "variant" else k): v for k, v in meta.items()}
    missing = [k for k in ("n_objectives", *meta_keys) if k not in meta]
    if missing:
        raise ArtifactError(f"{path}: population metadata has no {', '.join(map(repr, dict.fromkeys(missing)))} key")
    required = tuple(k for k in MEMBER_KEYS if k not in OPTIONAL_KEYS and (version >= 2 or k != "policy_name"))
    members = []
    for i, record in enumerate(obj["members"]):
        if not isinstance(record, dict):
            raise ArtifactError(f"{path}: member {i} is a {type(record).__name__}, expected a dict")
        lacking = [k for k in required if k not in record]
        if lacking:
            raise ArtifactError(f"{path}: member {i} has no {', '.join(map(repr, lacking))} key")
        unknown = sorted(set(record) - set(required) - set(OPTIONAL_KEYS))
        if unknown:
            raise ArtifactError(f"{path}: member {i} has unknown key(s) {unknown} (format_version {version})")
        if version < 2:
            record = {**record, "policy_name": "policy" if record["origin"] == "specialist" else None}
        members.append(Member(**record))
    n_obj = meta["n_objectives"]
    for i, m in enumerate(members):
        if len(m.returns) != n_obj:
            raise ArtifactError(f"{path}: member {i} has {len(m.returns)} returns, expected {n_obj}")
    return members, meta
