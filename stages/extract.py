"""Stage extract: MAPEX Algorithm 1 over the specialists of one seed, resumable per iteration."""

from __future__ import annotations

import csv
import io
from dataclasses import asdict
from pathlib import Path
import numpy as np
import torch
import typer

from pipeline.artifacts import ArtifactError, write_text_atomic
from pipeline.buffer import load_buffer
from pipeline.checkpoint import check_matches, load_critics, load_policy
from pipeline.envs import EnvError, env_spec, make_env
from pipeline.evaluation import eval_seeds, evaluate_policy
from pipeline.extraction import AdvantageConfig, make_child
from pipeline.pareto import hypervolume, pareto_mask
from pipeline.params import ParamsError, RunParams, section
from pipeline.params.extract import ExtractParams
from pipeline.population import Member, actor_state, member_actor, save_population
import pipeline.evaluation
import pipeline.extraction
import pipeline.nets
import pipeline.pareto
from pipeline.resume import clear_progress, fingerprint, load_progress, save_progress
from pipeline.seeding import derive_seeds, select_device
from stages.common import PARAMS_OPTION, fmt_vec, progress, read_params, reports_errors

EXTRACT_TAG = 0xE87AC7
EVAL_STREAM = 0  # evaluation seeds of extraction; the evaluate stage uses fresh streams


def load_specialists(spec_root: Path, critics_root: Path, objectives: list[int], spec_meta: dict):
    """Policies, buffers and critics of specialists 0..m-1, checked against the env and each other."""
    actors, hidden, buffers, critics, files = [], [], [], [], []
    for k in objectives:
        pol_path, buf_path = spec_root / f"obj{k}" / "policy.pt", spec_root / f"obj{k}" / "buffer.zarr"
        crit_path = critics_root / f"obj{k}" / "critics.pt"
        actor, meta = load_policy(pol_path)
        check_matches(pol_path, meta, spec_meta, "params env")
        data, attrs = load_buffer(buf_path)
        check_matches(buf_path, attrs, spec_meta, "params env")
        if attrs["objective"] != k:
            raise ArtifactError(f"{buf_path}: buffer of objective {attrs['objective']}, expected {k}")
        online, _, cmeta = load_critics(crit_path)
        check_matches(crit_path, cmeta, spec_meta, "params env")
        if cmeta["buffer_objective"] != k or cmeta["objectives"] != list(range(spec_meta["n_objectives"])):
            raise ArtifactError(
                f"{crit_path}: critics of buffer {cmeta['buffer_objective']} covering objectives {cmeta['objectives']}; "
                f"expected buffer {k} covering all of {list(range(spec_meta['n_objectives']))} "
                "(train with train_specialist.secondary_critics: true, or use extract.critics: posthoc)"
            )
        actors.append(actor)
        hidden.append(list(meta["hidden_sizes"]))
        buffers.append(data)
        critics.append(online)
        files += [pol_path, buf_path / "zarr.json", crit_path]
    return actors, hidden, buffers, critics, files


def history_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=["iteration", "population", "front_size", "hypervolume", "env_samples"], lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


def history_row(iteration: int, members: list[Member], ref: list[float]) -> dict:
    returns = np.array([m.returns for m in members])
    return {
        "iteration": iteration,
        "population": len(members),
        "front_size": int(pareto_mask(returns).sum()),
        "hypervolume": f"{hypervolume(returns, ref):.6g}",
        "env_samples": members[-1].env_samples,
    }


@reports_errors
def extract(
    seed: int = typer.Option(0, help="run seed (selects the specialists of this seed and seeds every draw)"),
    variant: str = typer.Option("mapex", help="'mapex' (Algorithm 1) or 'warmup_only' (ablation: epochs = 0)"),
    specialists: Path = typer.Option(..., help="directory with obj{K}/policy.pt, buffer.zarr, critics.pt per objective"),
    posthoc: Path = typer.Option(None, help="directory with obj{K}/critics.pt fitted post hoc (used if extract.critics = posthoc)"),
    out: Path = typer.Option(..., help="output directory: population.pt, history.csv"),
    resume_dir: Path = typer.Option(Path("data/resume"), help="where progress is checkpointed after every iteration"),
    params: Path = PARAMS_OPTION,
) -> None:
    """Extract a Pareto front from single-objective specialists (MAPEX, Algorithm 1).

    Params: sections `env` (reference_point needed for the hypervolume history) and `extract`.
    The population starts as the specialists; each iteration adds one child trained on a
    hybrid buffer by mixed-advantage-weighted regression. Progress is checkpointed after each
    iteration: killed and rerun with the same params and inputs, the stage resumes and ends
    with the same artifacts as an uninterrupted run; changed params or inputs start over.

    Writes OUT/population.pt (every policy with its returns, parents, target weight, iteration
    and cumulative env samples) and OUT/history.csv (front size, hypervolume and env samples
    per iteration).
    """
    raw, env_p, cfg = read_params(params, "extract", ExtractParams)
    run = section(raw, "", RunParams, params)
    if variant not in ("mapex", "warmup_only"):
        raise ParamsError(f"--variant {variant!r}: expected 'mapex' or 'warmup_only'")
    try:
        cfg = cfg.resolved(env_p.id)
    except ValueError as exc:
        raise ParamsError(f"{params}: {exc}") from None
    if variant == "warmup_only":
        cfg = cfg.model_copy(update={"epochs": 0})
    envs = [make_env(env_p.id, env_p.max_episode_steps) for _ in range(cfg.eval_episodes)]
    spec = env_spec(envs[0], env_p.id, env_p.max_episode_steps)
    if spec.n_objectives != 2:
        raise EnvError(
            f"env.id = {env_p.id!r} has {spec.n_objectives} objectives; MAPEX gap identification is "
            "defined for 2 (the paper leaves N >= 3 to future work)"
        )
    ref = env_p.reference_point
    if ref is None or len(ref) != spec.n_objectives:
        raise ParamsError(f"{params}: env.reference_point = {ref!r}: expected a list of {spec.n_objectives} numbers")
    if sorted(run.objectives) != list(range(spec.n_objectives)):
        raise ParamsError(f"{params}: objectives = {run.objectives}: extraction needs one specialist per objective 0..{spec.n_objectives - 1}")
    if cfg.critics == "posthoc" and posthoc is None:
        raise ParamsError("extract.critics = 'posthoc' but no --posthoc directory was given")
    spec_meta = {"env_id": spec.env_id, "obs_dim": spec.obs_dim, "act_dim": spec.act_dim, "n_objectives": spec.n_objectives}
    critics_root = posthoc if cfg.critics == "posthoc" else specialists
    actors, hidden, buffers, critics, files = load_specialists(specialists, critics_root, list(range(spec.n_objectives)), spec_meta)

    device = select_device(cfg.device)
    actors = [a.to(device) for a in actors]
    critics = [c.to(device) for c in critics]
    # Everything that can change the artifacts: params, inputs, the code that computes them,
    # and the device and thread count (which can change the last bits of CPU/GPU results).
    config = {"env": env_p.model_dump(exclude={"objective_names"}), "extract": cfg.model_dump(), "seed": seed, "variant": variant}
    code = [pipeline.extraction.__file__, pipeline.evaluation.__file__, pipeline.nets.__file__, pipeline.pareto.__file__, __file__]
    fp = fingerprint({**config, "device": str(device), "threads": torch.get_num_threads()}, files + code)
    progress_dir = resume_dir / "extract" / variant / f"seed{seed}"
    saved = load_progress(progress_dir, fp)

    def evaluate(actor, policy_id: int, samples_before: int):
        res = evaluate_policy(actor, envs, eval_seeds(seed, EVAL_STREAM, policy_id, cfg.eval_episodes))
        return res, samples_before + res.env_samples

    if saved is None:
        members, history, samples = [], [], 0
        for k, actor in enumerate(actors):
            res, samples = evaluate(actor, k, samples)
            members.append(Member("specialist", k, 0, [], None, res.mean.tolist(), res.std.tolist(), cfg.eval_episodes, samples, hidden[k], actor_state(actor)))
        history.append(history_row(0, members, ref))
        written = save_progress(progress_dir, fp, [asdict(m) for m in members], 0, {"history": history})
    else:
        items, extra = saved
        members = [Member(**m) for m in items]
        history = extra["history"]
        samples = members[-1].env_samples
        written = len(members)
    n_spec = spec.n_objectives
    done = len(members) - n_spec
    pop_actors = actors + [member_actor(m, {**spec_meta, "action_low": list(spec.action_low), "action_high": list(spec.action_high)}).to(device) for m in members[n_spec:]]
    adv = AdvantageConfig(cfg.epochs, cfg.beta, cfg.omega_max, cfg.lr, cfg.batch_size, cfg.max_grad_norm, cfg.advantage_recompute, cfg.advantage_norm)

    bar = progress(cfg.iterations, f"extract {variant} seed {seed}", unit="child")
    bar.update(done)
    with bar:
        for it in range(done + 1, cfg.iterations + 1):
            s_np, s_torch = derive_seeds(seed, EXTRACT_TAG, it, n=2)
            returns = np.array([m.returns for m in members])
            child, rec = make_child(
                returns, pop_actors, buffers, critics,
                hidden_sizes=cfg.hidden_sizes, child_buffer_size=cfg.child_buffer_size, weight_norm=cfg.weight_norm,
                warmup_steps=cfg.warmup_steps, warmup_lr=cfg.warmup_lr, warmup_batch_size=cfg.warmup_batch_size,
                adv=adv, rng=np.random.default_rng(s_np), torch_seed=s_torch, device=device,
            )
            res, samples = evaluate(child, len(members), samples)
            members.append(Member("child", None, it, list(rec.parents), rec.weight.tolist(), res.mean.tolist(), res.std.tolist(), cfg.eval_episodes, samples, list(cfg.hidden_sizes), actor_state(child)))
            pop_actors.append(child)
            history.append(history_row(it, members, ref))
            written = save_progress(progress_dir, fp, [asdict(members[-1])], written, {"history": history})
            bar.set_postfix_str(f"front {history[-1]['front_size']} HV {float(history[-1]['hypervolume']):.4g} child {fmt_vec(res.mean)}", refresh=False)
            bar.update(1)

    meta = {
        **spec_meta,
        "action_low": list(spec.action_low),
        "action_high": list(spec.action_high),
        "seed": seed,
        "variant": variant,
        "reference_point": list(ref),
        "params": config,
    }
    save_population(out / "population.pt", members, meta)
    write_text_atomic(out / "history.csv", history_csv(history))
    clear_progress(progress_dir)
