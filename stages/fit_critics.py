"""Stage fit_critics: post-hoc critics Q^(k)_m for every objective m on specialist k's buffer."""

from __future__ import annotations

import csv
import io
import json
import copy
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import typer

from pipeline.core.artifacts import ArtifactError, torch_load_checked, write_text_atomic
from pipeline.core.buffer import load_buffer
from pipeline.core.checkpoint import FORMAT_VERSION, POLICY_FORMAT, actor_from_meta, check_matches, load_policy, save_critics
from pipeline.critics.fidelity import FidelityReport, score_critics
from pipeline.core.nets import Actor
from pipeline.params import ParamsError
from pipeline.params.fit_critics import FitCriticsParams
from pipeline.critics.posthoc import fit_posthoc_critics
from pipeline.core.provenance import provenance
from pipeline.core.seeding import derive_seeds, select_device, torch_generator
from stages.common import PARAMS_OPTION, progress, read_params, reports_errors

# Extra seed key so post-hoc fitting draws streams independent of the specialist's own,
# which are derived from (seed, objective) alone.
POSTHOC_STREAM = 0x9057


class Specialist(NamedTuple):
    data: dict[str, np.ndarray]  # buffer D_k, in RAM
    attrs: dict[str, Any]  # buffer attributes (env_id, dims, objective, ...)
    buffer_path: Path
    actor: Actor  # pi_k
    target_actor: Actor  # pi_k's TD3 target actor (pi_k itself if the checkpoint has none)
    policy_meta: dict[str, Any]


def load_specialist(directory: Path, objective: int) -> Specialist:
    """Load and cross-check DIR/buffer.zarr and DIR/policy.pt of specialist `objective`.

    Raises ParamsError if `objective` is not an objective of the buffer's env, and
    ArtifactError naming the file if either artifact is missing or damaged, or if they
    disagree with each other or with `objective`.
    """
    buffer_path, policy_path = directory / "buffer.zarr", directory / "policy.pt"
    data, attrs = load_buffer(buffer_path)
    n_obj = attrs["n_objectives"]
    if not 0 <= objective < n_obj:
        raise ParamsError(f"--objective {objective}: {buffer_path} (env {attrs['env_id']}) has objectives 0..{n_obj - 1}")
    if attrs.get("objective") != objective:
        raise ArtifactError(f"{buffer_path}: buffer of specialist objective {attrs.get('objective')!r}, expected {objective}")
    if attrs["n_transitions"] == 0:
        raise ArtifactError(f"{buffer_path}: buffer holds no transitions")
    actor, meta = load_policy(policy_path)
    check_matches(policy_path, meta, attrs, str(buffer_path))
    if meta.get("objective") != objective:
        raise ArtifactError(f"{policy_path}: policy of objective {meta.get('objective')!r}, expected {objective}")
    obj = torch_load_checked(policy_path, POLICY_FORMAT, FORMAT_VERSION)
    target = actor
    if "actor_target" in obj:
        target = actor_from_meta(meta)
        try:
            target.load_state_dict(obj["actor_target"])
        except RuntimeError as exc:
            raise ArtifactError(f"{policy_path}: actor_target weights do not match its metadata ({exc})") from None
        target.eval()
    return Specialist(data, attrs, buffer_path, actor, target, meta)


def fidelity_json(report: FidelityReport, buffer_objective: int, **extra: Any) -> str:
    """Fidelity JSON text (DVC metrics); no NaN: undefined statistics are null."""
    return json.dumps({"buffer_objective": buffer_objective, **extra, **report.to_dict()}, indent=2) + "\n"


def mean_rel_error(report: FidelityReport) -> float:
    """The stopping rule's error: mean normalised error over the covered objectives (inf if undefined)."""
    errs = [f.rel_error for f in report.per_objective]
    return float(np.mean(errs)) if errs and all(e is not None for e in errs) else float("inf")


def fit_csv(checks) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["step", "loss", "mean_rel_error"])
    for c in checks:
        w.writerow([c.step, f"{c.loss:.6g}", f"{c.error:.6g}"])
    return buf.getvalue()


@reports_errors
def fit_critics(
    objective: int = typer.Option(..., help="k: the specialist whose buffer D_k the critics are fitted on"),
    seed: int = typer.Option(0, help="run seed; with the params it fixes every random draw"),
    specialist: Path = typer.Option(..., help="specialist directory holding buffer.zarr and policy.pt"),
    out: Path = typer.Option(..., help="output directory (critics.pt, fit.csv)"),
    params: Path = PARAMS_OPTION,
) -> None:
    """Fit post-hoc critics Q^(k)_m for every objective m offline on specialist k's buffer.

    Params: section `fit_critics`. No env interaction: TD3 policy evaluation of the
    specialist's own policy pi_k (its target actor) on the stored transitions (paper,
    "Secondary Critics", practical note). Fitting runs until the critics' fidelity (mean
    normalised error of Q(s, pi_k(s)) against discounted Monte-Carlo returns on the buffer's
    last episodes, pi_k the target actor they are fitted with) stops improving
    (fit_critics.check_every / patience / min_improvement), at most fit_critics.steps steps,
    and keeps the closest weights.

    Writes to OUT: critics.pt (same format as the jointly trained critics, source "posthoc",
    with the checksums of the buffer they were fitted on) and fit.csv (every fidelity check:
    step, loss, mean normalised error). Their fidelity report is stage critic_fidelity's.
    """
    _, _, cfg = read_params(params, "fit_critics", FitCriticsParams)
    try:
        device = select_device(cfg.device)
    except ValueError as exc:
        raise ParamsError(f"{params}: fit_critics.{exc}") from None
    spec = load_specialist(specialist, objective)
    if spec.policy_meta.get("seed") != seed:
        raise ArtifactError(f"{specialist / 'policy.pt'}: specialist of seed {spec.policy_meta.get('seed')!r}, expected --seed {seed}")
    objectives = list(range(spec.attrs["n_objectives"]))
    s_np, s_torch = derive_seeds(seed, objective, POSTHOC_STREAM, n=2)

    bar = progress(cfg.steps, f"post-hoc critics obj {objective} seed {seed}")

    def on_step(step: int, loss) -> None:
        bar.update(1)
        if step % 250 == 0:  # .item() synchronises a GPU: not every step
            bar.set_postfix_str(f"loss {loss.item():.4g}", refresh=False)

    scorer = copy.deepcopy(spec.target_actor).to(device)

    def error(critic) -> float:
        report = score_critics(spec.data, critic, objectives, scorer, cfg.gamma, cfg.fidelity_episodes, cfg.tail_tolerance)
        err = mean_rel_error(report)
        bar.set_postfix_str(f"fidelity error {err:.3f}", refresh=False)
        return err

    with bar:
        fitted = fit_posthoc_critics(
            spec.data, spec.target_actor, objectives, cfg,
            np.random.default_rng(s_np), torch_generator(s_torch, device), device, on_step, error,
        )
        bar.total = fitted.steps  # stopped early: the bar ends full
        bar.refresh()
    online = fitted.online.cpu()

    pm, attrs = spec.policy_meta, spec.attrs
    meta = {k: attrs[k] for k in ("env_id", "obs_dim", "act_dim", "n_objectives", "max_episode_steps")} | {
        "action_low": pm["action_low"],
        "action_high": pm["action_high"],
        "hidden_sizes": list(cfg.hidden_sizes),
        "seed": seed,
        "params": dict(pm.get("params") or {}) | {"fit_critics": cfg.model_dump()},
        "buffer_objective": objective,
        "objectives": objectives,
        "source": "posthoc",
        "buffer_checksums": dict(spec.attrs.get("checksums", {})),
        "fit": {"steps": fitted.steps, "best_step": fitted.best_step,
                "best_error": min((c.error for c in fitted.checks), default=None)},
        "provenance": provenance(device),
    }
    save_critics(out / "critics.pt", online, fitted.target.cpu(), meta)
    write_text_atomic(out / "fit.csv", fit_csv(fitted.checks))
