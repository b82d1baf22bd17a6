"""The grid file: its pydantic model (envs, seeds, override sets, per-stage resources,
targets), reading and validating it, and its expansion into cells, each one (env, override set)
with the params.yaml text it runs, validated with the stages' own params models before anything
runs (see the package docstring for how a grid maps onto DVC)."""

from __future__ import annotations

import copy
import re
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from pipeline.distributed.errors import GridError
from pipeline.params import KNOWN_SECTIONS, ParamsError
from pipeline.params.planned import with_tracked_env, without_derived

NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class EnvSpec(_Strict):
    """One env of the grid. `id` alone takes the base params with env.id (and the env's
    reference point from presets/envs.yaml); `preset` starts from that params file
    instead of the base; `params` is merged in on top of either."""

    name: str | None = Field(None, description="cell name prefix (default: the env id)")
    id: str | None = Field(None, description="MO-Gymnasium env id, set as env.id on the base params")
    preset: str | None = Field(
        None, description="params file (repository path) replacing the base, e.g. presets/paper/mo-hopper-2obj-v5.yaml"
    )
    params: dict[str, Any] = Field(default_factory=dict, description="params merged in, section by section")

    @field_validator("name")
    @classmethod
    def _name(cls, v: str | None) -> str | None:
        if v is not None and not NAME.match(v):
            raise ValueError(f"{v!r}: use letters, digits, '.', '_' and '-' (it names a directory)")
        return v


class ResourceSpec(_Strict):
    """What one task of a stage asks Ray for."""

    cpus: float = Field(1.0, gt=0, description="CPUs reserved per task")
    gpus: float | Literal["auto"] = Field(
        "auto",
        description="GPUs per task (fractions share one GPU); auto: 1 for the training stages when the cluster has a GPU, else 0",
    )
    threads: int | None = Field(
        None,
        ge=1,
        description="MAPEX_TORCH_THREADS for the stage (default: cpus, at least 1; shared among a stage's processes)",
    )

    @field_validator("gpus")
    @classmethod
    def _gpus(cls, v: float | str) -> float | str:
        if not isinstance(v, str) and v < 0:
            raise ValueError("must be >= 0 or 'auto'")
        return v


class Grid(_Strict):
    base: str = Field(
        "params.yaml", description="params file (repository path, read at the commit) each env starts from"
    )
    envs: list[EnvSpec] = Field(min_length=1, description="env ids, preset paths (*.yaml) or mappings")
    seeds: list[int] | None = Field(
        None, min_length=1, description="the seeds of every cell (default: the params' own)"
    )
    overrides: dict[str, dict[str, Any]] | None = Field(
        None, description="named param override sets; each env runs once per set (default: one cell per env)"
    )
    resources: dict[str, ResourceSpec] = Field(default_factory=dict, description="per dvc.yaml stage name")
    targets: list[str] | None = Field(
        None,
        min_length=1,
        description="dvc.yaml stages or stage items to reproduce, with their upstream (default: all)",
    )

    @field_validator("envs", mode="before")
    @classmethod
    def _env_shorthands(cls, v: Any) -> Any:
        if not isinstance(v, list):
            return v
        return [({"preset": e} if e.endswith((".yaml", ".yml")) else {"id": e}) if isinstance(e, str) else e for e in v]

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, v: list[int] | None) -> list[int] | None:
        if v is not None and (len(set(v)) != len(v) or any(s < 0 for s in v)):
            raise ValueError(f"seeds must be unique and >= 0, got {v}")
        return v

    @field_validator("overrides")
    @classmethod
    def _override_names(cls, v: dict[str, Any] | None) -> dict[str, Any] | None:
        for name in v or {}:
            if not NAME.match(str(name)):
                raise ValueError(f"override set name {name!r}: use letters, digits, '.', '_' and '-'")
        return v


def read_mapping(path: Path, what: str, expected: str) -> dict[str, Any]:
    """A YAML file's mapping; a missing file, bad YAML or another shape is one GridError naming
    the file (`what` the file is, `expected` what its mapping holds)."""
    if not path.is_file():
        raise GridError(f"{path}: {what} not found")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise GridError(f"{path}: not valid YAML ({exc})") from None
    if not isinstance(raw, dict):
        raise GridError(f"{path}: expected a mapping {expected}")
    return raw


def load_grid(path: Path) -> Grid:
    """Read and validate a grid file; every problem becomes one GridError naming file and key."""
    path = Path(path)
    raw = read_mapping(path, "grid file", "with keys envs, seeds, overrides, base, resources")
    try:
        return Grid.model_validate(raw)
    except ValidationError as exc:
        lines = []
        for err in exc.errors():
            loc = ".".join(str(p) for p in err["loc"])
            if err["type"] == "extra_forbidden":
                lines.append(f"{loc}: unknown key")
            elif err["type"] == "missing":
                lines.append(f"{loc}: required key is missing")
            else:
                lines.append(f"{loc} = {err.get('input')!r}: {err['msg']}")
        raise GridError(f"{path}: invalid grid:\n  " + "\n  ".join(dict.fromkeys(lines))) from None


def merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """A deep copy of `base` with `over` merged in, mapping by mapping (lists are replaced)."""
    out = copy.deepcopy(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


@dataclass(frozen=True)
class Cell:
    """One grid cell: a name (its workspace directory) and the params.yaml text it runs."""

    name: str
    params: dict[str, Any]
    params_text: str


def _yaml_at(repo: Path, commit: str, path: str, where: str) -> dict[str, Any]:
    r = subprocess.run(["git", "show", f"{commit}:{path}"], cwd=repo, capture_output=True, text=True)
    if r.returncode != 0:
        raise GridError(f"{where}: {path} is not in commit {commit[:12]} of {repo} (workers clone that commit)")
    try:
        data = yaml.safe_load(r.stdout)
    except yaml.YAMLError as exc:
        raise GridError(f"{where}: {path} at {commit[:12]} is not valid YAML ({exc})") from None
    if not isinstance(data, dict):
        raise GridError(f"{where}: {path} at {commit[:12]} is not a mapping")
    return data


def validate_params(params: dict[str, Any], where: str) -> None:
    """Check a cell's params with the stages' own pydantic models, before anything runs."""
    from pipeline.params import section
    from pipeline.params.registry import section_models

    unknown = sorted(set(params) - set(KNOWN_SECTIONS))
    if unknown:
        raise GridError(f"{where}: unknown top-level params key(s) {unknown}; expected some of {list(KNOWN_SECTIONS)}")
    models = section_models()
    for name, model in models.items():
        try:
            section(params, name, model, where)
        except ParamsError as exc:
            raise GridError(str(exc)) from None


def with_run_lists(params: dict[str, Any], where: str) -> dict[str, Any]:
    """`params` checked to derive run lists the plan can run (a GridError naming `where`
    otherwise); the cell's workspace gets its dvc.yaml planned from them (workspace.checkout_cell),
    so a cell lists what it runs once, like a preset. Derived keys a base or preset still
    carries are dropped (they are derived again)."""
    from pipeline.params.planned import run_lists

    user = without_derived(params)
    try:
        run_lists(user)
    except ValueError as exc:
        raise GridError(f"{where}: {exc}") from None
    return user


def with_seeds(grid: Grid, path: Path, seeds: list[int]) -> Grid:
    """The grid with its seeds replaced (`mapex repro --seed`): a first look at one seed of a long
    grid. Per-seed stage items do not read the seed list, so a later run of the grid's own seeds
    restores these from the remote's run-cache instead of recomputing them."""
    if len(set(seeds)) != len(seeds) or any(s < 0 for s in seeds):
        raise GridError(f"{path}: --seed {seeds}: seeds must be unique and >= 0")
    return grid.model_copy(update={"seeds": list(seeds)})


def plan_cells(grid: Grid, grid_path: Path, repo: Path, commit: str) -> list[Cell]:
    """The grid's cells in order (envs outer, override sets inner), params validated."""
    base = _yaml_at(repo, commit, grid.base, f"{grid_path}: base")
    refs_raw = subprocess.run(
        ["git", "show", f"{commit}:presets/envs.yaml"], cwd=repo, capture_output=True, text=True
    )  # the per-env facts (pipeline/params/env_facts.py): their reference points
    ref_points = (
        ((yaml.safe_load(refs_raw.stdout) or {}).get("reference_point") or {}) if refs_raw.returncode == 0 else {}
    )
    overrides = grid.overrides if grid.overrides is not None else {"": {}}
    cells: list[Cell] = []
    for i, entry in enumerate(grid.envs):
        where = f"{grid_path}: envs.{i}"
        if entry.preset is not None and entry.id is not None:
            raise GridError(f"{where}: give either id or preset, not both (a preset names its env)")
        if entry.preset is not None:
            params = _yaml_at(repo, commit, entry.preset, f"{where}.preset")
            default_name = str((params.get("env") or {}).get("id") or Path(entry.preset).stem)
        else:
            params = copy.deepcopy(base)
            if entry.id is not None:
                env = dict(params.get("env") or {})
                if env.get("id") != entry.id:
                    env["id"] = entry.id
                    if entry.id in ref_points:
                        env["reference_point"] = ref_points[entry.id]
                    else:
                        env.pop("reference_point", None)
                params["env"] = env
            default_name = str((params.get("env") or {}).get("id") or "env")
        params = merge(params, entry.params)
        env_name = entry.name or default_name
        if not NAME.match(env_name):
            raise GridError(f"{where}: cell name {env_name!r} is not a valid directory name; give the env a name")
        for set_name, over in overrides.items():
            cell_params = with_tracked_env(merge(params, over or {}))
            if grid.seeds is not None:
                cell_params["seeds"] = list(grid.seeds)
            name = f"{env_name}.{set_name}" if set_name else env_name
            cell_params = with_run_lists(cell_params, f"{grid_path}: cell {name}")
            validate_params(cell_params, f"{grid_path}: cell {name}")
            # No cell or grid name in the text, so that cells of equal params are equal checkouts.
            text = "# params of a `mapex repro --ray` grid cell (docs/sweeps.md)\n" + yaml.safe_dump(
                cell_params, sort_keys=False
            )
            cells.append(Cell(name, cell_params, text))
    names = [c.name for c in cells]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise GridError(f"{grid_path}: cells {dupes} appear more than once; give the envs distinct names")
    return cells
