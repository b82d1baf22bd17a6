"""Stage mopderl: phase 2 of the MOPDERL baseline from one seed's PDERL specialists (pipeline/baselines/mopderl.py), resumable per generation."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from pipeline.baselines.mopderl import GenerationRecord, MopderlRun, starts_from_slots
from pipeline.core.artifacts import csv_text, write_text_atomic
from pipeline.core.drive import drive
from pipeline.core.envs import env_spec, make_env, spec_meta
from pipeline.core.population import save_population
from pipeline.core.precision import resolve, without_fp32
from pipeline.core.provenance import write_provenance
from pipeline.core.resume import Checkpoint, resume_root, run_fingerprint
from pipeline.core.seeding import select_device
from pipeline.core.specialist import load_slots, training_frames
from pipeline.params import section
from pipeline.params.mopderl import MopderlParams
from pipeline.params.td3 import TD3Params
from stages.common import (
    PARAMS_OPTION,
    PROVENANCE_OPTION,
    method_option,
    progress_send,
    read_params,
    reports_errors,
    require_every_objective,
    require_variant_of,
)

HISTORY_FIELDS = ["generation", "env_frames", "new_individuals", "archive_size", "front_size", "archive_hv_norm"]


def history_csv(records: list[GenerationRecord]) -> str:
    rows = (
        {
            "generation": r.generation,
            "env_frames": r.frames,
            "new_individuals": r.new_individuals,
            "archive_size": r.archive_size,
            "front_size": r.front_size,
            "archive_hv_norm": f"{r.archive_hv_norm:.6g}",
        }
        for r in records
    )
    return csv_text(HISTORY_FIELDS, rows)


@reports_errors
def mopderl(
    seed: int = typer.Option(0, help="run seed: selects the PDERL specialists of this seed and seeds every draw"),
    specialists: Path = typer.Option(
        ...,
        help="the seed's PDERL specialists (stage train_pderl): obj{K}/ per objective K, each with policies.pt "
        "(population actors and 'rl'), policy.pt (RL actor and target), critics.pt (primary and secondary critics) "
        "and buffer.zarr (the RL replay buffer)",
    ),
    out: Path = typer.Option(..., help="output directory: population.pt, history.csv"),
    method: Optional[str] = method_option("mopderl", "section mopderl"),
    resume_dir: Path = typer.Option(
        None,
        help="where progress is checkpointed (RESUME_DIR/METHOD/seedS, METHOD mopderl or --method); default "
        "$MAPEX_RESUME_ROOT if set (a sweep's shared storage), else data/resume",
    ),
    params: Path = PARAMS_OPTION,
    provenance: Optional[Path] = PROVENANCE_OPTION,
) -> None:
    """MOPDERL phase 2 (the baseline): evolve the merged PDERL populations towards a Pareto front.

    Params: sections `env`, `objectives` (every objective 0..m-1), `mopderl` (population,
    operators, phase-2 frame budget) and `td3` (the RL agents' TD3 hyperparameters and
    cuda_graphs; learning_starts, hidden_sizes and secondary_critics come with the PDERL
    specialists). The population starts as every population actor of every
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

    With --method NAME (a named variant of mopderl in params `variants`) its overrides of section
    mopderl apply and the front is method NAME's.

    Progress is checkpointed every mopderl.checkpoint_every generations under
    RESUME_DIR/METHOD/seedS; killed and rerun with the same params, inputs, code, device and
    thread count, the stage resumes and ends with the same artifacts. Anything else starts over.
    On SIGTERM it stops after the current generation, its checkpoint written, with exit code 143.

    Writes OUT/population.pt: the starting actors (origin 'specialist', their objective and
    policy name), then every phase-2 individual that ever entered the archive (origin
    'mopderl', iteration = generation, parents = the member ids of its parents that are in
    the file), each with its training-time fitness (returns: the mean return vector of its
    one evaluation) and env_samples = phase-2 frames spent when it was evaluated. And
    OUT/history.csv, one row per generation (0 = the starting actors): env_frames,
    new_individuals, archive_size, front_size (rank-0 individuals of the population) and
    archive_hv_norm: the hypervolume of the archive's training-time fitness, scaled to [0, 1]
    by the archive's own range (reference 0), as extract's progress line shows. With
    --provenance, what produced the run (pipeline.core.provenance) goes to that file, outside OUT.

    Training that diverges (a NaN or infinity in an RL agent's losses, networks or buffer,
    checked every 100 updates and after every generation, or in a new individual's weights)
    stops the stage with one line naming the seed, objective, step and what went bad, and
    exit code 3; nothing is written and the last good checkpoint stays (docs/manual.md,
    "When training diverges").
    """
    raw, env_p, cfg, run_p = read_params(params, "mopderl", MopderlParams, method)
    method = require_variant_of(raw, method, "mopderl", params)
    td3 = section(raw, "td3", TD3Params, params)
    cfg = cfg.resolved(env_p.id)
    env = make_env(env_p.id, env_p.max_episode_steps, env_p.reward_terms)
    try:
        spec = env_spec(env, env_p.id, env_p.max_episode_steps)
        require_every_objective(run_p.objectives, spec.n_objectives, env_p.id, params, "MOPDERL")
        meta = spec_meta(spec)
        slots = load_slots(specialists, spec.n_objectives, seed=seed, spec_meta=meta, kind="pderl")
        population, agents = starts_from_slots(slots, specialists)
        files = [f for s in slots for f in s.files]
        specialist_frames = training_frames([s.policy_meta for s in slots])
        del slots
        device = select_device(cfg.device)
        precision = resolve(cfg.precision, device, max(td3.hidden_sizes))
        config = {
            "env": env_p.model_dump(exclude={"objective_names", "reference_point"}),
            "mopderl": without_fp32(cfg.model_dump(exclude={"checkpoint_every", "device"})),
            # all of td3: the keys phase 2 does not read (learning_starts, hidden_sizes,
            # secondary_critics) change the PDERL specialists it starts from, so the run anyway
            "td3": td3.model_dump(),
            "seed": seed,
        }
        ckpt = Checkpoint(
            (resume_dir or resume_root("data/resume")) / method / f"seed{seed}" / "state.pt",
            run_fingerprint("mopderl", config, device, files, precision),
            lambda line: typer.echo(line, err=True),
        )

        def save(run: MopderlRun) -> None:
            run_meta = meta | {
                "seed": seed,
                "method": method,
                "params": config,
                "specialist_frames": specialist_frames,
            }
            save_population(out / "population.pt", run.members, run_meta)
            write_text_atomic(out / "history.csv", history_csv(run.history))

        with progress_send(cfg.total_frames, f"MOPDERL seed {seed}", unit="frame") as send:
            drive(
                lambda: MopderlRun(spec, td3, cfg, seed, population, agents, device, env),
                ckpt,
                who=f"mopderl seed {seed}",
                stage="mopderl",
                resumed=lambda run: (
                    f"resuming from generation {run.generation} ({run.frames} frames) of {ckpt.path.parent}"
                ),
                save=save,
                send=send,
            )
    finally:
        env.close()
    write_provenance(provenance, "mopderl", device, precision)
