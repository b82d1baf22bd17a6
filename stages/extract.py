"""Stage extract: MAPEX Algorithm 1 over the specialists (their policy sets, buffers, critics) of one seed, resumable per iteration."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from pipeline.core.artifacts import write_text_atomic
from pipeline.core.drive import drive
from pipeline.core.envs import EnvError, env_spec, make_env, spec_meta
from pipeline.core.population import save_population
from pipeline.core.precision import resolve, without_fp32
from pipeline.core.provenance import write_provenance
from pipeline.core.resume import Checkpoint, resume_root, run_fingerprint
from pipeline.core.seeding import select_device
from pipeline.core.specialist import load_slots, slot_sources, training_frames
from pipeline.extraction.run import ExtractionRun, history_csv, variant_config
from pipeline.params import ParamsError
from pipeline.params.extract import ExtractParams, without_default_extensions
from pipeline.params.methods import EXTRACT_VARIANTS, SPECIALIST_KINDS, TRAINED_KINDS, method_name
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


def variant_params(
    cfg: ExtractParams, env_id: str, variant: str, kind: str, posthoc: Path | None, params: Path
) -> ExtractParams:
    """The `extract` section as variant VARIANT from KIND specialists runs it (resolved for the
    env); a bad --variant, --kind or a missing --posthoc is a one-line error."""
    if variant not in EXTRACT_VARIANTS:
        raise ParamsError(f"--variant {variant!r}: expected one of {list(EXTRACT_VARIANTS)}")
    if kind not in SPECIALIST_KINDS:
        raise ParamsError(f"--kind {kind!r}: expected one of {list(SPECIALIST_KINDS)}")
    if variant == "mapex_posthoc" and posthoc is None:
        raise ParamsError("--variant mapex_posthoc reads post-hoc critics, but no --posthoc directory was given")
    try:
        return variant_config(cfg.resolved(env_id), variant)
    except ValueError as exc:
        raise ParamsError(f"{params}: {exc}") from None


@reports_errors
def extract(
    seed: int = typer.Option(0, help="run seed (selects the specialists of this seed and seeds every draw)"),
    variant: str = typer.Option(
        "mapex",
        help="'mapex' (Algorithm 1 with the specialists' joint critics), 'mapex_posthoc' "
        "(with critics fitted post hoc, --posthoc) or 'warmup_only' (ablation: epochs = 0)",
    ),
    kind: str = typer.Option(
        "td3",
        help="the kind of specialists: 'td3', 'pderl' or 'imported'; the run is method VARIANT_KIND (mapex_td3, ...)",
    ),
    specialists: Path = typer.Option(
        ...,
        help="directory with, per objective K, obj{K}/policies.pt (a policy set, e.g. PDERL's) "
        "or policy.pt (one policy, TD3's), and buffer.zarr, critics.pt (not read by --variant warmup_only)",
    ),
    posthoc: Path = typer.Option(
        None, help="directory with obj{K}/critics.pt fitted post hoc (read by --variant mapex_posthoc)"
    ),
    method: Optional[str] = method_option("VARIANT_KIND", "section extract"),
    out: Path = typer.Option(..., help="output directory: population.pt, history.csv"),
    resume_dir: Path = typer.Option(
        None,
        help="where progress is checkpointed after every iteration; default "
        "$MAPEX_RESUME_ROOT if set (a sweep's shared storage), else data/resume",
    ),
    params: Path = PARAMS_OPTION,
    provenance: Optional[Path] = PROVENANCE_OPTION,
) -> None:
    """Extract a Pareto front from single-objective specialists (MAPEX, Algorithm 1).

    Params: sections `env` (id, max_episode_steps) and `extract`. The population starts as every
    policy of every specialist's policy set (SPECIALISTS/obj{K}/policies.pt, e.g. a PDERL
    population and its RL actor; or the one policy of obj{K}/policy.pt when there is no set),
    each evaluated; each iteration adds extract.children_per_iteration children (1 = Algorithm 1),
    each trained on its own hybrid buffer by mixed-advantage-weighted regression, with parents
    chosen from the whole population. The policies, buffer and critics of each objective must
    agree on objective, seed and env. --variant warmup_only (epochs = 0) reads no critics, so
    it also runs from specialists without critics.pt (imported ones). Progress is checkpointed after each iteration: killed and
    rerun with the same params and inputs, the stage resumes and ends with the same artifacts as
    an uninterrupted run; changed params, inputs or code start over. On SIGTERM the stage
    stops after the current iteration, its checkpoint written, with exit code 143.

    Writes OUT/population.pt (every policy with its origin: the specialist and policy name of a
    starting policy, or a child's parents, target weight and iteration; its returns and
    cumulative env samples) and OUT/history.csv (population, front size and env samples per
    iteration). Hypervolumes are computed downstream from population.pt, so env.reference_point
    is not an input here. With --provenance, what produced the run (pipeline.core.provenance)
    goes to that file, outside OUT.

    Not in the paper, off by default (docs/manual.md, "Hybrid extraction", "Early stopping"):
    extract.init interpolate starts each child from its parents' mixed weights (falling back to
    the paper's start, counted in meta init_fallbacks, where they cannot be mixed);
    extract.seed_interpolation adds the interpolation baseline's policies to the starting
    population (origin 'interpolated'); extract.stop_patience stops the run early (meta
    stopped_at). The provenance record's cost holds each iteration's training and evaluation
    seconds.

    A child whose training diverges (a NaN or infinity in its warm-up or advantage-weighted
    loss or its weights, e.g. from a critic that holds one) stops the stage with one line
    naming the seed, iteration, step and loss, and exit code 3; nothing is written and the
    checkpoint of the last whole iteration stays (docs/manual.md, "When training diverges").
    """
    raw, env_p, cfg, run_p = read_params(params, "extract", ExtractParams, method)
    base = method_name(variant, kind)
    require_variant_of(raw, method, base, params)
    cfg = variant_params(cfg, env_p.id, variant, kind, posthoc, params)
    envs = [
        make_env(env_p.id, env_p.max_episode_steps, env_p.reward_terms)
        for _ in range(cfg.eval_episodes * cfg.children_per_iteration)
    ]
    spec = env_spec(envs[0], env_p.id, env_p.max_episode_steps)
    if spec.n_objectives < 2:
        raise EnvError(
            f"env.id = {env_p.id!r} has {spec.n_objectives} objective; MAPEX extracts a Pareto front of "
            "2 or more objectives (N >= 3: docs/n_objectives.md)"
        )
    require_every_objective(run_p.objectives, spec.n_objectives, env_p.id, params, "extraction")
    critics_mode = "posthoc" if variant == "mapex_posthoc" else "joint"
    # warm-up only (epochs = 0) reads no critics, so it runs from specialists without any
    # (imported ones). Its recorded config keeps "joint" from the kinds trained here, as it always
    # had (their artifacts stay bitwise the same), and says "none" from imported specialists.
    reads_critics = variant != "warmup_only"
    meta = spec_meta(spec)
    slots = load_slots(
        specialists,
        spec.n_objectives,
        seed=seed,
        spec_meta=meta,
        kind=kind,
        critics_mode=critics_mode,
        critics_root=posthoc if critics_mode == "posthoc" else specialists,
        critics=reads_critics,
    )
    sources = slot_sources(slots) if kind == "imported" else None
    device = select_device(cfg.device)
    precision = resolve(cfg.precision, device, max(cfg.hidden_sizes))  # as ExtractionRun resolves it
    # env.reference_point is not in the config: it does not change what extraction computes;
    # nor, with 2 objectives, extract.facet_bridge_ratio (the paper's edges never read it), so
    # 2-objective populations and their resume fingerprints are what they were before it existed;
    # nor precision where it is fp32 (also the artifact's record: fp32 left out, precision.py)
    env_cfg = env_p.model_dump(exclude={"objective_names", "reference_point"})
    config = {
        "env": env_cfg,
        # the extensions (hybrid extraction, early stopping) only where set: a paper run's record is as before them
        "extract": without_default_extensions(
            without_fp32(cfg.model_dump(exclude={"facet_bridge_ratio"} if spec.n_objectives == 2 else None))
        ),
        "seed": seed,
        "variant": variant,
        "kind": kind,
        "critics": critics_mode if reads_critics or kind in TRAINED_KINDS else "none",
    }
    method = method or base
    ckpt = Checkpoint(
        (resume_dir or resume_root("data/resume")) / "extract" / method / f"seed{seed}" / "state.pt",
        run_fingerprint("extract", config, device, [f for s in slots for f in s.files], precision),
        lambda line: typer.echo(line, err=True),
    )

    def save(run: ExtractionRun) -> None:
        save_population(
            out / "population.pt",
            run.members,
            {
                **meta,
                "seed": seed,
                "method": method,
                "params": config,
                # env frames spent collecting imported specialists' buffers (their sample cost; 0 otherwise)
                "collection_frames": sum(int(s.buffer_attrs.get("collection_frames", 0)) for s in slots),
                # env frames the specialists trained on (None: an imported one's are not known here)
                "specialist_frames": training_frames([s.policy_meta for s in slots]),
                # imported slots beside slots trained here: where each came from (the report says it)
                **({"specialist_sources": sources} if sources else {}),
                # the extensions that ran: fallbacks, seeds, the early stop ({} for a paper run)
                **run.record(),
            },
        )
        write_text_atomic(out / "history.csv", history_csv(run.history))
        finished.append(run)

    finished: list[ExtractionRun] = []  # the run whose outputs `save` wrote: its costs go to the provenance record
    who = f"extract {method} seed {seed}"
    with progress_send(cfg.iterations * cfg.children_per_iteration, who, unit="child") as send:
        drive(
            lambda: ExtractionRun.from_slots(slots, cfg, meta, seed, envs, device),
            ckpt,
            who=who,
            stage=f"extract {method}",
            resumed=lambda run: f"resuming from iteration {run.iteration} of {cfg.iterations} ({ckpt.path.parent})",
            save=save,
            send=send,
        )
    write_provenance(provenance, "extract", device, precision, {"iterations": finished[0].costs})
