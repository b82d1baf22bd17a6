"""Stage train_specialist: the TD3 specialists of one seed, one per objective, with secondary critics."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Optional

import typer

from pipeline.artifacts import write_text_atomic
from pipeline.buffer import save_buffer
from pipeline.checkpoint import save_critics, save_policy
from pipeline.envs import env_spec, make_env, objective_names
from pipeline.params import ParamsError, RunParams, section
from pipeline.params.train_specialist import TrainSpecialistParams
from pipeline.provenance import provenance
from pipeline.seeding import select_device
from pipeline.specialist import SpecialistResult, train_specialists
from stages.common import PARAMS_OPTION, fmt_vec, progress, read_params, reports_errors


@reports_errors
def train_specialist(
    seed: int = typer.Option(0, help="run seed; with the params it fixes every random draw"),
    out: Path = typer.Option(..., help="output directory of the seed: one obj{K}/ folder per specialist"),
    objective: Optional[list[int]] = typer.Option(
        None, help="train only this objective's specialist (repeatable); default: every entry of params `objectives`"
    ),
    params: Path = PARAMS_OPTION,
) -> None:
    """Train the TD3 specialists of one seed, one per objective of a multi-objective env.

    Params: sections `env`, `objectives` and `train_specialist`. Each specialist's primary
    critic drives its actor while secondary critics for every other objective learn from the
    same batches (train_specialist.secondary_critics). With train_specialist.batched (the
    default) all specialists train in lockstep in this one process, their networks stacked so
    one batched update serves all; each still has its own env, buffer, seeds and minibatches,
    exactly as if trained alone. batched: false trains them one after another.

    Writes OUT/obj{K}/ for each objective K: buffer.zarr (Zarr replay buffer with full reward
    vectors), policy.pt (actor and target actor), critics.pt (all critics, online and target)
    and returns.csv (the undiscounted return vector of every training episode, a learning
    curve for `dvc plots`).
    """
    raw, env_p, cfg = read_params(params, "train_specialist", TrainSpecialistParams)
    objectives = list(objective) if objective else section(raw, "", RunParams, params).objectives
    probe = make_env(env_p.id, env_p.max_episode_steps)
    spec = env_spec(probe, env_p.id, env_p.max_episode_steps)
    probe.close()
    bad = [k for k in objectives if not 0 <= k < spec.n_objectives]
    if bad:
        where = f"--objective {bad[0]}" if objective else f"{params}: objectives = {objectives}"
        raise ParamsError(f"{where}: env {env_p.id} has objectives 0..{spec.n_objectives - 1}")
    names = objective_names(env_p.id, spec.n_objectives, env_p.objective_names)
    device = select_device(cfg.device)
    groups = [objectives] if cfg.batched else [[k] for k in objectives]
    for group in groups:
        jobs = [(seed, k) for k in group]
        envs = [make_env(env_p.id, env_p.max_episode_steps) for _ in jobs]
        what = ", ".join(f"obj {k} ({names[k]})" for k in group)
        bar = progress(cfg.total_steps * len(jobs), f"specialists seed {seed}: {what}")

        def on_step(t: int, records) -> None:
            bar.update(len(records))
            ended = [f"obj {k} {fmt_vec(r.returns)}" for k, r in zip(group, records) if r is not None]
            if ended:
                bar.set_postfix_str("return " + "; ".join(ended), refresh=False)

        with bar:
            results = train_specialists(envs, spec, cfg, jobs, device, on_step=on_step)
        for env in envs:
            env.close()
        for result in results:
            save_specialist(out / f"obj{result.objective}", result, spec, env_p, cfg, device)


def specialist_meta(spec, env_p, hidden_sizes, seed: int, params: dict, device) -> dict:
    """Metadata every specialist artifact carries (TD3 and PDERL alike; extraction cross-checks it)."""
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
        "params": {"env": env_p.model_dump(), **params},
        "provenance": provenance(device),
    }


def save_rl_agent(out: Path, meta: dict, objective: int, result) -> None:
    """Write an RL agent's buffer.zarr, policy.pt and critics.pt (each atomically) into `out`.

    `result` has buffer, actor, actor_target, critic, critic_target and objectives
    (a SpecialistResult, or a PderlResult for PDERL's RL agent)."""
    save_buffer(
        out / "buffer.zarr",
        result.buffer,
        {key: meta[key] for key in ("env_id", "obs_dim", "act_dim", "n_objectives", "max_episode_steps", "seed", "provenance")}
        | {"objective": objective},
    )
    save_policy(out / "policy.pt", result.actor, meta | {"objective": objective}, result.actor_target)
    save_critics(
        out / "critics.pt",
        result.critic,
        result.critic_target,
        meta | {"buffer_objective": objective, "objectives": result.objectives, "source": "joint"},
    )


def save_specialist(out: Path, result: SpecialistResult, spec, env_p, cfg: TrainSpecialistParams, device) -> None:
    """Write one specialist's four artifacts (each atomically) into `out`."""
    meta = specialist_meta(spec, env_p, cfg.hidden_sizes, result.seed, {"train_specialist": cfg.model_dump()}, device)
    save_rl_agent(out, meta, result.objective, result)
    write_text_atomic(out / "returns.csv", returns_csv(result.episodes, spec.n_objectives))


def returns_csv(episodes, n_objectives: int) -> str:
    """Per-episode training returns as CSV: episode, step, length, terminated, obj0, obj1, ...

    Objective columns are named by index (as in evaluate's CSVs) so dvc.yaml's plot axes fit
    every env; the report and README map them to objective names.
    """
    cols = [f"obj{m}" for m in range(n_objectives)]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["episode", "step", "length", "terminated", *cols])
    for e in episodes:
        w.writerow([e.episode, e.end_step, e.length, int(e.terminated), *(f"{x:.6g}" for x in e.returns)])
    return buf.getvalue()
