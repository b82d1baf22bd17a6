"""Stage fit_critics: post-hoc critics Q^(k)_m for every objective m on specialist k's buffer."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from pipeline.core.artifacts import ArtifactError, csv_text, write_text_atomic
from pipeline.core.checkpoint import save_critics
from pipeline.core.finite import TrainingDiverged
from pipeline.core.precision import resolve, without_fp32
from pipeline.core.provenance import write_provenance
from pipeline.core.seeding import derive_seeds, select_device, torch_generator
from pipeline.core.specialist import load_slot
from pipeline.critics.fidelity import mean_rel_error, score_critics
from pipeline.critics.posthoc import fit_posthoc_critics
from pipeline.params import ParamsError
from pipeline.params.fit_critics import FitCriticsParams
from stages.common import PARAMS_OPTION, PROVENANCE_OPTION, progress, read_params, reports_errors

# Extra seed key so post-hoc fitting draws streams independent of the specialist's own,
# which are derived from (seed, objective) alone.
POSTHOC_STREAM = 0x9057


def fit_csv(checks) -> str:
    return csv_text(["step", "loss", "mean_rel_error"], ([c.step, f"{c.loss:.6g}", f"{c.error:.6g}"] for c in checks))


@reports_errors
def fit_critics(
    objective: int = typer.Option(..., help="k: the specialist whose buffer D_k the critics are fitted on"),
    seed: int = typer.Option(0, help="run seed; with the params it fixes every random draw"),
    specialist: Path = typer.Option(..., help="specialist directory holding buffer.zarr and policy.pt"),
    out: Path = typer.Option(..., help="output directory (critics.pt, fit.csv)"),
    params: Path = PARAMS_OPTION,
    provenance: Optional[Path] = PROVENANCE_OPTION,
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
    step, loss, mean normalised error). Their fidelity report is stage critic_fidelity's. With
    --provenance, what produced the run (pipeline.core.provenance) goes to that file, outside OUT.

    A fit that diverges (a NaN or infinity in the loss or a critic weight, checked every 100
    steps and at the end) stops with one line naming the seed, objective and step, and exit
    code 3, and writes nothing (docs/manual.md, "When training diverges").
    """
    _, _, cfg, _ = read_params(params, "fit_critics", FitCriticsParams)
    try:
        device = select_device(cfg.device)
    except ValueError as exc:
        raise ParamsError(f"{params}: fit_critics.{exc}") from None
    spec = load_slot(specialist, objective)
    if spec.policy_meta.get("seed") != seed:
        raise ArtifactError(
            f"{specialist / 'policy.pt'}: specialist of seed {spec.policy_meta.get('seed')!r}, expected --seed {seed}"
        )
    objectives = list(range(spec.buffer_attrs["n_objectives"]))
    s_np, s_torch = derive_seeds(seed, objective, POSTHOC_STREAM, n=2)

    bar = progress(cfg.steps, f"post-hoc critics obj {objective} seed {seed}")

    def on_step(step: int, loss) -> None:
        bar.update(1)
        if step % 250 == 0:  # .item() synchronises a GPU: not every step
            bar.set_postfix_str(f"loss {loss.item():.4g}", refresh=False)

    target = (
        spec.actor if spec.actor_target is None else spec.actor_target
    )  # pi_k's TD3 target actor (pi_k itself if it has none)
    scorer = copy.deepcopy(target).to(device)

    def error(critic) -> float:
        report = score_critics(
            spec.buffer, critic, objectives, scorer, cfg.gamma, cfg.fidelity_episodes, cfg.tail_tolerance
        )
        err = mean_rel_error(report)
        bar.set_postfix_str(f"fidelity error {err:.3f}", refresh=False)
        return err

    with bar:
        try:
            fitted = fit_posthoc_critics(
                spec.buffer,
                target,
                objectives,
                cfg,
                np.random.default_rng(s_np),
                torch_generator(s_torch, device),
                device,
                on_step,
                error,
            )
        except TrainingDiverged as exc:
            raise exc.about(seed, objective).within("fit_critics") from None
        bar.total = fitted.steps  # stopped early: the bar ends full
        bar.refresh()
    online = fitted.online.cpu()

    pm, attrs = spec.policy_meta, spec.buffer_attrs
    meta = {k: attrs[k] for k in ("env_id", "obs_dim", "act_dim", "n_objectives", "max_episode_steps")} | {
        "action_low": pm["action_low"],
        "action_high": pm["action_high"],
        "hidden_sizes": list(cfg.hidden_sizes),
        "seed": seed,
        "params": dict(pm.get("params") or {}) | {"fit_critics": without_fp32(cfg.model_dump())},
        "buffer_objective": objective,
        "objectives": objectives,
        "source": "posthoc",
        "buffer_checksums": dict(attrs.get("checksums", {})),
        "fit": {
            "steps": fitted.steps,
            "best_step": fitted.best_step,
            "best_error": min((c.error for c in fitted.checks), default=None),
        },
    }
    save_critics(out / "critics.pt", online, fitted.target.cpu(), meta)
    write_text_atomic(out / "fit.csv", fit_csv(fitted.checks))
    write_provenance(provenance, "fit_critics", device, resolve(cfg.precision, device, max(cfg.hidden_sizes)))
