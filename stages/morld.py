"""Stage morld: the MORL/D baseline of one seed (morl-baselines' MORLD, pipeline/baselines/morld.py), resumable per exchange."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from pipeline.baselines.morld import (
    BaselinesMissing,
    ExchangeRecord,
    MorldRun,
    export_members,
    history_csv_rows,
    require_morl_baselines,
)
from pipeline.core.artifacts import csv_text, write_text_atomic
from pipeline.core.drive import drive
from pipeline.core.envs import spec_meta
from pipeline.core.population import save_population
from pipeline.core.provenance import write_provenance
from pipeline.core.resume import Checkpoint, checkpoint_dir, run_fingerprint
from pipeline.core.seeding import select_device
from pipeline.evaluation.preflight import preflight
from pipeline.params import ParamsError
from pipeline.params.morld import MorldParams
from stages.common import (
    PARAMS_OPTION,
    PROVENANCE_OPTION,
    fmt_vec,
    method_option,
    progress_send,
    read_params,
    reports_errors,
    require_variant_of,
)

CHECKPOINT = "morld_state.pt"
HISTORY_COLUMNS = ("exchange", "frames", "front_eval_frames", "trained_policy", "archive_size")


@reports_errors
def morld(
    seed: int = typer.Option(0, help="run seed; with the params it fixes every random draw"),
    out: Path = typer.Option(..., help="output directory: population.pt, history.csv"),
    method: Optional[str] = method_option("morld", "section morld"),
    params: Path = PARAMS_OPTION,
    provenance: Optional[Path] = PROVENANCE_OPTION,
) -> None:
    """Run the MORL/D baseline of one seed and export its policies as a population.

    Needs the optional extra: pip install -e ".[baselines]" (morl-baselines 1.3.0).

    With --method NAME (a named variant of morld in params `variants`) its overrides of section
    morld apply and the front is method NAME's.

    Params: sections `env` (id, max_episode_steps: every training and evaluation episode is
    capped there) and `morld`. Runs morl-baselines' MORLD with MOSAC agents (the paper's
    settings by default: weighted sums, SER evaluation, population 6, exchange every 50,000
    frames, shared buffer, PSA weight adaptation, gamma 0.99) until morld.total_frames
    training frames are spent, in whole exchanges. MORL/D's own archive scores (discounted
    returns of stochastic actions) only decide what its archive keeps.

    Exports the final agents (pop0, pop1, ...) and the archive's entries (archive0, ...;
    exact copies of a final agent left out), each converted to our deterministic actor
    (tanh of MOSAC's mean action, scaled to the action bounds) and scored by its mean
    undiscounted return over morld.eval_episodes deterministic episodes.

    Writes OUT/population.pt (origin "morld"; iteration = exchanges done when the actor was
    taken, env_samples = training frames then; target_weight = its MORL/D weight vector) and
    OUT/history.csv (per exchange: training frames, MORL/D's evaluation frames, the agent
    trained, archive size). Progress is checkpointed to OUT/morld_state.pt (replay buffer
    included) every morld.checkpoint_every exchanges; a rerun with the same params, code,
    device and thread count resumes from it and ends with the same artifacts. It is deleted
    once the artifacts are written. On SIGTERM the stage stops after the current exchange, its
    checkpoint written, with exit code 143. With --provenance, what produced the run
    (pipeline.core.provenance) goes to that file, outside OUT.

    Training that diverges (a NaN or infinity in an agent's networks, entropy temperature or
    replay buffer, checked after every exchange; MOSAC's losses are not exposed) stops the
    stage with one line naming the seed, exchange and what went bad, and exit code 3; nothing
    is written and the last good checkpoint stays (docs/manual.md, "When training diverges").
    """
    raw, env_p, cfg, _ = read_params(params, "morld", MorldParams, method)
    method = require_variant_of(raw, method, "morld", params)
    try:
        require_morl_baselines()
    except BaselinesMissing as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=2) from None
    spec = preflight(env_p, params, reference=False)  # the env builds and fits, in one line if not
    if cfg.weight_init == "uniform" and cfg.pop_size < spec.n_objectives:
        # morl-baselines spreads uniform weights with pymoo's Riesz-energy directions, which fail
        # (an AttributeError deep in pymoo 0.6.2) for fewer points than objectives
        raise ParamsError(
            f"{params}: morld.pop_size = {cfg.pop_size}, but env.id = {env_p.id!r} has {spec.n_objectives} "
            "objectives: uniform weight_init needs pop_size >= the number of objectives (one agent per corner "
            "of the weight simplex at least)"
        )
    device = select_device(cfg.device)
    config = {
        "env": env_p.model_dump(exclude={"objective_names", "reference_point"}),
        "morld": cfg.model_dump(),
        "seed": seed,
    }
    # the library version is in the fingerprint: the run drives morl-baselines' internals
    fp = run_fingerprint(
        "morld",
        {
            **config,
            "morld": cfg.model_dump(exclude={"checkpoint_every", "device"}),
            "morl_baselines": _library_version(),
        },
        device,
    )
    out.mkdir(parents=True, exist_ok=True)
    # beside the outputs, or on shared storage in a sweep
    ckpt = Checkpoint(checkpoint_dir(out) / CHECKPOINT, fp, lambda line: typer.echo(line, err=True))

    def save(run: MorldRun) -> None:
        typer.echo(
            f"morld seed {seed}: {run.frames} frames, {run.exchange} exchanges; evaluating the exported actors",
            err=True,
        )
        members, extra = export_members(run, cfg.eval_episodes)
        meta = {**spec_meta(spec), "seed": seed, "method": method, "params": config, "specialist_frames": 0}
        save_population(out / "population.pt", members, meta | extra)
        write_text_atomic(out / "history.csv", history_csv(run.history))
        best = max(members, key=lambda m: m.returns[0])
        typer.echo(
            f"morld seed {seed}: {len(members)} actors; best on objective 0: {best.policy_name} {fmt_vec(best.returns)}",
            err=True,
        )

    with progress_send(cfg.frames(), f"MORL/D seed {seed}", unit="frame") as send:
        drive(
            lambda: MorldRun(spec, cfg, seed, device),
            ckpt,
            who=f"morld seed {seed}",
            stage="morld",
            resumed=lambda run: (
                f"morld seed {seed}: resuming after exchange {run.exchange} ({run.frames} frames) from {ckpt.path}"
            ),
            save=save,
            send=send,
        )
    write_provenance(provenance, "morld", device)


def _library_version() -> str | None:
    from importlib import metadata

    try:
        return metadata.version("morl-baselines")
    except metadata.PackageNotFoundError:
        return None


def history_csv(history: list[ExchangeRecord]) -> str:
    return csv_text(HISTORY_COLUMNS, history_csv_rows(history))
