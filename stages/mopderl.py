"""Stage mopderl: phase 2 of the MOPDERL baseline from one seed's PDERL specialists (pipeline/baselines/mopderl.py), resumable per generation."""

from __future__ import annotations

import csv
import io
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable

import torch
import typer

from pipeline.core.artifacts import ArtifactError, atomic_path, torch_load_checked, write_text_atomic
from pipeline.core.checkpoint import FORMAT_VERSION as POLICY_VERSION
from pipeline.core.checkpoint import POLICY_FORMAT, actor_from_meta, load_critics
from pipeline.core.codedeps import closure_files
from pipeline.core.envs import make_env, env_spec
from pipeline.baselines.mopderl import AgentInit, GenerationRecord, MopderlRun, StartingActor
from pipeline.params import ParamsError, RunParams, section
from pipeline.params.mopderl import MopderlParams
from pipeline.params.train_specialist import TrainSpecialistParams
from pipeline.specialists.pderl import EpisodeResult
from pipeline.core.population import Member, save_population
from pipeline.core.provenance import provenance
from pipeline.core.resume import clear_progress, fingerprint, load_progress, resume_root, save_progress
from pipeline.core.seeding import select_device
from stages.common import PARAMS_OPTION, fmt_vec, progress, read_params, reports_errors
from stages.extract import SPEC_KEYS, load_specialists, normalised_hypervolume

RUN_FORMAT = "mapex.mopderl_checkpoint"
RUN_VERSION = 1
HISTORY_FIELDS = ["generation", "env_frames", "new_individuals", "archive_size", "front_size", "archive_hv_norm"]
# train_specialist keys phase 2 does not read: the budget is mopderl.total_frames, the buffers
# are already full (no start timesteps), the networks' shapes come from the artifacts, and
# the agents run on mopderl.device (cuda_graphs is read: the agents are TD3Learners).
_UNUSED_TD3_KEYS = {"total_steps", "learning_starts", "hidden_sizes", "secondary_critics", "batched", "device"}


def load_rl_agents(specialists: Path, objectives: list[int], spec_meta: dict, seed: int, buffers: list[dict]) -> tuple[list[AgentInit], list[Path]]:
    """Each objective's RL agent: actor and target actor (policy.pt), online and target critics
    (critics.pt) and the buffer rows already read. policy.pt must be of the same specialist as
    the slot's other files (objective, seed, env). Returns the agents and the files read."""
    agents, files = [], []
    for k, rows in zip(objectives, buffers):
        slot = specialists / f"obj{k}"
        pol_path, crit_path = slot / "policy.pt", slot / "critics.pt"
        obj = torch_load_checked(pol_path, POLICY_FORMAT, POLICY_VERSION)
        meta = obj.get("meta") or {}
        expected = {"objective": k, "seed": seed} | {key: spec_meta[key] for key in SPEC_KEYS}
        for key, want in expected.items():
            if meta.get(key) != want:
                raise ArtifactError(f"{pol_path}: {key} = {meta.get(key)!r}, but the slot obj{k} of {specialists} expects {want!r}")
        if "actor_target" not in obj:
            raise ArtifactError(f"{pol_path}: no 'actor_target': not an RL agent's policy (stage train_pderl writes one)")
        nets = []
        for key in ("actor", "actor_target"):
            actor = actor_from_meta(meta)
            try:
                actor.load_state_dict(obj[key])
            except (RuntimeError, KeyError) as exc:
                raise ArtifactError(f"{pol_path}: {key} weights do not match its metadata ({exc})") from None
            nets.append(actor)
        online, target, cmeta = load_critics(crit_path)
        agents.append(AgentInit(k, nets[0], nets[1], online, target, list(cmeta["objectives"]), rows))
        files.append(pol_path)
    return agents, files


def history_row(rec: GenerationRecord, run: MopderlRun) -> dict[str, Any]:
    return {"generation": rec.generation, "env_frames": rec.frames, "new_individuals": rec.new_individuals,
            "archive_size": rec.archive_size, "front_size": rec.front_size,
            "archive_hv_norm": f"{normalised_hypervolume(run.archive_returns()):.6g}"}


def history_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=HISTORY_FIELDS, lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


def _run_file(generation: int) -> str:
    return f"run_{generation:05d}.pt"


def save_checkpoint(progress_dir: Path, fp: str, run: MopderlRun, history: list[dict], written: int) -> int:
    """Checkpoint after a generation: the members not yet written (each once, as resume items),
    the run's state (streamed to its own file, atomically) and the small state naming it.
    Returns the number of members written."""
    name = _run_file(run.generation)
    small = {"generation": run.generation, "history": history, "run_file": name}
    blob = {"format": RUN_FORMAT, "format_version": RUN_VERSION, "fingerprint": fp, "generation": run.generation, "state": run.state_dict()}
    new = [asdict(m) for m in run.members[written:]]
    if written == 0:
        # a fresh directory: save_progress empties it first, so the run file comes after (a kill
        # in between leaves progress without its run file, which load_checkpoint rejects)
        written = save_progress(progress_dir, fp, new, 0, small)
        _write_run_file(progress_dir / name, blob)
    else:
        # the run file first: until state.pt names it, the previous one stays the valid one
        _write_run_file(progress_dir / name, blob)
        written = save_progress(progress_dir, fp, new, written, small)
    for old in progress_dir.glob("run_*.pt"):
        if old.name != name:
            old.unlink(missing_ok=True)
    return written


def _write_run_file(path: Path, blob: dict) -> None:
    with atomic_path(path) as tmp:  # streamed to disk: no second in-memory copy of the buffers
        torch.save(blob, tmp)


def load_checkpoint(progress_dir: Path, fp: str, make_run: Callable[[], MopderlRun]) -> tuple[MopderlRun, list[dict] | None]:
    """A run (`make_run()`) restored from the progress in `progress_dir` saved under
    fingerprint `fp`, and its history rows; or a fresh run and None if there is none that fits
    (a restore that failed half-way is thrown away)."""
    run = make_run()
    saved = load_progress(progress_dir, fp)
    if saved is None:
        return run, None
    items, small = saved
    path = progress_dir / small.get("run_file", "")
    try:
        blob = torch_load_checked(path, RUN_FORMAT, RUN_VERSION)
        if blob.get("fingerprint") != fp or blob.get("generation") != small.get("generation"):
            raise ValueError("it is not the run state the progress names")
        run.load_state_dict(blob["state"], [Member(**m) for m in items])
    except (ArtifactError, ValueError, KeyError, TypeError) as exc:
        typer.echo(f"{progress_dir}: cannot be resumed ({exc}); starting over", err=True)
        return make_run(), None
    return run, small["history"]


@reports_errors
def mopderl(
    seed: int = typer.Option(0, help="run seed: selects the PDERL specialists of this seed and seeds every draw"),
    specialists: Path = typer.Option(
        ..., help="the seed's PDERL specialists (stage train_pderl): obj{K}/ per objective K, each with policies.pt "
        "(population actors and 'rl'), policy.pt (RL actor and target), critics.pt (primary and secondary critics) "
        "and buffer.zarr (the RL replay buffer)",
    ),
    out: Path = typer.Option(..., help="output directory: population.pt, history.csv"),
    resume_dir: Path = typer.Option(None, help="where progress is checkpointed (RESUME_DIR/mopderl/seedS); default "
                                               "$MAPEX_RESUME_ROOT if set (a sweep's shared storage), else data/resume"),
    params: Path = PARAMS_OPTION,
) -> None:
    """MOPDERL phase 2 (the baseline): evolve the merged PDERL populations towards a Pareto front.

    Params: sections `env`, `objectives` (every objective 0..m-1), `mopderl` (population,
    operators, phase-2 frame budget) and `train_specialist` (the RL agents' TD3
    hyperparameters and cuda_graphs; its total_steps, learning_starts, hidden_sizes, batched
    and device are not read). The population starts as every population actor of every
    specialist's policy set, each evaluated. Each generation makes mopderl.children
    distillation-crossover children of tournament-picked pairs (Pareto rank, then crowding),
    one child per RL agent distilled with its RL actor, and proximally mutated clones; every
    new individual is evaluated (its transitions also feed both RL agents' replay buffers),
    the all-time archive of non-dominated individuals is updated, and NSGA-II selection keeps
    mopderl.population_size. Each RL agent (restored from its specialist's policy.pt,
    critics.pt and buffer.zarr with fresh optimizers) then runs one noisy episode and makes
    rl_updates_per_frame TD3 updates per frame it received. Every env frame counts towards
    mopderl.total_frames; the last generation runs to its end. The specialists' policies,
    critics and buffer must agree on objective, seed and env.

    Progress is checkpointed every mopderl.checkpoint_every generations under
    RESUME_DIR/mopderl/seedS; killed and rerun with the same params, inputs, code, device and
    thread count, the stage resumes and ends with the same artifacts. Anything else starts over.

    Writes OUT/population.pt: the starting actors (origin 'specialist', their objective and
    policy name), then every phase-2 individual that ever entered the archive (origin
    'mopderl', iteration = generation, parents = the member ids of its parents that are in
    the file), each with its training-time fitness (returns: the mean return vector of its
    one evaluation) and env_samples = phase-2 frames spent when it was evaluated. And
    OUT/history.csv, one row per generation (0 = the starting actors): env_frames,
    new_individuals, archive_size, front_size (rank-0 individuals of the population) and
    archive_hv_norm: the hypervolume of the archive's training-time fitness, scaled to [0, 1]
    by the archive's own range (reference 0), as extract's progress line shows.
    """
    raw, env_p, cfg = read_params(params, "mopderl", MopderlParams)
    run_p = section(raw, "", RunParams, params)
    td3 = section(raw, "train_specialist", TrainSpecialistParams, params)
    cfg = cfg.resolved(env_p.id)
    env = make_env(env_p.id, env_p.max_episode_steps)
    try:
        spec = env_spec(env, env_p.id, env_p.max_episode_steps)
        objectives = list(range(spec.n_objectives))
        if sorted(run_p.objectives) != objectives:
            raise ParamsError(f"{params}: objectives = {run_p.objectives}: MOPDERL needs one specialist per objective 0..{spec.n_objectives - 1}")
        spec_meta = {"env_id": spec.env_id, "obs_dim": spec.obs_dim, "act_dim": spec.act_dim, "n_objectives": spec.n_objectives}
        bounds = {"action_low": list(spec.action_low), "action_high": list(spec.action_high)}
        starts, buffers, _, files = load_specialists(specialists, specialists, objectives, spec_meta, seed, "joint", "pderl")
        population = [StartingActor(s.objective, s.name, s.actor) for s in starts if s.name != "rl"]
        if len(population) < 2:
            raise ArtifactError(f"{specialists}: {len(population)} population actor(s) in the policy sets; MOPDERL starts from "
                                "PDERL specialists' populations (policies.pt of stage train_pderl)")
        agents, more = load_rl_agents(specialists, objectives, spec_meta, seed, buffers)
        del buffers
        device = select_device(cfg.device)
        config = {"env": env_p.model_dump(exclude={"objective_names", "reference_point"}),
                  "mopderl": cfg.model_dump(exclude={"checkpoint_every", "device"}),
                  "train_specialist": td3.model_dump(exclude=_UNUSED_TD3_KEYS), "seed": seed}
        fp = fingerprint({**config, "device": str(device), "threads": torch.get_num_threads()},
                         files + more + closure_files("stages.mopderl"))
        progress_dir = (resume_dir or resume_root("data/resume")) / "mopderl" / f"seed{seed}"

        run, history = load_checkpoint(progress_dir, fp, lambda: MopderlRun(spec, td3, cfg, seed, population, agents, device))
        del agents
        written = len(run.members) if history is not None else 0
        if history is not None:
            typer.echo(f"resuming from generation {run.generation} ({run.frames} frames) of {progress_dir}", err=True)

        bar = progress(cfg.total_frames, f"MOPDERL seed {seed}", unit="frame")

        def on_episode(ep: EpisodeResult) -> None:
            bar.update(ep.length)

        with bar:
            bar.update(run.frames)
            if history is None:
                rec = run.initialize(env, on_episode)
                history = [history_row(rec, run)]
                written = save_checkpoint(progress_dir, fp, run, history, 0)
            while not run.budget_spent:
                rec = run.step_generation(env, on_episode)
                history.append(history_row(rec, run))
                if rec.generation % cfg.checkpoint_every == 0:
                    written = save_checkpoint(progress_dir, fp, run, history, written)
                best = run.archive_returns().max(axis=0)
                bar.set_postfix_str(f"gen {rec.generation} archive {rec.archive_size} HV(norm) {history[-1]['archive_hv_norm']} "
                                    f"best {fmt_vec(best)}", refresh=False)
            bar.total = run.frames
    finally:
        env.close()

    meta = {**spec_meta, **bounds, "seed": seed, "variant": "mopderl", "params": config, "provenance": provenance(device)}
    save_population(out / "population.pt", run.members, meta)
    write_text_atomic(out / "history.csv", history_csv(history))
    clear_progress(progress_dir)
