"""Stage train_specialist: the TD3 specialists of one seed, one per objective, with secondary critics."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional, Sequence

import torch
import typer

from pipeline.core.artifacts import csv_text, write_text_atomic
from pipeline.core.drive import drive
from pipeline.core.envs import make_env
from pipeline.core.envstate import env_checkpoint_problem
from pipeline.core.precision import resolve, without_fp32
from pipeline.core.resume import Checkpoint, checkpoint_dir, run_fingerprint
from pipeline.core.signals import sigterm_deferred
from pipeline.core.specialist import save_specialist, specialist_meta
from pipeline.core.workers import split_evenly
from pipeline.params import EnvParams, ParamsError
from pipeline.params.td3 import TD3Params
from pipeline.params.train_specialist import TrainSpecialistParams, check_against_td3
from pipeline.specialists.keep_best import KeepBest, keep_best_hook
from pipeline.specialists.preamble import training_inputs
from pipeline.specialists.td3_training import SpecialistResult, SpecialistsRun
from stages.common import (
    PARAMS_OPTION,
    PROVENANCE_OPTION,
    named_variant,
    progress,
    read_params,
    reports_errors,
    run_parts,
)

CHECKPOINT_PREFIX = "specialist_state_"  # + obj0-obj1.pt: the objectives trained together
# --kind -> what the slots' policy.pt records as their source: nothing for TD3 specialists (their
# artifacts stay as they were), {"trained": "td3"} for a slot of the imported kind trained here
SLOT_SOURCES: dict[str, dict | None] = {"td3": None, "imported": {"trained": "td3"}}
PROGRESS_EVERY = 250  # env steps (of all specialists of a group) between progress messages


@reports_errors
def train_specialist(
    seed: int = typer.Option(0, help="run seed; with the params it fixes every random draw"),
    out: Path = typer.Option(..., help="output directory of the seed: one obj{K}/ folder per specialist"),
    objective: Optional[list[int]] = typer.Option(
        None, help="train only this objective's specialist (repeatable); default: every entry of params `objectives`"
    ),
    kind: str = typer.Option(
        "td3",
        help="the kind of specialists the slots are: 'td3', or 'imported' (objectives import_specialists.policies "
        "leaves out, trained here; needs --objective)",
    ),
    variant: Optional[str] = typer.Option(
        None,
        help="train this specialists variant of kind td3 (params `variants`: its overrides of sections td3 and "
        "train_specialist apply)",
    ),
    params: Path = PARAMS_OPTION,
    provenance: Optional[Path] = PROVENANCE_OPTION,
) -> None:
    """Train the TD3 specialists of one seed, one per objective of a multi-objective env.

    Params: sections `env`, `objectives`, `td3` (the agent) and `train_specialist` (the run).
    Each specialist's primary critic drives its actor while secondary critics for every other
    objective learn from the same batches (td3.secondary_critics). With train_specialist.batched (the
    default) all specialists train in lockstep in this one process, their networks stacked so
    one batched update serves all; each still has its own env, buffer, seeds and minibatches,
    exactly as if trained alone. batched: false trains them one after another.
    train_specialist.processes > 1 splits the specialists over that many worker processes
    that train side by side (on a CPU with cores to spare, two processes of one specialist
    each beat one process of two stacked at the quickstart's small widths).

    Writes OUT/obj{K}/ for each objective K: buffer.zarr (Zarr replay buffer with full reward
    vectors), policy.pt (actor and target actor), critics.pt (all critics, online and target)
    and returns.csv (the undiscounted return vector of every training episode, a learning
    curve for `dvc plots`). With train_specialist.keep_best_every > 0 (off by default: the
    final actor, as in the paper), policy.pt holds instead the actor that scored best in the
    deterministic evaluations made every keep_best_every steps and at the end, and
    keep_best.csv lists every evaluation (step, score, kept). With --provenance, what produced
    the run (pipeline.core.provenance) goes to that file, outside OUT.

    With --kind imported the slots are those of the imported kind that import_specialists.policies
    leaves out (dvc.yaml's train_specialist_imported, one objective per item): trained exactly
    as above, seeded as stage train_specialist seeds that objective, their policy.pt recording
    source {"trained": "td3"} (an imported slot's records its file and format).

    Every train_specialist.checkpoint_every env steps the specialists trained together save
    their whole state (networks, optimizers, replay buffers, RNGs, the envs mid-episode) to
    .<OUT name>.resume/specialist_state_obj{K}[-obj{L}...].pt beside OUT, atomically; a rerun with the same params,
    code, device and thread count resumes from it and writes the same artifacts, bit for bit
    on a CPU, as an uninterrupted run. Anything else starts over. It is deleted once the
    artifacts are written (it is not a DVC out). On SIGTERM the stage (each worker process)
    writes the checkpoint after the step it is in and exits with code 143; a rerun resumes.

    Training that diverges (a NaN or infinity in a loss, Q-value, weight or buffer, checked
    every 100 updates and before every checkpoint) stops the stage with one line naming the
    seed, objective, step and what went bad, and exit code 3; the diverged specialists write
    nothing and their last good checkpoint stays (docs/manual.md, "When training diverges").
    """
    t = training_inputs(
        read_params(params, "train_specialist", TrainSpecialistParams, variant), params, objective, check_against_td3
    )
    raw, env_p, cfg, td3 = t.params.raw, t.params.env, t.params.cfg, t.td3
    if variant is not None and ((of := named_variant(raw, variant, params).of) != "td3" or kind != "td3"):
        raise ParamsError(f"--variant {variant}: variants.{variant}.of is {of!r}; expected td3 (and --kind td3)")
    if kind not in SLOT_SOURCES:
        raise ParamsError(f"--kind {kind!r}: expected one of {', '.join(SLOT_SOURCES)}")
    if kind == "imported" and not objective:
        raise ParamsError("--kind imported: name the objectives to train (--objective), those without an import entry")
    spec, objectives, names, device = t.spec, t.objectives, t.names, t.device
    parts = plan(objectives, cfg)
    weights = prefix_weights(td3, spec.n_objectives, params)
    shared = td3.shared_prefix_steps
    bar = progress(
        shared + (cfg.total_steps - shared) * len(objectives),
        f"specialists seed {seed}" + (f" ({len(parts)} processes)" if len(parts) > 1 else ""),
    )
    with bar:
        if weights is not None:  # the shared prefix first, here; every part forks from its final state
            run_parts(
                train_prefix,
                [(out, seed, spec, env_p, td3, cfg, device, weights)],
                bar,
                lambda i: f"prefix seed {seed}",
            )
        run_parts(
            train_part,
            [(out, part, seed, spec, env_p, td3, cfg, device, names, SLOT_SOURCES[kind], weights) for part in parts],
            bar,
            lambda i: f"specialists seed {seed}, " + ", ".join(f"obj {k}" for group in parts[i] for k in group),
        )
    remove_stale_checkpoints(out, objectives)
    if weights is not None:
        prefix_checkpoint(out, seed, env_p, td3, cfg, device, weights).clear()
    t.record(provenance, "train_specialist")


def plan(objectives: Sequence[int], cfg: TrainSpecialistParams) -> list[list[list[int]]]:
    """How the stage trains `objectives`: parts (one process each, train_specialist.processes
    of them at most), each a list of groups trained one after another, the specialists of a
    group stacked together (all of the part's if batched, else one per group)."""
    parts = split_evenly([int(k) for k in objectives], cfg.processes)
    return [[part] if cfg.batched else [[k] for k in part] for part in parts]


def train_part(
    out: Path,
    groups: list[list[int]],
    seed: int,
    spec,
    env_p: EnvParams,
    td3: TD3Params,
    cfg: TrainSpecialistParams,
    device,
    names: Sequence[str],
    source: dict | None,
    weights: list[float] | None,
    threads: int,
    *,
    send,
) -> None:
    """Train and save the specialists (seed, k) of `groups`, one group after another (one part
    of `plan`: in this process, or a worker's whole job with `threads` torch threads); `source`:
    what their policy.pt records as their source (SLOT_SOURCES), None for nothing; `weights`:
    the shared prefix's mixed reward (`prefix_weights`), None without one."""
    torch.set_num_threads(threads)
    with sigterm_deferred():  # SIGTERM: checkpoint after the current step and stop
        for group in groups:
            train_group(out, group, seed, spec, env_p, td3, cfg, device, names, send, source, weights)


def prefix_weights(td3: TD3Params, n_objectives: int, params: Path) -> list[float] | None:
    """The weights of the shared prefix's mixed reward (td3.shared_prefix_weights, default equal),
    None when td3.shared_prefix_steps is 0; ParamsError for a wrong count or an all-zero mix."""
    if not td3.shared_prefix_steps:
        return None
    weights = td3.shared_prefix_weights or [1.0 / n_objectives] * n_objectives
    if len(weights) != n_objectives or not any(weights):
        raise ParamsError(
            f"{params}: td3.shared_prefix_weights = {td3.shared_prefix_weights}: expected {n_objectives} "
            "non-negative weights, one per objective, not all zero"
        )
    return [float(w) for w in weights]


def prefix_config(seed: int, env_p: EnvParams, td3: TD3Params, cfg: TrainSpecialistParams) -> dict[str, Any]:
    """What a seed's shared prefix depends on besides code, device and threads: the env, the td3
    section (its length and weights included), the run settings a prefix reads and the seed."""
    return {
        "env": env_p.model_dump(exclude={"objective_names", "reference_point"}),
        "td3": td3.model_dump(),
        "train_specialist": cfg.model_dump(
            exclude={
                "checkpoint_every",
                "device",
                "batched",
                "processes",
                "total_steps",
                "keep_best_every",
                "keep_best_episodes",
            }
        ),
        "seed": seed,
        "prefix": "mixed",
    }


def prefix_checkpoint(
    out: Path, seed: int, env_p: EnvParams, td3: TD3Params, cfg: TrainSpecialistParams, device, weights, send=None
) -> Checkpoint:
    """Where the finished shared prefix of the seed is kept (beside the specialists' checkpoints)
    until every specialist of the stage has been written: a killed stage forks again from it."""
    precision = resolve(cfg.precision, device, max(td3.hidden_sizes))
    fp = run_fingerprint(
        "train_specialist", prefix_config(seed, env_p, td3, cfg) | {"weights": weights}, device, precision=precision
    )
    say = (lambda line: send("say", line)) if send is not None else (lambda line: None)
    return Checkpoint(checkpoint_dir(out, inside=False) / "specialist_prefix.pt", fp, say)


def prefix_run(spec, env_p: EnvParams, td3: TD3Params, cfg: TrainSpecialistParams, seed: int, device, weights):
    """A fresh shared-prefix run: one TD3 on the mixed reward (objective n of the run's n + 1),
    td3.shared_prefix_steps long, without keep-best."""
    short = cfg.model_copy(update={"total_steps": td3.shared_prefix_steps, "keep_best_every": 0})
    env = make_env(env_p.id, env_p.max_episode_steps, env_p.reward_terms)
    return SpecialistsRun([env], spec, td3, short, [(seed, spec.n_objectives)], device, mix=weights)


def train_prefix(
    out: Path,
    seed: int,
    spec,
    env_p: EnvParams,
    td3: TD3Params,
    cfg: TrainSpecialistParams,
    device,
    weights,
    threads,
    *,
    send,
) -> None:
    """Train the seed's shared prefix (td3.shared_prefix_steps), unless a finished one of these
    params is kept already, checkpointing as the specialists do; its final state is kept by
    `prefix_checkpoint` for the specialists to fork from."""
    torch.set_num_threads(threads)
    done = prefix_checkpoint(out, seed, env_p, td3, cfg, device, weights, send)
    if done.load() is not None:
        send("say", f"seed {seed}: forking from the shared prefix kept in {done.path}")
        send("steps", td3.shared_prefix_steps)
        return
    probe = make_env(env_p.id, env_p.max_episode_steps, env_p.reward_terms)
    problem = env_checkpoint_problem(probe)
    probe.close()
    if problem is not None:
        raise ParamsError(
            f"td3.shared_prefix_steps: env {env_p.id} cannot be forked mid-episode ({problem}); set it to 0"
        )
    # the run in progress has the finished prefix's fingerprint: the same params, code and device
    ckpt = Checkpoint(
        checkpoint_dir(out, inside=False) / (CHECKPOINT_PREFIX + "prefix.pt"), done.fp, lambda line: send("say", line)
    )
    with sigterm_deferred():
        drive(
            lambda: prefix_run(spec, env_p, td3, cfg, seed, device, weights),
            ckpt,
            who=f"train_specialist seed {seed}, shared prefix",
            stage="train_specialist",
            resumed=lambda run: f"shared prefix: resuming from step {run.t} of {ckpt.path}",
            save=lambda run: done.save(run.state_dict()),
            send=send,
            periodic=cfg.checkpoint_every > 0,
            every=PROGRESS_EVERY,
        )


def checkpoint_path(out: Path, group: Sequence[int]) -> Path:
    """The checkpoint of the specialists of objectives `group` trained together: beside the
    outputs in .<OUT's name>.resume (OUT is DVC's out, deleted before a rerun), or under
    $MAPEX_RESUME_ROOT in a sweep (pipeline.core.resume.checkpoint_dir)."""
    return checkpoint_dir(out, inside=False) / (CHECKPOINT_PREFIX + "-".join(f"obj{k}" for k in group) + ".pt")


def remove_stale_checkpoints(out: Path, trained: Sequence[int]) -> None:
    """Remove checkpoints left by another grouping of objectives this run has now trained
    (a run killed with batched: true, rerun with batched: false, say): they cannot be resumed
    any more, and a paper-scale one holds gigabytes."""
    for path in checkpoint_dir(out, inside=False).glob(f"{CHECKPOINT_PREFIX}obj*.pt"):
        names = path.name[len(CHECKPOINT_PREFIX) : -len(".pt")].split("-")
        if all(n.startswith("obj") and n[3:].isdigit() for n in names) and {int(n[3:]) for n in names} <= set(trained):
            path.unlink(missing_ok=True)


def run_config(
    seed: int, group: Sequence[int], env_p: EnvParams, td3: TD3Params, cfg: TrainSpecialistParams
) -> dict[str, Any]:
    """What the run of specialists (seed, k) for k in `group`, stacked, depends on besides code,
    device and threads (pipeline.core.resume.run_fingerprint): the params it reads, seed and
    objectives. Not checkpoint_every (when to save changes nothing saved), device (the device
    it resolved to is in the fingerprint), batched or processes (the group is: a group trains
    the same in a worker process as in the stage's own)."""
    return {
        "env": env_p.model_dump(exclude={"objective_names", "reference_point"}),
        "td3": td3.model_dump(),
        "train_specialist": cfg.model_dump(exclude={"checkpoint_every", "device", "batched", "processes"}),
        "seed": seed,
        "objectives": list(group),
    }


def train_group(
    out: Path,
    group: list[int],
    seed: int,
    spec,
    env_p: EnvParams,
    td3: TD3Params,
    cfg: TrainSpecialistParams,
    device: torch.device,
    names: Sequence[str],
    send,
    source: dict | None = None,
    weights: list[float] | None = None,
) -> None:
    """Train and save the specialists (seed, k), k in `group`, together: from their checkpoint
    if one fits, checkpointing every cfg.checkpoint_every steps (pipeline.core.drive). Progress
    goes to `send` (see Relay), in batches of about PROGRESS_EVERY steps."""
    jobs = [(seed, k) for k in group]
    what = ", ".join(f"obj {k} ({names[k]})" for k in group)
    precision = resolve(cfg.precision, device, max(td3.hidden_sizes))
    fp = run_fingerprint("train_specialist", run_config(seed, group, env_p, td3, cfg), device, precision=precision)
    ckpt = Checkpoint(checkpoint_path(out, group), fp, lambda line: send("say", line))
    probe = make_env(env_p.id, env_p.max_episode_steps, env_p.reward_terms)
    problem = env_checkpoint_problem(probe)
    probe.close()
    if cfg.checkpoint_every and problem is not None:
        send("say", f"train_specialist.checkpoint_every: checkpoints off for env {env_p.id} ({problem})")

    def save(run: SpecialistsRun) -> None:
        for result in run.results():
            save_td3_specialist(out / f"obj{result.objective}", result, spec, env_p, td3, cfg, source)
            if result.keep_best is not None:
                send("say", f"seed {seed}, obj {result.objective} ({names[result.objective]}): " + kept_line(result))

    # with a shared prefix, a fresh run forks from the prefix's final state (its `start`)
    fork = None
    if weights is not None:
        kept = prefix_checkpoint(out, seed, env_p, td3, cfg, device, weights, send)

        def fork() -> dict[str, Any]:
            state = kept.load()
            if state is None:
                raise RuntimeError(f"the shared prefix of seed {seed} is not in {kept.path}; rerun the stage")
            return state

    drive(
        lambda: SpecialistsRun(
            [make_env(env_p.id, env_p.max_episode_steps, env_p.reward_terms) for _ in jobs],
            spec,
            td3,
            cfg,
            jobs,
            device,
            fork_from=fork,
        ),
        ckpt,
        who=f"train_specialist seed {seed}, {what}",
        stage="train_specialist",
        resumed=lambda run: f"{what}: resuming from step {run.t} of {ckpt.path}",
        save=save,
        send=send,
        problem=problem,
        periodic=cfg.checkpoint_every > 0,
        hooks=[keep_best_hook],
        every=PROGRESS_EVERY,
    )


def save_td3_specialist(
    out: Path,
    result: SpecialistResult,
    spec,
    env_p,
    td3: TD3Params,
    cfg: TrainSpecialistParams,
    source: dict | None = None,
) -> None:
    """Write one specialist's four artifacts (each atomically) into `out`; with keep-best, also
    keep_best.csv, and policy.pt's metadata gets `keep_best` (the kept step and score, every check);
    with `source` (a slot of the imported kind trained here), policy.pt's metadata gets it as `source`."""
    params = {"td3": td3.model_dump(), "train_specialist": without_fp32(cfg.model_dump())}
    meta = specialist_meta(spec, env_p, td3.hidden_sizes, result.seed, params)
    kb = result.keep_best
    policy_meta = {"source": dict(source)} if source is not None else {}
    if kb is not None:
        policy_meta["keep_best"] = {"step": kb.step, "score": kb.score, "checks": [[t, x] for t, x in kb.checks]}
    save_specialist(out, meta, result.objective, result, policy_meta or None)
    write_text_atomic(out / "returns.csv", returns_csv(result.episodes, spec.n_objectives))
    if kb is not None:
        write_text_atomic(out / "keep_best.csv", keep_best_csv(kb))


def keep_best_csv(kb: KeepBest) -> str:
    """Every keep-best check as CSV: step, score (mean deterministic return on the specialist's
    own objective), kept (1 on the check whose actor policy.pt holds)."""
    return csv_text(["step", "score", "kept"], ([t, f"{score:.6g}", int(t == kb.step)] for t, score in kb.checks))


def kept_line(result: SpecialistResult) -> str:
    """What keep-best kept, in words."""
    kb = result.keep_best
    final_step, final_score = kb.checks[-1]
    if kb.step is None:
        return f"keep-best: no check scored a finite return; the final actor (step {final_step}) is kept"
    return (
        f"keep-best kept the actor of step {kb.step} (score {kb.score:.1f} over {kb.episodes} deterministic "
        f"episodes; the final one, step {final_step}: {final_score:.1f})"
    )


def returns_csv(episodes, n_objectives: int) -> str:
    """Per-episode training returns as CSV: episode, step, length, terminated, obj0, obj1, ...

    Objective columns are named by index (as in evaluate's CSVs) so dvc.yaml's plot axes fit
    every env; the report and README map them to objective names.
    """
    cols = [f"obj{m}" for m in range(n_objectives)]
    return csv_text(
        ["episode", "step", "length", "terminated", *cols],
        ([e.episode, e.end_step, e.length, int(e.terminated), *(f"{x:.6g}" for x in e.returns)] for e in episodes),
    )
