"""Stage import_specialist: a specialist trained elsewhere becomes slot obj{K} of kind `imported`."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import typer

from pipeline.core.artifacts import ArtifactError, csv_text, write_text_atomic
from pipeline.core.buffer import load_buffer, save_buffer
from pipeline.core.checkpoint import save_policy
from pipeline.core.drive import drive
from pipeline.core.envs import EnvSpec, env_spec, make_env, spec_meta
from pipeline.core.envstate import env_checkpoint_problem
from pipeline.core.provenance import write_provenance
from pipeline.core.resume import Checkpoint, checkpoint_dir, run_fingerprint
from pipeline.interop.collect import CollectionRun
from pipeline.interop.readers import FORMATS, input_scale_warning, read_policy
from pipeline.params import EnvParams, ParamsError
from pipeline.params.import_specialists import ImportSpecialistsParams
from pipeline.params.methods import normalize_file
from stages.common import PARAMS_OPTION, PROVENANCE_OPTION, fmt_vec, progress_send, read_params, reports_errors

CHECKPOINT_NAME = "collect.ckpt.pt"


def check_user_buffer(path: Path, spec: EnvSpec) -> tuple[dict[str, np.ndarray], dict]:
    """Read a buffer a user hands in (the project's Zarr format, docs/artifacts.md) and check it
    fits env `spec`: env id, dims, full reward vectors, dtypes and finite values. An SB3 replay
    buffer (a pickle file) is refused with the reason it cannot serve."""
    if path.is_file():
        head = path.read_bytes()[:2]
        if path.suffix in (".pkl", ".pickle") or head[:1] == b"\x80":
            raise ArtifactError(
                f"{path}: a pickled replay buffer (as SB3's save_replay_buffer writes); it holds only the scalar reward "
                "the model was trained on, and MAPEX needs every objective's reward per transition, so it cannot serve: "
                "leave the buffer out (null) and let import_specialist collect one"
            )
        raise ArtifactError(
            f"{path}: a file; expected a buffer.zarr directory in the project's format (docs/artifacts.md)"
        )
    data, attrs = load_buffer(path)  # format, checksums, shapes, finite values
    for key, want in (("env_id", spec.env_id), ("obs_dim", spec.obs_dim), ("act_dim", spec.act_dim)):
        if attrs.get(key) != want:
            raise ArtifactError(f"{path}: {key} = {attrs.get(key)!r}; env.id {spec.env_id} needs {want!r}")
    if attrs.get("n_objectives") != spec.n_objectives:
        raise ArtifactError(
            f"{path}: rewards of {attrs.get('n_objectives')} objectives; {spec.env_id} has {spec.n_objectives} "
            "(the buffer must hold every objective's reward)"
        )
    dtypes = {"obs": np.float32, "action": np.float32, "reward": np.float32, "next_obs": np.float32}
    dtypes |= {"terminated": np.bool_, "truncated": np.bool_, "episode": np.int64, "episode_step": np.int32}
    for name, dtype in dtypes.items():
        if data[name].dtype != dtype:
            raise ArtifactError(f"{path}: array {name!r} is {data[name].dtype}, expected {np.dtype(dtype)}")
    low, high = np.asarray(spec.action_low), np.asarray(spec.action_high)
    if len(data["action"]) and ((data["action"] < low - 1e-6).any() or (data["action"] > high + 1e-6).any()):
        raise ArtifactError(f"{path}: actions outside the bounds of {spec.env_id}")
    if attrs["n_transitions"] == 0:
        raise ArtifactError(f"{path}: buffer holds no transitions")
    return data, attrs


def episodes_csv(returns: list[list[float]], n_objectives: int) -> str:
    header = ["episode", *(f"obj{m}" for m in range(n_objectives))]
    return csv_text(header, ([i, *(f"{x:.6g}" for x in r)] for i, r in enumerate(returns)))


def collect(
    out: Path,
    actor,
    spec: EnvSpec,
    env_p: EnvParams,
    cfg: ImportSpecialistsParams,
    seed: int,
    objective: int,
    inputs: list[Path],
    save: Callable[[CollectionRun], None],
) -> None:
    """Roll the imported policy out (resuming from OUT's checkpoint when one fits), then `save(run)`;
    `inputs`: the policy file, then its statistics file if any (both in the resume fingerprint)."""
    config = {
        "env": env_p.model_dump(exclude={"objective_names", "reference_point"}),
        "import_specialists": cfg.model_dump(include={"collect_rows", "exploration_noise"}),
        "seed": seed,
        "objective": objective,
    }
    fp = run_fingerprint("import_specialist", config, "cpu", inputs)
    ckpt = Checkpoint(checkpoint_dir(out, inside=False) / CHECKPOINT_NAME, fp, lambda line: typer.echo(line, err=True))
    probe = make_env(env_p.id, env_p.max_episode_steps, env_p.reward_terms)
    problem = env_checkpoint_problem(probe)
    probe.close()

    def fresh() -> CollectionRun:
        env = make_env(env_p.id, env_p.max_episode_steps, env_p.reward_terms)
        return CollectionRun(
            actor,
            env,
            spec,
            cfg.collect_rows,
            cfg.exploration_noise,
            seed,
            objective,
            cfg.checkpoint_every,
            source=str(inputs[0]),
        )

    who = f"import_specialist seed {seed} obj {objective}"
    with progress_send(cfg.collect_rows, f"collect obj {objective} seed {seed}", unit="row") as send:
        drive(
            fresh,
            ckpt,
            who=who,
            stage="import_specialist",
            resumed=lambda run: f"{who}: resuming from row {run.t} of {ckpt.path}",
            save=save,
            send=send,
            problem=problem,
        )


@reports_errors
def import_specialist(
    objective: int = typer.Option(..., help="k: the objective the policy was trained for (slot obj{k})"),
    file: Path = typer.Option(
        ..., "--file", help="the policy file: an SB3 model.zip, a CleanRL checkpoint or TorchScript"
    ),
    format: str = typer.Option(..., "--format", help=f"the file's format: one of {', '.join(FORMATS)}"),
    buffer: Path | None = typer.Option(
        None, help="a buffer.zarr of this policy's transitions with every objective's reward; omitted: collect one"
    ),
    normalize: str = typer.Option(
        "auto",
        help="SB3 VecNormalize statistics the policy was trained with (a vecnormalize.pkl), baked into it; "
        "none: none; auto: the file rl-zoo3 saves beside an sb3 model, if any",
    ),
    seed: int = typer.Option(0, help="run seed: it fixes the collection's noise and episode starts"),
    out: Path = typer.Option(..., help="the slot directory to write (policy.pt, buffer.zarr, collect.csv)"),
    params: Path = PARAMS_OPTION,
    provenance: Path | None = PROVENANCE_OPTION,
) -> None:
    """Import a specialist trained elsewhere (Stable-Baselines3 TD3/DDPG/SAC, CleanRL
    TD3/DDPG/SAC, or a TorchScript actor) as slot obj{K} of kind `imported`.

    Params: `env` and section `import_specialists` (collect_rows, exploration_noise,
    checkpoint_every). The policy is checked against env.id (continuous actions, observation
    and action dimensions, action bounds) and written as OUT/policy.pt, loadable with
    torch.load(weights_only=True). Unless --buffer hands one in (checked: format, env, dims,
    every objective's reward, dtypes, finite values), its buffer is collected: collect_rows
    transitions of the policy with Gaussian exploration noise in the MO env, episodes capped at
    env.max_episode_steps, written as OUT/buffer.zarr with the full reward vector, plus
    OUT/collect.csv (each collected episode's return vector). A long collection checkpoints
    every checkpoint_every rows and on SIGTERM; a rerun resumes it. Post-hoc critics for every
    objective come next (stage fit_critics), then MAPEX-PostHoc (docs/import_export.md).
    With --normalize (an SB3 or CleanRL MLP), the observation statistics of SB3's VecNormalize
    are read without running the pickle's code and put before the actor's first layer, so the
    slot's policy, like every export of it, takes raw observations; a line warns when an SB3
    model was trained on normalised observations and imported without them.
    With --provenance, what produced the run (pipeline.core.provenance) goes to that file, outside OUT.
    """
    _, env_p, cfg, _ = read_params(params, "import_specialists", ImportSpecialistsParams)
    env = make_env(env_p.id, env_p.max_episode_steps, env_p.reward_terms)
    spec = env_spec(env, env_p.id, env_p.max_episode_steps)
    env.close()
    if not 0 <= objective < spec.n_objectives:
        raise ParamsError(f"--objective {objective}: env {env_p.id} has objectives 0..{spec.n_objectives - 1}")
    stats = normalize_file({"file": str(file), "format": format}) if normalize == "auto" else normalize
    stats = None if stats in (None, "none") else Path(stats)
    imported = read_policy(file, format, spec, stats)
    if stats is not None:
        typer.echo(
            f"import_specialist obj {objective}: observation statistics of {stats} baked into the policy", err=True
        )
    for line in imported.warnings:
        typer.echo(line, err=True)

    late_warnings: list[str | None] = []  # what the observations say, printed once the progress bar is done

    def write(data: dict[str, np.ndarray], origin: dict, collected: int, returns: list[list[float]] | None) -> None:
        """The slot's artifacts; `returns`: the collected episodes' (None: the buffer was given)."""
        meta = spec_meta(spec) | {
            "max_episode_steps": spec.max_episode_steps,
            "hidden_sizes": imported.hidden_sizes,
            "architecture": imported.architecture,
            "seed": seed,
            "objective": objective,
            # what the import reads (dvc.yaml's params of this stage): not the scoring reference point,
            # the objectives' labels or when to checkpoint, nor, for a buffer handed in, the collection's
            "params": {
                "env": env_p.model_dump(exclude={"objective_names", "reference_point"}),
                "import_specialists": cfg.model_dump(include={"collect_rows", "exploration_noise"})
                if buffer is None
                else {},
            },
            "source": imported.source | origin,
            "collection_frames": collected,
        }
        keys = ("env_id", "obs_dim", "act_dim", "n_objectives", "max_episode_steps", "seed")
        buf_attrs = {k: meta[k] for k in keys}
        save_buffer(
            out / "buffer.zarr",
            data,
            buf_attrs | {"objective": objective, "source": origin["buffer"], "collection_frames": collected},
        )
        save_policy(out / "policy.pt", imported.actor, meta)
        write_text_atomic(out / "collect.csv", episodes_csv(returns or [], spec.n_objectives))
        normalizes = imported.architecture == "normalized_mlp"
        late_warnings.append(input_scale_warning(file, imported.input_scales, data["obs"], normalizes))
        if returns is not None:
            mean = np.mean(returns, axis=0).tolist() if returns else None
            typer.echo(
                f"import_specialist obj {objective} seed {seed}: {collected} rows, {len(returns)} whole episodes"
                + (f", mean return {fmt_vec(mean)}" if mean else ""),
                err=True,
            )

    if buffer is not None:
        data, battrs = check_user_buffer(buffer, spec)
        origin = {"buffer": "given", "buffer_file": buffer.name, "buffer_checksums": dict(battrs.get("checksums", {}))}
        write(data, origin, 0, None)
    else:
        save = lambda run: write(run.data(), {"buffer": "collected"}, run.t, run.returns)  # noqa: E731
        collect(out, imported.actor, spec, env_p, cfg, seed, objective, [file, *([stats] if stats else [])], save)
    for line in filter(None, late_warnings):
        typer.echo(line, err=True)
    write_provenance(provenance, "import_specialist", "cpu")
