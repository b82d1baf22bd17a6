"""Stage interpolate: the weight-space interpolation baseline from one seed's specialists (pipeline/baselines/interpolate.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from pipeline.baselines.interpolate import interpolate as interpolate_policies
from pipeline.baselines.interpolate import mixing_weights, starts_problem
from pipeline.core.alignment import MixOptions, buffer_states, mixer
from pipeline.core.artifacts import ArtifactError
from pipeline.core.buffer import load_buffer
from pipeline.core.envs import EnvError, env_spec, make_env, spec_meta
from pipeline.core.policyset import load_policy_set
from pipeline.core.population import save_population
from pipeline.core.provenance import write_provenance
from pipeline.core.specialist import StartingPolicy, check_slot, kind_from_meta, policies_path, training_frames
from pipeline.params import ParamsError, section
from pipeline.params.extract import ExtractParams
from pipeline.params.interpolate import InterpolateParams
from pipeline.params.methods import SPECIALIST_KINDS, method_name
from stages.common import (
    PARAMS_OPTION,
    PROVENANCE_OPTION,
    fmt_vec,
    method_option,
    progress,
    read_params,
    reports_errors,
    require_every_objective,
    require_variant_of,
)


def load_starts(
    specialists: Path, n_objectives: int, seed: int, meta: dict, kind: str
) -> tuple[list[StartingPolicy], int | None]:
    """Every policy of every objective's policy set (SPECIALISTS/obj{K}/policies.pt, else
    policy.pt), checked to be of objective K, run seed `seed`, the env of `meta` and `kind`
    where its metadata says, and the env frames the specialists trained on (`training_frames`).
    No buffer or critic is read: interpolation needs neither."""
    starts, metas = [], []
    for k in range(n_objectives):
        path = policies_path(specialists / f"obj{k}")
        pset = load_policy_set(path)
        found = kind_from_meta(pset.meta)
        if found is not None and found != kind:
            raise ArtifactError(f"{path}: a {found} specialist, but --kind is {kind!r}")
        check_slot(k, seed, meta, [(path, pset.meta, "objective")])
        hidden = list(pset.meta["hidden_sizes"])
        starts += [StartingPolicy(k, name, actor, hidden) for name, actor in zip(pset.names, pset.actors)]
        metas.append(pset.meta)
    return starts, training_frames(metas)


def load_states(specialists: Path, n_objectives: int, count: int, seed: int):
    """`count` states drawn from the specialists' buffers (SPECIALISTS/obj{K}/buffer.zarr), in
    equal shares (pipeline.core.alignment.buffer_states, generator `seed`): what REPAIR and
    RegMean measure on. A slot without a buffer is a one-line error naming it."""
    buffers = []
    for k in range(n_objectives):
        path = specialists / f"obj{k}" / "buffer.zarr"
        if not path.exists():
            raise ArtifactError(
                f"{path}: no replay buffer, which interpolate.repair and interpolate.mix: regmean measure states on "
                "(set both off, or give the specialist its buffer)"
            )
        buffers.append(load_buffer(path)[0])
    return buffer_states(buffers, count, seed)


@reports_errors
def interpolate(
    seed: int = typer.Option(
        0, help="run seed (selects the specialists of this seed and seeds the evaluation episodes)"
    ),
    kind: str = typer.Option(
        "td3", help="the kind of specialists: 'td3', 'pderl' or 'imported'; the run is method interpolate_KIND"
    ),
    specialists: Path = typer.Option(
        ..., help="directory with, per objective K, obj{K}/policies.pt (a policy set) or obj{K}/policy.pt"
    ),
    out: Path = typer.Option(..., help="output directory: population.pt"),
    method: Optional[str] = method_option("interpolate_KIND", "sections interpolate and extract"),
    params: Path = PARAMS_OPTION,
    provenance: Optional[Path] = PROVENANCE_OPTION,
) -> None:
    """The interpolation baseline (not in the paper): policies mixed from the specialists' weights.

    Params: sections `env` (id, max_episode_steps), `objectives` (every objective 0..m-1),
    `interpolate` and the extract keys it defaults to (iterations, children_per_iteration,
    eval_episodes). The population starts as every policy of every specialist's policy set,
    each evaluated on the episodes extraction evaluates it on. Per objective, the policy of its
    set with the highest evaluated return on that objective is the one mixed. Then one policy
    per point w of an evenly spaced simplex grid (N = 2: mixing weights l = 1/H .. (H-1)/H between
    the two specialists; the specialists themselves, l = 0 and 1, are the population's starting
    policies), at most interpolate.policies of them (null: extract.iterations x
    extract.children_per_iteration, the children of the MAPEX run it is compared with), each with
    parameters sum_i w_i theta_i, evaluated on interpolate.eval_episodes episodes (null:
    extract.eval_episodes). Its only env frames are those evaluations. Specialists whose actors
    differ in architecture, or are TorchScript or torch.export programs, are a one-line error.

    Aligned interpolation (issue 61, not in the paper; pipeline/core/alignment.py):
    interpolate.align: weights permutes the other specialists' hidden units to match the first's
    (weight matching) before mixing; interpolate.repair rescales each mixed policy's hidden
    preactivations to the specialists' statistics; interpolate.mix: regmean merges each layer by
    least squares on its inputs. REPAIR and RegMean read interpolate.states states from the
    specialists' buffers (obj{K}/buffer.zarr). Actors whose hidden layers cannot be permuted are
    mixed plainly, and the run's metadata says so in one line (the report shows it).

    Writes OUT/population.pt (as extract's: origin 'interpolated', target_weight the mixing
    weights, parents the specialists mixed, iteration grid point // children_per_iteration + 1);
    evaluate, score and report read it like any method's. With --provenance, what produced the
    run (pipeline.core.provenance) goes to that file, outside OUT.
    """
    if kind not in SPECIALIST_KINDS:
        raise ParamsError(f"--kind {kind!r}: expected one of {list(SPECIALIST_KINDS)}")
    raw, env_p, cfg, run_p = read_params(params, "interpolate", InterpolateParams, method)
    base = method_name("interpolate", kind)
    require_variant_of(raw, method, base, params)
    ext = section(raw, "extract", ExtractParams, params)
    policies = cfg.policies if cfg.policies is not None else ext.iterations * ext.children_per_iteration
    episodes = cfg.eval_episodes or ext.eval_episodes
    envs = [make_env(env_p.id, env_p.max_episode_steps, env_p.reward_terms) for _ in range(episodes)]
    try:
        spec = env_spec(envs[0], env_p.id, env_p.max_episode_steps)
        if spec.n_objectives < 2:
            raise EnvError(f"env.id = {env_p.id!r} has 1 objective; interpolation mixes 2 or more specialists")
        objectives = run_p.objectives
        require_every_objective(objectives, spec.n_objectives, env_p.id, params, "interpolation")
        meta = spec_meta(spec)
        starts, specialist_frames = load_starts(specialists, spec.n_objectives, seed, meta, kind)
        problem = starts_problem(starts)
        if problem is not None:  # e.g. imported specialists of different nets
            raise ArtifactError(f"{specialists}: cannot interpolate: {problem}")
        options = MixOptions(cfg.align, cfg.repair, cfg.mix, cfg.regmean_alpha)
        obs = load_states(specialists, spec.n_objectives, cfg.states, seed) if options.needs_states else None
        fallback: list[str] = []

        def make_mixer(actors):
            make, line = mixer(actors, options, obs)
            if line is not None:
                fallback.append(line)
                typer.echo(f"interpolate {kind} seed {seed}: {line}", err=True)
            return make

        total = len(starts) + len(mixing_weights(spec.n_objectives, policies))
        costs: list[dict] = []  # per-iteration cost rows, for the provenance record
        with progress(total, f"interpolate {kind} seed {seed}", unit="policy") as bar:

            def shown(member) -> None:
                bar.set_postfix_str(f"{member.origin} return {fmt_vec(member.returns)}", refresh=False)
                bar.update(1)

            members = interpolate_policies(
                starts,
                spec.n_objectives,
                policies,
                ext.children_per_iteration,
                episodes,
                seed,
                envs,
                shown,
                costs,
                make_mixer=None if options.plain else make_mixer,
            )
    finally:
        for env in envs:
            env.close()
    config = {
        "env": env_p.model_dump(exclude={"objective_names", "reference_point"}),
        "interpolate": {"policies": policies, "eval_episodes": episodes}
        | ({} if options.plain else cfg.model_dump(include={"align", "repair", "mix", "regmean_alpha", "states"})),
        "children_per_iteration": ext.children_per_iteration,
        "seed": seed,
        "kind": kind,
    }
    run_meta = meta | {"seed": seed, "method": method or base, "params": config, "specialist_frames": specialist_frames}
    if not options.plain:
        run_meta["mixing"] = options.describe()
    if fallback:
        run_meta["mixing_fallback"] = fallback[0]
    save_population(out / "population.pt", members, run_meta)
    write_provenance(provenance, "interpolate", "cpu", cost={"iterations": costs})
