"""Stage morld: the MORL/D baseline of one seed (morl-baselines' MORLD, pipeline/baselines/morld.py), resumable per exchange."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

import torch
import typer

from pipeline.core.artifacts import write_text_atomic
from pipeline.core.codedeps import closure_files
from pipeline.core.envs import env_spec, make_env
from pipeline.baselines.morld import BaselinesMissing, ExchangeRecord, MorldRun, export_members, history_csv_rows, require_morl_baselines
from pipeline.params.morld import MorldParams
from pipeline.core.population import save_population
from pipeline.core.provenance import provenance
from pipeline.core.resume import checkpoint_dir, fingerprint, load_run_checkpoint, save_run_checkpoint
from pipeline.core.seeding import select_device
from stages.common import PARAMS_OPTION, fmt_vec, progress, read_params, reports_errors

CHECKPOINT = "morld_state.pt"
CHECKPOINT_FORMAT = "mapex.morld_checkpoint"
CHECKPOINT_VERSION = 1
HISTORY_COLUMNS = ("exchange", "frames", "front_eval_frames", "trained_policy", "archive_size")


@reports_errors
def morld(
    seed: int = typer.Option(0, help="run seed; with the params it fixes every random draw"),
    out: Path = typer.Option(..., help="output directory: population.pt, history.csv"),
    params: Path = PARAMS_OPTION,
) -> None:
    """Run the MORL/D baseline of one seed and export its policies as a population.

    Needs the optional extra: pip install -e ".[baselines]" (morl-baselines 1.3.0).

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
    once the artifacts are written.
    """
    _, env_p, cfg = read_params(params, "morld", MorldParams)
    try:
        require_morl_baselines()
    except BaselinesMissing as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=2) from None
    probe = make_env(env_p.id, env_p.max_episode_steps)
    spec = env_spec(probe, env_p.id, env_p.max_episode_steps)
    probe.close()
    device = select_device(cfg.device)
    config = {"env": env_p.model_dump(exclude={"objective_names", "reference_point"}), "morld": cfg.model_dump(), "seed": seed}
    fp = run_fingerprint(config, cfg, device)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = checkpoint_dir(out) / CHECKPOINT  # beside the outputs, or on shared storage in a sweep

    run = MorldRun(spec, cfg, seed, device)
    state = load_checkpoint(ckpt, fp)
    if state is not None:
        try:
            run.load_state_dict(state)
            typer.echo(f"morld seed {seed}: resuming after exchange {run.exchange} ({run.frames} frames) from {ckpt}", err=True)
        except (ValueError, KeyError, RuntimeError) as exc:  # right fingerprint, yet it does not fit: never trust it
            typer.echo(f"{ckpt}: cannot be resumed ({exc}); starting over", err=True)
            run = MorldRun(spec, cfg, seed, device)
    del state

    bar = progress(cfg.frames(), f"MORL/D seed {seed}", unit="frame")
    bar.update(run.frames)
    run.env.on_step = lambda: bar.update(1)

    def on_exchange(run: MorldRun, rec: ExchangeRecord) -> None:
        bar.set_postfix_str(f"exchange {rec.exchange} agent {rec.trained_policy} archive {rec.archive_size}", refresh=False)
        # the last exchange too: a run killed while its actors are evaluated need not train again
        if rec.exchange % cfg.checkpoint_every == 0 or run.done:
            save_checkpoint(ckpt, fp, run)

    with bar:
        run.train(on_exchange)
    run.env.on_step = None
    typer.echo(f"morld seed {seed}: {run.frames} frames, {run.exchange} exchanges; evaluating the exported actors", err=True)
    members, extra = export_members(run, cfg.eval_episodes)
    meta = {
        "env_id": spec.env_id, "obs_dim": spec.obs_dim, "act_dim": spec.act_dim, "n_objectives": spec.n_objectives,
        "action_low": list(spec.action_low), "action_high": list(spec.action_high), "seed": seed, "variant": "morld",
        "params": config, "provenance": provenance(device), **extra,
    }
    save_population(out / "population.pt", members, meta)
    write_text_atomic(out / "history.csv", history_csv(run.history))
    ckpt.unlink(missing_ok=True)
    best = max(members, key=lambda m: m.returns[0])
    typer.echo(f"morld seed {seed}: {len(members)} actors; best on objective 0: {best.policy_name} {fmt_vec(best.returns)}", err=True)


def run_fingerprint(config: dict[str, Any], cfg: MorldParams, device: torch.device) -> str:
    """Everything a run's results depend on: params (not checkpoint_every, device: given
    separately), seed, device, thread count, the library version and every code file the
    stage runs (as in pipeline/core/resume.py)."""
    full = {
        **config, "morld": cfg.model_dump(exclude={"checkpoint_every", "device"}),
        "device": str(device), "threads": torch.get_num_threads(), "morl_baselines": _library_version(),
    }
    return fingerprint(full, closure_files("stages.morld"))


def _library_version() -> str | None:
    from importlib import metadata

    try:
        return metadata.version("morl-baselines")
    except metadata.PackageNotFoundError:
        return None


def load_checkpoint(path: Path, fp: str) -> dict[str, Any] | None:
    """The run state saved at `path` under fingerprint `fp`, else None (pipeline.core.resume)."""
    return load_run_checkpoint(path, CHECKPOINT_FORMAT, CHECKPOINT_VERSION, fp, lambda line: typer.echo(line, err=True))


def save_checkpoint(path: Path, fp: str, run: MorldRun) -> None:
    save_run_checkpoint(path, CHECKPOINT_FORMAT, CHECKPOINT_VERSION, fp, run.state_dict())


def history_csv(history: list[ExchangeRecord]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(HISTORY_COLUMNS), lineterminator="\n")
    w.writeheader()
    w.writerows(history_csv_rows(history))
    return buf.getvalue()
