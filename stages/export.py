"""Stage export: a front's policies as self-contained TorchScript, torch.export (and ONNX) files, with front.csv/json."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from pipeline.core.artifacts import ArtifactError, atomic_path, csv_text, read_json
from pipeline.core.pareto import pareto_mask
from pipeline.core.population import load_population, member_actor
from pipeline.core.provenance import write_provenance
from pipeline.evaluation.evaluated import EVALUATION_KEYS, META_KEYS, check_same_run, read_evaluated, read_std
from pipeline.interop.export import (
    check_export,
    onnx_available,
    onnx_bytes,
    torch_export_bytes,
    torchscript_bytes,
)
from pipeline.params import ParamsError
from pipeline.params.export import ExportParams
from stages.common import PARAMS_OPTION, PROVENANCE_OPTION, progress, read_params, reports_errors

FRONT_FORMAT = "mapex.front"
FRONT_VERSION = 2  # 2: pt2_file (a torch.export program per policy)


def front_csv(records: list[dict], n_obj: int) -> str:
    objs = [f"obj{m}" for m in range(n_obj)]
    header = [
        "id",
        "file",
        "onnx_file",
        "pt2_file",
        "origin",
        "objective",
        "policy_name",
        "iteration",
        "parents",
        "target_weight",
        *objs,
        *(f"{c}_std" for c in objs),
        *(f"{c}_extract" for c in objs),
    ]
    rows = [
        [
            r["id"],
            r["file"],
            r["onnx_file"] or "",
            r["pt2_file"] or "",
            r["origin"],
            "" if r["objective"] is None else r["objective"],
            r["policy_name"] or "",
            r["iteration"],
            ";".join(map(str, r["parents"])),
            "" if r["target_weight"] is None else ";".join(f"{x:.6g}" for x in r["target_weight"]),
            *r["returns"],
            *r["returns_std"],
            *r["returns_extract"],
        ]
        for r in records
    ]
    return csv_text(header, rows)


@reports_errors
def export(
    population: Path = typer.Option(..., help="population.pt of a method (extract, mopderl or morld stage)"),
    evaluated: Path = typer.Option(..., help="the evaluate stage's output directory (evaluated.csv, evaluation.json)"),
    out: Path = typer.Option(
        ..., help="output directory: TorchScript and torch.export files per front policy, front.csv, front.json"
    ),
    onnx: str = typer.Option(None, help="auto | yes | no (default: params export.onnx)"),
    params: Path = PARAMS_OPTION,
    provenance: Optional[Path] = PROVENANCE_OPTION,
) -> None:
    """Export the non-dominated policies of one run as self-contained files.

    The front is the non-dominated set of the re-evaluated mean returns (EVALUATED, as stage
    score computes it). Each of its policies is written as OUT/member_<id>.pt, a TorchScript
    module mapping a batch of observations (B, obs_dim) float32 to actions (B, act_dim) in the
    env's bounds: `torch.jit.load(path)` reads it without this project; and as
    OUT/member_<id>.pt2, the same as a torch.export program (`torch.export.load(path).module()`;
    none for a policy imported as TorchScript). Each file is reloaded and checked against the
    population's actor (largest action difference <= 1e-6). With the optional onnx package
    (pip install -e ".[onnx]"), also OUT/member_<id>.onnx.

    OUT/front.csv and OUT/front.json list, per policy: its file, its re-evaluated returns and
    their spread (std over the evaluation episodes), its extraction-time returns, its origin
    (a specialist's starting policy, or a child with its parents, target weight and iteration);
    front.json adds the env (id, dims, bounds, episode cap). OUT is replaced as a whole, never
    left half-written. With --provenance, what produced the run (pipeline.core.provenance) goes
    to that file, outside OUT.
    """
    _, _, cfg, _ = read_params(params, "export", ExportParams)  # export.methods must be in methods (RunParams)
    want_onnx = onnx or cfg.onnx
    if want_onnx not in ("auto", "yes", "no"):
        raise ParamsError(f"--onnx {want_onnx!r}: expected auto, yes or no")
    if want_onnx == "yes" and not onnx_available():
        raise ParamsError('export.onnx = yes, but the onnx package is not installed (pip install -e ".[onnx]")')
    write_onnx = want_onnx == "yes" or (want_onnx == "auto" and onnx_available())
    members, meta = load_population(population, META_KEYS)
    if not members:
        raise ArtifactError(f"{population}: population has no members")
    n_obj = meta["n_objectives"]
    record = read_json(evaluated / "evaluation.json", EVALUATION_KEYS)
    means = read_evaluated(evaluated / "evaluated.csv", members, n_obj)
    stds = read_std(evaluated / "evaluated.csv", n_obj)
    check_same_run(evaluated / "evaluation.json", record, population, meta, len(members))
    front = np.flatnonzero(pareto_mask(means))
    front = front[np.argsort(means[front, 0], kind="stable")]
    records = []
    with (
        atomic_path(out) as tmp,
        progress(len(front), f"export {meta['method']} seed {meta['seed']}", unit="policy") as bar,
    ):
        tmp.mkdir(parents=True)
        for i in front.tolist():
            m = members[i]
            actor = member_actor(m, meta)
            name = f"member_{i:04d}"
            data = torchscript_bytes(actor, meta["obs_dim"])
            (tmp / f"{name}.pt").write_bytes(data)
            diff = check_export(out / f"{name}.pt", data, actor, meta["obs_dim"])
            pt2_file, program = f"{name}.pt2", torch_export_bytes(actor, meta["obs_dim"])
            if program is None:
                pt2_file = None
            else:
                (tmp / pt2_file).write_bytes(program)
                diff = max(diff, check_export(out / pt2_file, program, actor, meta["obs_dim"], kind="torch_export"))
            onnx_file = None
            if write_onnx:
                onnx_file = f"{name}.onnx"
                (tmp / onnx_file).write_bytes(onnx_bytes(actor, meta["obs_dim"]))
            records.append(
                {
                    "id": i,
                    "file": f"{name}.pt",
                    "onnx_file": onnx_file,
                    "pt2_file": pt2_file,
                    "origin": m.origin,
                    "objective": m.objective,
                    "policy_name": m.policy_name,
                    "iteration": m.iteration,
                    "parents": list(m.parents),
                    "target_weight": m.target_weight,
                    "returns": means[i].tolist(),
                    "returns_std": stds[i].tolist(),
                    "returns_extract": [float(x) for x in m.returns],
                    "export_max_abs_diff": diff,
                }
            )
            bar.update(1)
        env = {k: meta.get(k) for k in ("env_id", "obs_dim", "act_dim", "n_objectives", "action_low", "action_high")}
        doc = {
            "format": FRONT_FORMAT,
            "format_version": FRONT_VERSION,
            "usage": "policy = torch.jit.load(file) or torch.export.load(pt2_file).module(); action = policy(obs) "
            "with obs a float32 (B, obs_dim) tensor; actions are in the env's bounds",
            "env": env | {"max_episode_steps": record.get("max_episode_steps")},
            "method": meta["method"],
            "seed": meta["seed"],
            "evaluation": {"episodes": record["episodes"]},
            "policies": records,
        }
        (tmp / "front.csv").write_text(front_csv(records, n_obj))
        (tmp / "front.json").write_text(json.dumps(doc, indent=2) + "\n")
    write_provenance(provenance, "export", "cpu")
    typer.echo(f"export: {len(records)} front policies of {meta['method']} seed {meta['seed']} in {out}", err=True)
