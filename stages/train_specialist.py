"""Stage train_specialist: one TD3 specialist per (objective, seed), with secondary critics."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import typer

from pipeline.artifacts import write_text_atomic
from pipeline.buffer import save_buffer
from pipeline.checkpoint import save_critics, save_policy
from pipeline.envs import env_spec, make_env, objective_names
from pipeline.params import ParamsError
from pipeline.params.train_specialist import TrainSpecialistParams
from pipeline.seeding import select_device
from pipeline.specialist import train_specialist as train
from stages.common import PARAMS_OPTION, fmt_vec, progress, read_params, reports_errors


@reports_errors
def train_specialist(
    objective: int = typer.Option(..., help="index of the objective this specialist maximises"),
    seed: int = typer.Option(0, help="run seed; with the params it fixes every random draw"),
    out: Path = typer.Option(..., help="output directory (buffer.zarr, policy.pt, critics.pt, returns.csv)"),
    params: Path = PARAMS_OPTION,
) -> None:
    """Train a TD3 specialist that maximises one objective of a multi-objective env.

    Params: sections `env` and `train_specialist` of the params file. While the specialist's
    primary critic drives its actor, secondary critics for every other objective learn from
    the same batches (turn off with train_specialist.secondary_critics: false).

    Writes to OUT: buffer.zarr (Zarr replay buffer with full reward vectors), policy.pt (actor
    and target actor), critics.pt (all critics, online and target) and returns.csv (the
    undiscounted return vector of every training episode, a learning curve for `dvc plots`).
    """
    _, env_p, cfg = read_params(params, "train_specialist", TrainSpecialistParams)
    env = make_env(env_p.id, env_p.max_episode_steps)
    spec = env_spec(env, env_p.id, env_p.max_episode_steps)
    if not 0 <= objective < spec.n_objectives:
        raise ParamsError(f"--objective {objective}: env {env_p.id} has objectives 0..{spec.n_objectives - 1}")
    names = objective_names(env_p.id, spec.n_objectives, env_p.objective_names)
    device = select_device(cfg.device)

    bar = progress(cfg.total_steps, f"specialist obj {objective} ({names[objective]}) seed {seed}")

    def on_step(t: int, record) -> None:
        bar.update(1)
        if record is not None:
            bar.set_postfix_str(f"ep {record.episode} return {fmt_vec(record.returns)}", refresh=False)

    with bar:
        result = train(env, spec, cfg, objective, seed, device, on_step=on_step)
    env.close()

    meta = {
        "env_id": spec.env_id,
        "obs_dim": spec.obs_dim,
        "act_dim": spec.act_dim,
        "n_objectives": spec.n_objectives,
        "max_episode_steps": spec.max_episode_steps,
        "action_low": list(spec.action_low),
        "action_high": list(spec.action_high),
        "hidden_sizes": list(cfg.hidden_sizes),
        "seed": seed,
        "params": {"env": env_p.model_dump(), "train_specialist": cfg.model_dump()},
    }
    st = result.state
    save_buffer(
        out / "buffer.zarr",
        result.buffer.chronological(),
        {k: meta[k] for k in ("env_id", "obs_dim", "act_dim", "n_objectives", "max_episode_steps", "seed")}
        | {"objective": objective},
    )
    save_policy(out / "policy.pt", st.actor, meta | {"objective": objective}, st.actor_target)
    save_critics(
        out / "critics.pt",
        st.critic,
        st.critic_target,
        meta | {"buffer_objective": objective, "objectives": st.objectives, "source": "joint"},
    )
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
