"""Specialist artifacts: the slot obj{K}/ one specialist run writes and every later stage reads.

A slot holds buffer.zarr (its replay buffer D_k with full reward vectors), policy.pt (its
actor and TD3 target actor), critics.pt (its primary and secondary critics Q^(k)_m) and, for
a PDERL specialist, policies.pt (its population actors and RL actor). This module is the one
place that writes a slot (`save_specialist`) and reads one with every cross-check
(`load_slot`): the files must describe one specialist (objective, seed, env and dims), the
critics must be of the kind the reader asks for and cover every objective, and critics
fitted post hoc must carry the checksums of exactly this buffer (`check_posthoc_buffer`).
See docs/artifacts.md for the formats.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from pipeline.core.artifacts import ArtifactError
from pipeline.core.buffer import load_buffer, save_buffer
from pipeline.core.checkpoint import load_critics, load_policy, save_critics, save_policy
from pipeline.core.nets import Actor, CriticEnsemble
from pipeline.core.policyset import load_policy_set

SPEC_KEYS = ("env_id", "obs_dim", "act_dim", "n_objectives")
_BUFFER_META_KEYS = ("env_id", "obs_dim", "act_dim", "n_objectives", "max_episode_steps", "seed")

Claim = tuple[Path, dict[str, Any], str]  # (file, its metadata, the key naming its objective)


def specialist_meta(spec, env_p, hidden_sizes, seed: int, params: dict) -> dict:
    """Metadata every specialist artifact carries (TD3 and PDERL alike; readers cross-check it):
    what the inputs and params fix, nothing of the run itself (its provenance is a file of its
    own, pipeline.core.provenance), so a rerun that changes no number writes the same bytes."""
    return {
        "env_id": spec.env_id,
        "obs_dim": spec.obs_dim,
        "act_dim": spec.act_dim,
        "n_objectives": spec.n_objectives,
        "max_episode_steps": spec.max_episode_steps,
        "action_low": list(spec.action_low),
        "action_high": list(spec.action_high),
        "hidden_sizes": list(hidden_sizes),
        "seed": seed,
        # the env keys training reads (dvc.yaml's env.id, env.max_episode_steps), not the scoring
        # reference point or the objectives' labels: changing those must leave these bytes alone
        "params": {"env": env_p.model_dump(exclude={"objective_names", "reference_point"}), **params},
    }


def save_specialist(slot: Path, meta: dict, objective: int, result, policy_meta: dict | None = None) -> None:
    """Write an RL agent's buffer.zarr, policy.pt and critics.pt (each atomically) into `slot`.

    `result` has buffer, actor, actor_target, critic, critic_target and objectives (a TD3
    specialist's result, or PDERL's RL agent). `policy_meta`: keys only policy.pt's metadata
    gets (a TD3 specialist's `keep_best`)."""
    save_buffer(
        slot / "buffer.zarr", result.buffer, {key: meta[key] for key in _BUFFER_META_KEYS} | {"objective": objective}
    )
    save_policy(
        slot / "policy.pt", result.actor, meta | (policy_meta or {}) | {"objective": objective}, result.actor_target
    )
    save_critics(
        slot / "critics.pt",
        result.critic,
        result.critic_target,
        meta | {"buffer_objective": objective, "objectives": result.objectives, "source": "joint"},
    )


def kind_from_meta(meta: dict) -> str | None:
    """'pderl' or 'td3' from a specialist artifact's recorded params; 'imported' for a slot of the
    imported kind trained here (its policy.pt's source is {"trained": ...}: stage
    train_specialist_imported); None if it records none."""
    source = meta.get("source")
    if isinstance(source, dict) and "trained" in source:
        return "imported"
    params = meta.get("params")
    if not isinstance(params, dict):
        return None
    return "pderl" if "train_pderl" in params else "td3" if "train_specialist" in params else None


def training_frames(metas: list[dict]) -> int | None:
    """Env frames one seed's specialists trained on, from their artifacts' metadata (policy.pt's
    or policies.pt's, one per objective): a PDERL specialist's `env_frames`; a TD3 specialist's
    train_specialist.total_steps, its shared prefix (td3.shared_prefix_steps) counted once for the
    seed, not once per specialist. None when any records neither: an imported specialist trained
    elsewhere, whose frames are not known here (its buffer collection is counted apart)."""
    own, shared = 0, 0
    for meta in metas:
        if meta.get("env_frames") is not None:
            own += int(meta["env_frames"])
            continue
        params = meta.get("params") if isinstance(meta.get("params"), dict) else {}
        steps = (params.get("train_specialist") or {}).get("total_steps")
        if steps is None:
            return None
        prefix = int((params.get("td3") or {}).get("shared_prefix_steps") or 0)
        own += int(steps) - prefix
        shared = max(shared, prefix)
    return own + shared


def slot_sources(slots: list["Slot"]) -> list[dict] | None:
    """Where each slot of one seed's imported kind came from, in objective order, when some were
    trained here (stage train_specialist_imported) beside the imported ones; None when none was
    (a run of imported slots only, or of a kind trained here, records nothing new). An imported
    slot gives its format, algorithm and file name ({"objective", "imported": {...}}), a trained
    one its algorithm and length ({"objective", "trained": "td3", "total_steps"})."""
    sources = [s.policy_meta.get("source") for s in slots]
    if not any(isinstance(src, dict) and "trained" in src for src in sources):
        return None
    out = []
    for slot, src in zip(slots, sources):
        if isinstance(src, dict) and "trained" in src:
            steps = ((slot.policy_meta.get("params") or {}).get("train_specialist") or {}).get("total_steps")
            out.append({"objective": slot.objective, "trained": src["trained"], "total_steps": steps})
        else:
            src = src if isinstance(src, dict) else {}
            out.append(
                {"objective": slot.objective, "imported": {k: src.get(k) for k in ("format", "algorithm", "file")}}
            )
    return out


def policies_path(slot: Path) -> Path:
    """A slot's starting policies: its policy set policies.pt if there is one (a PDERL
    specialist: population actors and RL actor), else its policy.pt (a TD3 specialist)."""
    return slot / "policies.pt" if (slot / "policies.pt").exists() else slot / "policy.pt"


class StartingPolicy(NamedTuple):
    """One policy of a specialist's policy set: it starts in the population."""

    objective: int  # the specialist's objective (its slot obj{k})
    name: str  # its name in the set ("rl", "pop3", ...; "policy" for a policy.pt)
    actor: Actor
    hidden_sizes: list[int]


class Slot(NamedTuple):
    """One specialist's artifacts, read and cross-checked by `load_slot` (CPU, eval mode)."""

    objective: int
    buffer: dict[str, np.ndarray]  # D_k, in RAM
    buffer_attrs: dict[str, Any]
    buffer_path: Path
    actor: Actor  # policy.pt: pi_k
    actor_target: Actor | None  # its TD3 target actor; None if policy.pt holds none
    policy_meta: dict[str, Any]
    starts: list[StartingPolicy]  # the policy set (policies.pt, else policy.pt as a set of one); [] unless asked
    critic: CriticEnsemble | None  # None unless critics were asked for
    critic_target: CriticEnsemble | None
    critics_meta: dict[str, Any] | None
    files: list[Path]  # what was read, for resume fingerprints


def check_slot(k: int, seed: int | None, spec_meta: dict | None, claims: list[Claim]) -> None:
    """The files of slot obj{k} must describe one specialist: objective k, run seed `seed`
    and the env and dims of `spec_meta` (each skipped when None), and agree with each other.
    Raises ArtifactError naming both files of the first disagreement (or the file lacking a
    key and the one it is checked against)."""
    expected: dict[str, tuple[Any, str]] = {"objective": (k, "the objective asked for")}
    if seed is not None:
        expected["seed"] = (seed, f"--seed {seed}")
    expected |= {key: (spec_meta[key] if spec_meta else None, "params env") for key in SPEC_KEYS}
    for key, (want, source) in expected.items():
        values = []
        for i, (path, meta, objective_key) in enumerate(claims):
            name = objective_key if key == "objective" else key
            if name not in meta:
                other = claims[1 if i != 1 else 0][0]
                raise ArtifactError(f"{path}: metadata has no {name!r}, so it cannot be checked against {other}")
            values.append((path, name, meta[name]))
        for (pa, na, va), (pb, nb, vb) in zip(values, values[1:]):
            if va != vb:
                raise ArtifactError(f"{pa} ({na} = {va!r}) and {pb} ({nb} = {vb!r}) are not of the same specialist")
        if want is not None and values[0][2] != want:
            paths = ", ".join(str(p) for p, _, _ in values)
            raise ArtifactError(f"{paths} all have {key} = {values[0][2]!r}, expected {want!r} ({source})")


def check_posthoc_buffer(crit_path: Path, cmeta: dict, buf_path: Path, attrs: dict) -> None:
    """Critics fitted post hoc must record the checksums of the buffer they were fitted on,
    and those must be the checksums of `buf_path` (its arrays, `attrs["checksums"]`)."""
    theirs = cmeta.get("buffer_checksums")
    if theirs is None:
        raise ArtifactError(
            f"{crit_path}: the post-hoc critics do not record which buffer they were fitted on (they are "
            f"without 'buffer_checksums'), so they cannot be checked against {buf_path}; refit them with fit-critics"
        )
    ours = attrs.get("checksums", {})
    if theirs != ours:
        differ = sorted(k for k in set(theirs) | set(ours) if theirs.get(k) != ours.get(k))
        raise ArtifactError(
            f"{crit_path} was fitted on a different buffer than {buf_path}: the checksums of {differ} differ"
        )


def check_critics(crit_path: Path, cmeta: dict, buf_path: Path, attrs: dict, mode: str, n_objectives: int) -> None:
    """The critics are of the kind the reader asks for (mode "posthoc" or "joint"), cover every
    objective and, if fitted post hoc, were fitted on exactly this buffer."""
    if cmeta.get("source") != mode:
        raise ArtifactError(
            f"{crit_path}: critics of source {cmeta.get('source')!r} beside {buf_path}, but the variant "
            f"reads {mode!r} critics (mapex_posthoc: posthoc; the others: joint)"
        )
    if cmeta["objectives"] != list(range(n_objectives)):
        raise ArtifactError(
            f"{crit_path}: critics covering objectives {cmeta['objectives']}; expected all of {list(range(n_objectives))} "
            f"for {buf_path} (train with td3.secondary_critics: true, or use --variant mapex_posthoc)"
        )
    if mode == "posthoc":
        check_posthoc_buffer(crit_path, cmeta, buf_path, attrs)


def load_slot(
    slot: Path,
    objective: int,
    *,
    seed: int | None = None,
    spec_meta: dict | None = None,
    policies: bool = False,
    critics: Path | None = None,
    critics_mode: str = "joint",
    kind: str | None = None,
) -> Slot:
    """Read specialist `objective`'s slot directory: buffer.zarr and policy.pt always, its
    policy set if `policies`, and the critics file `critics` (of source `critics_mode`) if
    given; every file read is cross-checked (see check_slot, check_critics; given `kind`, the
    policies must be of that kind where their metadata says).

    Raises ArtifactError naming the file for a missing or damaged file, an objective the
    buffer's env does not have, an empty buffer, or files of different specialists."""
    buf_path, pol_path = slot / "buffer.zarr", slot / "policy.pt"
    starts: list[StartingPolicy] = []
    set_claim: list[Claim] = []
    if policies:  # read first: a missing specialist is reported by its policies' file
        set_path = policies_path(slot)
        pset = load_policy_set(set_path)
        found = kind_from_meta(pset.meta)
        if kind is not None and found is not None and found != kind:
            raise ArtifactError(f"{set_path}: a {found} specialist, but --kind is {kind!r}")
        hidden = list(pset.meta["hidden_sizes"])
        starts = [StartingPolicy(objective, name, a, hidden) for name, a in zip(pset.names, pset.actors)]
        if set_path != pol_path:
            set_claim = [(set_path, pset.meta, "objective")]
    actor, meta, target = load_policy(pol_path, target=True)
    data, attrs = load_buffer(buf_path)
    n_obj = attrs["n_objectives"]
    if not 0 <= objective < n_obj:
        raise ArtifactError(f"{buf_path} (env {attrs['env_id']}) has objectives 0..{n_obj - 1}, not {objective}")
    if attrs["n_transitions"] == 0:
        raise ArtifactError(f"{buf_path}: buffer holds no transitions")
    # the starting policies first, then the buffer they are checked against (then a set's policy.pt)
    policy_claim: Claim = (pol_path, meta, "objective")
    claims = [*(set_claim or [policy_claim]), (buf_path, attrs, "objective"), *([policy_claim] if set_claim else [])]
    files = [*(c[0] for c in set_claim), pol_path, buf_path / "zarr.json"]
    online = crit_target = cmeta = None
    if critics is not None:
        online, crit_target, cmeta = load_critics(critics)
        claims.append((critics, cmeta, "buffer_objective"))
        files.append(critics)
    check_slot(objective, seed, spec_meta or attrs, claims)
    if critics is not None:
        check_critics(critics, cmeta, buf_path, attrs, critics_mode, n_obj)
    return Slot(objective, data, attrs, buf_path, actor, target, meta, starts, online, crit_target, cmeta, files)


def load_slots(
    spec_root: Path,
    n_objectives: int,
    *,
    seed: int,
    spec_meta: dict,
    critics_root: Path | None = None,
    critics_mode: str = "joint",
    kind: str | None = None,
    critics: bool = True,
) -> list[Slot]:
    """Every slot obj0 .. obj{n-1} of one seed's specialists under `spec_root`, each with its
    policy set and the critics CRITICS_ROOT/obj{k}/critics.pt (default: the slot's own), all
    cross-checked (load_slot). With critics=False no critics file is read (nor needed): the
    slots' `critic` is None (the warm-up-only variant, which trains no advantage-weighted epoch)."""
    critics_root = critics_root or spec_root
    return [
        load_slot(
            spec_root / f"obj{k}",
            k,
            seed=seed,
            spec_meta=spec_meta,
            policies=True,
            critics=critics_root / f"obj{k}" / "critics.pt" if critics else None,
            critics_mode=critics_mode,
            kind=kind,
        )
        for k in range(n_objectives)
    ]
