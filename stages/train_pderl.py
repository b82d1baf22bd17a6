"""Stage train_pderl: PDERL specialists of one seed, one PDERL run per objective (pipeline/specialists/pderl.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import torch
import typer

from pipeline.core.artifacts import csv_text, write_text_atomic
from pipeline.core.drive import drive
from pipeline.core.envs import EnvSpec
from pipeline.core.policyset import save_policy_set
from pipeline.core.precision import resolve, without_fp32
from pipeline.core.resume import Checkpoint, checkpoint_dir, run_fingerprint
from pipeline.core.signals import sigterm_deferred
from pipeline.core.specialist import save_specialist, specialist_meta
from pipeline.core.workers import split_evenly
from pipeline.params import EnvParams
from pipeline.params.td3 import TD3Params
from pipeline.params.train_pderl import TrainPderlParams
from pipeline.specialists.pderl import PderlResult, PderlRun
from pipeline.specialists.preamble import training_inputs
from stages.common import PARAMS_OPTION, PROVENANCE_OPTION, progress, read_params, reports_errors, run_parts

CHECKPOINT_PREFIX = "pderl_state_"  # + obj{K}.pt


def checkpoint_path(out: Path, k: int) -> Path:
    """Objective k's checkpoint: in .<OUT's name>.resume beside OUT (pipeline.core.resume.checkpoint_dir)."""
    return checkpoint_dir(out, inside=False) / f"{CHECKPOINT_PREFIX}obj{k}.pt"


@reports_errors
def train_pderl(
    seed: int = typer.Option(0, help="run seed; with the params it fixes every random draw"),
    out: Path = typer.Option(..., help="output directory of the seed: one obj{K}/ folder per specialist"),
    objective: Optional[list[int]] = typer.Option(
        None, help="train only this objective's specialist (repeatable); default: every entry of params `objectives`"
    ),
    params: Path = PARAMS_OPTION,
    provenance: Optional[Path] = PROVENANCE_OPTION,
) -> None:
    """Train the PDERL specialists of one seed: one PDERL run per objective.

    Params: sections `env`, `objectives`, `train_pderl` (population, evolution, budget) and
    `td3` (the RL agent: TD3 with secondary critics).
    Each generation evaluates the population (fitness: return of the specialist's objective),
    evolves it (elites, tournament selection, distillation crossover, proximal mutation), runs
    one noisy RL episode and makes one TD3 update per frame collected (once
    td3.learning_starts frames are in); every train_pderl.rl_sync_period
    generations the RL actor replaces the worst individual. Every frame lands in the RL
    agent's replay buffer. Once train_pderl.total_frames are spent (the last generation runs
    to its end), every actor is evaluated once more; those frames count too.

    Writes OUT/obj{K}/ for each objective K: policies.pt (policy set: the RL actor "rl" and
    the population "pop0".., with their final fitness), policy.pt (the RL actor and its
    target actor), critics.pt (the RL agent's critics, online and target), buffer.zarr (its
    replay buffer, full reward vectors) and fitness.csv (per generation: frames, updates,
    best and mean population fitness, the RL episode's return; last row "final": the final
    evaluation). Progress is checkpointed to .<OUT name>.resume/pderl_state_obj{K}.pt beside OUT every
    train_pderl.checkpoint_every generations; a rerun with the same params, code, device and
    thread count resumes from it and ends with the same artifacts. It is deleted once the
    artifacts are written; on SIGTERM it is written after the current generation and the
    stage exits with code 143. train_pderl.processes > 1 runs the objectives side by side in that
    many worker processes (the same artifacts: each run is the same in any process). With
    --provenance, what produced the run (pipeline.core.provenance) goes to that file, outside OUT.

    Training that diverges (a NaN or infinity in the RL agent's losses, networks or buffer, or
    in a population actor after crossover or mutation; checked every 100 updates and after
    every generation) stops the stage with one line naming the seed, objective, update or
    generation and what went bad, and exit code 3; that objective writes nothing and its last
    good checkpoint stays (docs/manual.md, "When training diverges").
    """
    t = training_inputs(read_params(params, "train_pderl", TrainPderlParams), params, objective, check_budget)
    env_p, cfg, td3, spec, objectives, names, device = (
        t.params.env,
        t.params.cfg,
        t.td3,
        t.spec,
        t.objectives,
        t.names,
        t.device,
    )
    parts = split_evenly(objectives, cfg.processes)
    what = ", ".join(f"obj {k} ({names[k]})" for k in objectives)
    bar = progress(
        cfg.total_frames * len(objectives),
        f"PDERL seed {seed}: {what}" + (f" ({len(parts)} processes)" if len(parts) > 1 else ""),
        unit="frame",
    )
    with bar:
        run_parts(
            train_part,
            [(out, part, names, seed, spec, env_p, td3, cfg, device) for part in parts],
            bar,
            lambda i: f"PDERL seed {seed}, " + ", ".join(f"obj {k}" for k in parts[i]),
            prefix="",
        )
        bar.total = bar.n  # the final evaluations overshoot the frame budget
    t.record(provenance, "train_pderl")


def check_budget(cfg: TrainPderlParams, td3: TD3Params) -> None:
    """The RL agent must get frames to learn from within the run's budget."""
    if td3.learning_starts >= cfg.total_frames:
        raise ValueError(
            f"td3.learning_starts ({td3.learning_starts}) must be < train_pderl.total_frames "
            f"({cfg.total_frames}), or the RL agent is never trained"
        )


def train_part(
    out: Path,
    objectives: list[int],
    names,
    seed: int,
    spec: EnvSpec,
    env_p: EnvParams,
    td3: TD3Params,
    cfg: TrainPderlParams,
    device,
    threads: int,
    *,
    send,
) -> None:
    """The PDERL runs of `objectives`, one after another (in this process, or as one worker of
    train_pderl.processes with `threads` torch threads); progress goes to `send` (stages.
    train_specialist.Relay)."""
    torch.set_num_threads(threads)
    with sigterm_deferred():  # SIGTERM: checkpoint after the current generation and stop
        for k in objectives:
            train_one(out, k, names[k], seed, spec, env_p, td3, cfg, device, send)


def run_config(seed: int, objective: int, env_p: EnvParams, td3: TD3Params, cfg: TrainPderlParams) -> dict[str, Any]:
    """What a PDERL run depends on besides code, device and threads (pipeline.core.resume.
    run_fingerprint): the params it reads, seed and objective."""
    return {
        "env": env_p.model_dump(exclude={"objective_names", "reference_point"}),
        "td3": td3.model_dump(),
        "train_pderl": cfg.model_dump(exclude={"checkpoint_every", "device", "processes"}),
        "seed": seed,
        "objective": objective,
    }


def train_one(
    out: Path,
    k: int,
    name: str,
    seed: int,
    spec: EnvSpec,
    env_p: EnvParams,
    td3: TD3Params,
    cfg: TrainPderlParams,
    device: torch.device,
    send,
) -> None:
    """One objective's PDERL run, resumed from its checkpoint if one fits, and its artifacts
    (OUT/obj{k}/). Progress to `send`: ("steps", frames), ("returns", text), ("say", line)."""
    fp = run_fingerprint(
        "train_pderl",
        run_config(seed, k, env_p, td3, cfg),
        device,
        precision=resolve(cfg.precision, device, max(td3.hidden_sizes)),
    )
    # beside OUT (DVC's out, deleted before a rerun), or on shared storage in a sweep
    ckpt = Checkpoint(checkpoint_path(out, k), fp, lambda line: send("say", line))
    label = f"obj {k} ({name})"

    def save(run: PderlRun) -> None:
        result = run.result()
        send("returns", f"{label} final: best {max(result.fitness):.1f} rl {result.rl_fitness:.1f}")
        save_pderl(out / f"obj{k}", result, spec, env_p, td3, cfg)

    drive(
        lambda: PderlRun(spec, td3, cfg, k, seed, device),  # on an env of its own
        ckpt,
        who=f"train_pderl seed {seed}, {label}",
        stage="train_pderl",
        resumed=lambda run: f"obj {k}: resuming from generation {run.generation} ({run.frames} frames) of {ckpt.path}",
        save=save,
        send=lambda kind, value: send(kind, f"{label} {value}" if kind == "returns" else value),
    )


def save_pderl(
    out: Path,
    result: PderlResult,
    spec: EnvSpec,
    env_p: EnvParams,
    td3: TD3Params,
    cfg: TrainPderlParams,
) -> None:
    """Write one PDERL specialist's artifacts (each atomically) into `out`; the meta keys are
    those of a TD3 specialist's (stages/train_specialist.py) plus `trainer` and `env_frames`."""
    k = result.objective
    params = {"td3": td3.model_dump(), "train_pderl": without_fp32(cfg.model_dump())}
    meta = specialist_meta(spec, env_p, td3.hidden_sizes, result.seed, params)
    meta |= {"trainer": "pderl", "env_frames": result.frames}
    save_specialist(out, meta, k, result)
    save_policy_set(
        out / "policies.pt",
        [result.actor, *result.actors],
        ["rl", *(f"pop{i}" for i in range(len(result.actors)))],
        [result.rl_fitness, *result.fitness],
        meta | {"objective": k},
    )
    write_text_atomic(out / "fitness.csv", fitness_csv(result))


def fitness_csv(result: PderlResult) -> str:
    """Per generation: generation, frames, updates, best, mean (population fitness on the run's
    objective), rl_fitness (the noisy RL episode's return); last row 'final': the final
    deterministic evaluation of the population and the RL actor."""
    rows = [
        [r.generation, r.frames, r.updates, f"{r.best:.6g}", f"{r.mean:.6g}", f"{r.rl_fitness:.6g}"]
        for r in result.history
    ]
    fit = result.fitness
    rows.append(
        [
            "final",
            result.frames,
            result.updates,
            f"{max(fit):.6g}",
            f"{sum(fit) / len(fit):.6g}",
            f"{result.rl_fitness:.6g}",
        ]
    )
    return csv_text(["generation", "frames", "updates", "best", "mean", "rl_fitness"], rows)
