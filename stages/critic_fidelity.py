"""Stage critic_fidelity: score a critics.pt (normally the joint one) against its buffer's returns."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer

from pipeline.core.artifacts import ArtifactError, write_text_atomic
from pipeline.core.checkpoint import check_matches, load_critics
from pipeline.core.specialist import check_posthoc_buffer, load_slot
from pipeline.critics.fidelity import fidelity_json, score_critics
from pipeline.params import load_params, section
from pipeline.params.critic_fidelity import CriticFidelityParams
from stages.common import PARAMS_OPTION, reports_errors

# Which params section of a critics file's meta holds the discount it was trained with.
_GAMMA_SECTION = {"joint": "td3", "posthoc": "fit_critics"}


def trained_gamma(path: Path, meta: dict[str, Any]) -> float:
    """The discount a critics artifact was trained with, read from its own metadata."""
    name = _GAMMA_SECTION.get(meta.get("source"))
    gamma = (meta.get("params") or {}).get(name, {}).get("gamma") if name else None
    if not isinstance(gamma, (int, float)):
        raise ArtifactError(f"{path}: metadata does not record the critics' discount (source {meta.get('source')!r})")
    return float(gamma)


@reports_errors
def critic_fidelity(
    objective: int = typer.Option(..., help="k: the specialist whose buffer D_k the critics were trained on"),
    specialist: Path = typer.Option(..., help="specialist directory holding buffer.zarr and policy.pt"),
    critics: Optional[Path] = typer.Option(
        None, help="critics file to score: joint (default: SPECIALIST/critics.pt) or post-hoc (fit-critics' critics.pt)"
    ),
    out: Path = typer.Option(..., help="output JSON file (DVC metrics)"),
    params: Path = PARAMS_OPTION,
) -> None:
    """Score critics Q^(k)_m against discounted Monte-Carlo returns of their own buffer D_k.

    Params: section `critic_fidelity`. Joint and post-hoc critics are scored by this same
    rule, so their scores compare like with like. The discount is the one the critics were
    trained with, read from their metadata; pi_k is the specialist's TD3 target actor, whose
    actions both kinds of critic bootstrap through (its online actor if it has none). For
    each covered objective m, OUT holds the Pearson correlation and normalised error
    mean|Q - G| / mean|G| of Q^(k)_m(s, pi_k(s)) against the return G_m over the buffer's
    last episodes. The critics must be of this specialist: same env, dims, seed and buffer
    objective, and post-hoc critics must carry the checksums of this buffer.
    """
    fid = section(load_params(params), "critic_fidelity", CriticFidelityParams, params)
    spec = load_slot(specialist, objective)
    critics_path = critics if critics is not None else specialist / "critics.pt"
    online, _, meta = load_critics(critics_path)
    check_matches(critics_path, meta, spec.buffer_attrs, str(spec.buffer_path))
    if meta.get("buffer_objective") != objective:
        raise ArtifactError(
            f"{critics_path}: critics of buffer objective {meta.get('buffer_objective')!r}, expected {objective}"
        )
    policy_path = specialist / "policy.pt"
    if meta.get("seed") != spec.policy_meta.get("seed"):
        raise ArtifactError(
            f"{critics_path}: critics of seed {meta.get('seed')!r}, but {policy_path} is of seed {spec.policy_meta.get('seed')!r}"
        )
    if meta.get("source") == "posthoc":
        check_posthoc_buffer(critics_path, meta, spec.buffer_path, spec.buffer_attrs)
    gamma = trained_gamma(critics_path, meta)
    target = spec.actor if spec.actor_target is None else spec.actor_target
    report = score_critics(spec.buffer, online, meta["objectives"], target, gamma, fid.episodes, fid.tail_tolerance)
    write_text_atomic(out, fidelity_json(report, objective, source=meta.get("source"), actor="target"))
