"""Stage extract: MAPEX Algorithm 1 over the specialists (their policy sets, buffers, critics) of one seed, resumable per iteration."""

from __future__ import annotations

import csv
import io
from dataclasses import asdict
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
import typer

from pipeline.core.artifacts import ArtifactError, write_text_atomic
from pipeline.core.buffer import load_buffer
from pipeline.core.checkpoint import load_critics
from pipeline.core.codedeps import closure_files
from pipeline.core.envs import EnvError, env_spec, make_env
from pipeline.evaluation.episodes import eval_seeds, evaluate_policies, evaluate_policy
from pipeline.extraction.mapex import AdvantageConfig, ChildConfig, ChildSeeds, make_children, population_scale
from pipeline.core.nets import Actor
from pipeline.core.pareto import hypervolume, pareto_mask
from pipeline.params import ParamsError, RunParams, section
from pipeline.params.common import EXTRACT_VARIANTS, SPECIALIST_KINDS, method_name
from pipeline.params.extract import ExtractParams
from pipeline.core.policyset import load_policy_set
from pipeline.core.population import Member, actor_state, member_actor, save_population
from pipeline.core.provenance import provenance
from pipeline.core.resume import clear_progress, fingerprint, load_progress, resume_root, save_progress
from pipeline.core.seeding import derive_seeds, select_device
from stages.common import PARAMS_OPTION, fmt_vec, progress, read_params, reports_errors

EXTRACT_TAG = 0xE87AC7
EVAL_STREAM = 0  # evaluation seeds of extraction; the evaluate stage uses fresh streams
SPEC_KEYS = ("env_id", "obs_dim", "act_dim", "n_objectives")

Claim = tuple[Path, dict[str, Any], str]  # (file, its metadata, the key naming its objective)


def check_slot(k: int, seed: int, spec_meta: dict, policy: Claim, buffer: Claim, critics: Claim) -> None:
    """Policies (policies.pt, or policy.pt), buffer and critics of slot obj{k} must describe one
    specialist: objective k, run seed `seed`, the params' env and dims. Raises ArtifactError
    naming both files of the first disagreement (or the file lacking a key and the one it is
    checked against)."""
    files = [policy, buffer, critics]
    expected = {"objective": (k, f"directory obj{k}"), "seed": (seed, f"--seed {seed}")}
    expected |= {key: (spec_meta[key], "params env") for key in SPEC_KEYS}
    for key, (want, source) in expected.items():
        values = []
        for i, (path, meta, objective_key) in enumerate(files):
            name = objective_key if key == "objective" else key
            if name not in meta:
                other = files[1 if i != 1 else 0][0]
                raise ArtifactError(f"{path}: metadata has no {name!r}, so it cannot be checked against {other}")
            values.append((path, name, meta[name]))
        for (pa, na, va), (pb, nb, vb) in zip(values, values[1:]):
            if va != vb:
                raise ArtifactError(f"{pa} ({na} = {va!r}) and {pb} ({nb} = {vb!r}) are not of the same specialist")
        if values[0][2] != want:
            paths = ", ".join(str(p) for p, _, _ in values)
            raise ArtifactError(f"{paths} all have {key} = {values[0][2]!r}, but {source} expects {want!r}")


def check_critics(crit_path: Path, cmeta: dict, buf_path: Path, attrs: dict, mode: str, n_objectives: int) -> None:
    """The critics are of the kind the variant reads (mapex_posthoc: posthoc, else joint), cover every objective and, if
    fitted post hoc, were fitted on exactly this buffer (their recorded buffer checksums)."""
    if cmeta.get("source") != mode:
        raise ArtifactError(f"{crit_path}: critics of source {cmeta.get('source')!r} beside {buf_path}, but the variant "
                            f"reads {mode!r} critics (mapex_posthoc: posthoc; the others: joint)")
    if cmeta["objectives"] != list(range(n_objectives)):
        raise ArtifactError(
            f"{crit_path}: critics covering objectives {cmeta['objectives']}; expected all of {list(range(n_objectives))} "
            f"for {buf_path} (train with train_specialist.secondary_critics: true, or use --variant mapex_posthoc)"
        )
    if mode != "posthoc":
        return
    if "buffer_checksums" not in cmeta:
        raise ArtifactError(f"{crit_path}: the post-hoc critics do not record which buffer they were fitted on "
                            f"(no 'buffer_checksums'), so they cannot be checked against {buf_path}; refit them with fit-critics")
    theirs, ours = cmeta["buffer_checksums"], attrs.get("checksums", {})
    if theirs != ours:
        differ = sorted(k for k in set(theirs) | set(ours) if theirs.get(k) != ours.get(k))
        raise ArtifactError(f"{crit_path} was fitted on another buffer than {buf_path}: the checksums of {differ} differ")


class StartingPolicy(NamedTuple):
    """One policy of a specialist's policy set: it starts in the population."""

    objective: int  # the specialist's objective (its slot obj{k})
    name: str  # its name in the set ("rl", "pop3", ...; "policy" for a policy.pt)
    actor: Actor
    hidden_sizes: list[int]


def policies_path(spec_root: Path, k: int) -> Path:
    """Slot obj{k}'s starting policies: its policy set policies.pt if there is one (a PDERL
    specialist: population actors and RL actor), else its policy.pt (a TD3 specialist)."""
    slot = spec_root / f"obj{k}"
    return slot / "policies.pt" if (slot / "policies.pt").exists() else slot / "policy.pt"


def specialist_kind(meta: dict) -> str | None:
    """'pderl' or 'td3' from a specialist artifact's recorded params; None if it records none."""
    params = meta.get("params")
    if not isinstance(params, dict):
        return None
    return "pderl" if "train_pderl" in params else "td3" if "train_specialist" in params else None


def load_specialists(spec_root: Path, critics_root: Path, objectives: list[int], spec_meta: dict, seed: int, critics_mode: str,
                     kind: str | None = None):
    """Starting policies, buffers and critics of specialists 0..m-1, each slot cross-checked
    (see check_slot; and, given `kind`, that the policies are of that kind where their metadata
    says). Returns (starting policies, slot by slot in each set's order, buffers, critics, the
    files read)."""
    starts, buffers, critics, files = [], [], [], []
    for k in objectives:
        pol_path, buf_path = policies_path(spec_root, k), spec_root / f"obj{k}" / "buffer.zarr"
        crit_path = critics_root / f"obj{k}" / "critics.pt"
        pset = load_policy_set(pol_path)
        data, attrs = load_buffer(buf_path)
        online, _, cmeta = load_critics(crit_path)
        check_slot(k, seed, spec_meta, (pol_path, pset.meta, "objective"), (buf_path, attrs, "objective"), (crit_path, cmeta, "buffer_objective"))
        check_critics(crit_path, cmeta, buf_path, attrs, critics_mode, spec_meta["n_objectives"])
        found = specialist_kind(pset.meta)
        if kind is not None and found is not None and found != kind:
            raise ArtifactError(f"{pol_path}: a {found} specialist, but --kind is {kind!r}")
        starts += [StartingPolicy(k, name, actor, list(pset.meta["hidden_sizes"])) for name, actor in zip(pset.names, pset.actors)]
        buffers.append(data)
        critics.append(online)
        files += [pol_path, buf_path / "zarr.json", crit_path]
    return starts, buffers, critics, files


def child_seeds(seed: int, first: int, k: int) -> list[ChildSeeds]:
    """Streams of the run's children first .. first + k - 1 (counted from 1): child c's depend on
    (seed, c) alone, so with K = 1 child c has the streams iteration c always had."""
    return [ChildSeeds(*derive_seeds(seed, EXTRACT_TAG, c, n=3)) for c in range(first, first + k)]


def history_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=["iteration", "population", "front_size", "env_samples"], lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


def history_row(iteration: int, members: list[Member]) -> dict:
    returns = np.array([m.returns for m in members])
    return {"iteration": iteration, "population": len(members), "front_size": int(pareto_mask(returns).sum()),
            "env_samples": members[-1].env_samples}


def normalised_hypervolume(returns: np.ndarray) -> float:
    """Hypervolume of the returns scaled to [0, 1] by the population's own per-objective range,
    reference at 0: needs no reference point (shown while running; moves when the range does)."""
    lo, span = population_scale(returns)
    return hypervolume((returns - lo) / span, np.zeros(returns.shape[1]))


@reports_errors
def extract(
    seed: int = typer.Option(0, help="run seed (selects the specialists of this seed and seeds every draw)"),
    variant: str = typer.Option("mapex", help="'mapex' (Algorithm 1 with the specialists' joint critics), 'mapex_posthoc' "
                                              "(with critics fitted post hoc, --posthoc) or 'warmup_only' (ablation: epochs = 0)"),
    kind: str = typer.Option("td3", help="the kind of specialists: 'td3' or 'pderl'; the run is method VARIANT_KIND (mapex_td3, ...)"),
    specialists: Path = typer.Option(..., help="directory with, per objective K, obj{K}/policies.pt (a policy set, e.g. PDERL's) "
                                          "or policy.pt (one policy, TD3's), and buffer.zarr, critics.pt"),
    posthoc: Path = typer.Option(None, help="directory with obj{K}/critics.pt fitted post hoc (read by --variant mapex_posthoc)"),
    out: Path = typer.Option(..., help="output directory: population.pt, history.csv"),
    resume_dir: Path = typer.Option(None, help="where progress is checkpointed after every iteration; default "
                                               "$MAPEX_RESUME_ROOT if set (a sweep's shared storage), else data/resume"),
    params: Path = PARAMS_OPTION,
) -> None:
    """Extract a Pareto front from single-objective specialists (MAPEX, Algorithm 1).

    Params: sections `env` (id, max_episode_steps) and `extract`. The population starts as every
    policy of every specialist's policy set (SPECIALISTS/obj{K}/policies.pt, e.g. a PDERL
    population and its RL actor; or the one policy of obj{K}/policy.pt when there is no set),
    each evaluated; each iteration adds extract.children_per_iteration children (1 = Algorithm 1),
    each trained on its own hybrid buffer by mixed-advantage-weighted regression, with parents
    chosen from the whole population. The policies, buffer and critics of each objective must
    agree on objective, seed and env. Progress is checkpointed after each iteration: killed and
    rerun with the same params and inputs, the stage resumes and ends with the same artifacts as
    an uninterrupted run; changed params, inputs or code start over.

    Writes OUT/population.pt (every policy with its origin: the specialist and policy name of a
    starting policy, or a child's parents, target weight and iteration; its returns and
    cumulative env samples) and OUT/history.csv (population, front size and env samples per
    iteration). Hypervolumes are computed downstream from population.pt, so env.reference_point
    is not an input here.
    """
    raw, env_p, cfg = read_params(params, "extract", ExtractParams)
    run = section(raw, "", RunParams, params)
    if variant not in EXTRACT_VARIANTS:
        raise ParamsError(f"--variant {variant!r}: expected one of {list(EXTRACT_VARIANTS)}")
    if kind not in SPECIALIST_KINDS:
        raise ParamsError(f"--kind {kind!r}: expected one of {list(SPECIALIST_KINDS)}")
    method = method_name(variant, kind)
    critics_mode = "posthoc" if variant == "mapex_posthoc" else "joint"
    try:
        cfg = cfg.resolved(env_p.id)
    except ValueError as exc:
        raise ParamsError(f"{params}: {exc}") from None
    if variant == "warmup_only":
        cfg = cfg.model_copy(update={"epochs": 0})
    k_children = cfg.children_per_iteration
    envs = [make_env(env_p.id, env_p.max_episode_steps) for _ in range(cfg.eval_episodes * k_children)]
    spec = env_spec(envs[0], env_p.id, env_p.max_episode_steps)
    if spec.n_objectives != 2:
        raise EnvError(
            f"env.id = {env_p.id!r} has {spec.n_objectives} objectives; MAPEX gap identification is "
            "defined for 2 (the paper leaves N >= 3 to future work)"
        )
    if sorted(run.objectives) != list(range(spec.n_objectives)):
        raise ParamsError(f"{params}: objectives = {run.objectives}: extraction needs one specialist per objective 0..{spec.n_objectives - 1}")
    if critics_mode == "posthoc" and posthoc is None:
        raise ParamsError("--variant mapex_posthoc reads post-hoc critics, but no --posthoc directory was given")
    spec_meta = {"env_id": spec.env_id, "obs_dim": spec.obs_dim, "act_dim": spec.act_dim, "n_objectives": spec.n_objectives}
    bounds = {"action_low": list(spec.action_low), "action_high": list(spec.action_high)}
    critics_root = posthoc if critics_mode == "posthoc" else specialists
    starts, buffers, critics, files = load_specialists(
        specialists, critics_root, list(range(spec.n_objectives)), spec_meta, seed, critics_mode, kind
    )

    device = select_device(cfg.device)
    actors = [s.actor.to(device) for s in starts]
    critics = [c.to(device) for c in critics]
    # Everything that can change the artifacts: params, inputs, every code file the stage
    # runs, and the device and thread count (which can change the last bits of results).
    # env.reference_point is not among them: it does not change what extraction computes.
    config = {"env": env_p.model_dump(exclude={"objective_names", "reference_point"}), "extract": cfg.model_dump(), "seed": seed, "variant": variant,
              "kind": kind, "critics": critics_mode}
    fp = fingerprint({**config, "device": str(device), "threads": torch.get_num_threads()}, files + closure_files("stages.extract"))
    progress_dir = (resume_dir or resume_root("data/resume")) / "extract" / method / f"seed{seed}"
    n_start = len(starts)  # the starting policies: member ids 0 .. n_start - 1
    saved = load_progress(progress_dir, fp)
    if saved is not None and (len(saved[0]) < n_start or (len(saved[0]) - n_start) % k_children):
        saved = None  # not the starting policies plus whole iterations: not progress this code wrote

    if saved is None:
        members, history, samples = [], [], 0
        # Member i is evaluated on stream i: a specialist's single policy (TD3) is member k.
        for i, (start, actor) in enumerate(zip(starts, actors)):
            res = evaluate_policy(actor, envs, eval_seeds(seed, EVAL_STREAM, i, cfg.eval_episodes))
            samples += res.env_samples
            members.append(Member(
                origin="specialist", objective=start.objective, iteration=0, parents=[], target_weight=None,
                returns=res.mean.tolist(), returns_std=res.std.tolist(), eval_episodes=cfg.eval_episodes,
                env_samples=samples, hidden_sizes=start.hidden_sizes, actor=actor_state(actor), policy_name=start.name,
            ))
        history.append(history_row(0, members))
        written = save_progress(progress_dir, fp, [asdict(m) for m in members], 0, {"history": history})
    else:
        items, extra = saved
        members = [Member(**m) for m in items]
        history = extra["history"]
        samples = members[-1].env_samples
        written = len(members)
    done = (len(members) - n_start) // k_children
    if saved is not None:
        typer.echo(f"resuming from iteration {done} of {cfg.iterations} ({progress_dir})", err=True)
    pop_actors = actors + [member_actor(m, {**spec_meta, **bounds}).to(device) for m in members[n_start:]]
    child_cfg = ChildConfig(
        tuple(cfg.hidden_sizes), cfg.child_buffer_size, cfg.weight_norm, cfg.warmup_steps, cfg.warmup_lr, cfg.warmup_batch_size,
        AdvantageConfig(cfg.epochs, cfg.beta, cfg.omega_max, cfg.lr, cfg.batch_size, cfg.max_grad_norm, cfg.advantage_recompute, cfg.advantage_norm),
    )

    bar = progress(cfg.iterations * k_children, f"extract {method} seed {seed}", unit="child")
    bar.update(done * k_children)
    with bar:
        for it in range(done + 1, cfg.iterations + 1):
            returns = np.array([m.returns for m in members])
            children = make_children(returns, pop_actors, buffers, critics, child_cfg, child_seeds(seed, len(members) - n_start + 1, k_children), device)
            ids = range(len(members), len(members) + k_children)
            results = evaluate_policies([a for a, _ in children], envs, [eval_seeds(seed, EVAL_STREAM, i, cfg.eval_episodes) for i in ids])
            for (child, rec), res in zip(children, results):
                samples += res.env_samples
                members.append(Member(
                    origin="child", objective=None, iteration=it, parents=list(rec.parents), target_weight=rec.weight.tolist(),
                    returns=res.mean.tolist(), returns_std=res.std.tolist(), eval_episodes=cfg.eval_episodes,
                    env_samples=samples, hidden_sizes=list(cfg.hidden_sizes), actor=actor_state(child), policy_name=None,
                ))
                pop_actors.append(child)
            history.append(history_row(it, members))
            written = save_progress(progress_dir, fp, [asdict(m) for m in members[-k_children:]], written, {"history": history})
            returns = np.array([m.returns for m in members])
            bar.set_postfix_str(f"front {history[-1]['front_size']} HV(norm) {normalised_hypervolume(returns):.3f} child {fmt_vec(results[-1].mean)}", refresh=False)
            bar.update(k_children)

    meta = {**spec_meta, **bounds, "seed": seed, "variant": method, "params": config, "provenance": provenance(device)}
    save_population(out / "population.pt", members, meta)
    write_text_atomic(out / "history.csv", history_csv(history))
    clear_progress(progress_dir)
