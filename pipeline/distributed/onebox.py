"""A grid or a preset on this machine, with no Ray and no remote: what `mapex repro PLAN` runs
when PLAN is a grid file or a preset (docs/sweeps.md, "On one machine").

The cells and their workspaces are the sweep's (pipeline.distributed.grid and .workspace): one
git clone of the commit per cell under WORKDIR/<cell>, with the cell's params.yaml and its planned
dvc.yaml, so a grid run here and the same grid run on Ray leave the same layout and the same
dvc.lock. What differs is where the stage items run and where their outputs go:

- every cell's DVC uses the checkout's own cache (`cache.dir` in the cell's .dvc/config.local,
  which git ignores), so the run-cache is shared: an item two cells have in common (the same
  command, params and upstream, e.g. the specialists of two override sets that change only the
  extraction) runs once and the second cell restores it, as the sweep's shared tasks do through
  its remote; a later run of the checkout's own `dvc repro` restores them too;
- the items of all cells run as `dvc repro --single-item` processes side by side, at most `jobs`
  at a time, each in its cell's workspace once its upstream has finished
  (pipeline.distributed.local.repro_parallel); an item shared with an earlier cell waits for it.

A preset is a grid of one cell (`envs: [PRESET]`): it runs in its own workspace and is never
copied over the user's params.yaml.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from pipeline.distributed.errors import GridError, SweepError
from pipeline.distributed.grid import EnvSpec, Grid, load_grid, plan_cells, read_mapping, with_seeds
from pipeline.distributed.local import ReproResult, repro_parallel
from pipeline.distributed.workspace import StageItem, _git, prepare_workspace, stage_items


def load_plan(path: Path, repo: Path) -> tuple[Grid, str]:
    """The grid a PLAN file stands for, and its name (the file's stem, naming its work directory):
    a grid file (a mapping with `envs`) as it is, a preset (a params file) as a grid of one cell.
    A preset must lie inside `repo` (the cell reads it at the commit)."""
    path = Path(path)
    raw = read_mapping(
        path, "plan file (params.yaml, a preset or a grid file)", "(a params file, a preset, or a grid with `envs`)"
    )
    if "envs" in raw:
        return load_grid(path), path.stem
    try:
        rel = path.resolve().relative_to(repo.resolve())
    except ValueError:
        raise GridError(
            f"{path}: a preset must lie inside the checkout {repo} (its cell reads it at the commit)"
        ) from None
    return Grid(envs=[EnvSpec(preset=rel.as_posix())]), path.stem


def share_cache(workspace: Path, cache: Path) -> None:
    """Point the cell workspace's DVC at `cache` (its .dvc/config.local, which git ignores): one
    cache and run-cache for every cell and the checkout itself."""
    (workspace / ".dvc" / "config.local").write_text(f"[cache]\n    dir = {cache}\n")


@dataclass
class CellItems:
    """One cell to run: its name, workspace and stage items (in stage_items' order)."""

    name: str
    workspace: Path
    items: list[StageItem]


def merged_items(cells: list[CellItems]) -> tuple[list[StageItem], dict[str, tuple[Path, str]]]:
    """The stage items of every cell as one list for run_items, each named CELL/ITEM with its
    upstream renamed alike, and where each runs (name -> (workspace, DVC's item name)). An item
    whose signature an earlier item has (one DVC computation: same command, params, upstream)
    also waits for that item, so that it is restored from the shared run-cache instead of being
    computed twice. The order interleaves the cells by position, so that their first items (the
    specialists, the longest chains) start before any cell's tail."""
    first: dict[str, str] = {}
    renamed: list[list[StageItem]] = []
    places: dict[str, tuple[Path, str]] = {}
    for cell in cells:
        out = []
        for it in cell.items:
            name = f"{cell.name}/{it.name}"
            upstream = [f"{cell.name}/{u}" for u in it.upstream]
            if it.signature in first:
                upstream.append(first[it.signature])
            else:
                first[it.signature] = name
            out.append(dataclasses.replace(it, name=name, upstream=tuple(upstream)))
            places[name] = (cell.workspace, it.name)
        renamed.append(out)
    order = [it for row in _interleave(renamed) for it in row]
    return order, places


def _interleave(lists: list[list[StageItem]]) -> list[list[StageItem]]:
    """Rows of the lists' i-th elements: [[a0, b0], [a1, b1], [a2], ...]."""
    rows: list[list[StageItem]] = []
    for i in range(max((len(x) for x in lists), default=0)):
        rows.append([x[i] for x in lists if i < len(x)])
    return rows


@dataclass
class OneBoxResult:
    workdir: Path
    cells: list[str]
    up_to_date: list[str] = field(default_factory=list)
    repro: ReproResult | None = None


def run_plan_here(
    plan: Path,
    repo: Path,
    jobs: int,
    *,
    workdir: Path | None = None,
    seeds: list[int] | None = None,
    targets: list[str] | None = None,
    log: Callable[[str], None] = lambda line: None,
) -> OneBoxResult:
    """Run a grid or preset (`plan`) on this machine: one workspace per cell under `workdir`
    (default: REPO/sweeps/<plan name>), every cell's stage items side by side (at most `jobs`),
    the checkout's DVC cache shared by all. The code is the checkout's HEAD commit (uncommitted
    changes are refused, as by the sweep). Raises SweepError for what stops it before it runs."""
    from pipeline.distributed.driver import _check_clean, _repo_root

    repo = _repo_root(Path(repo).resolve())
    grid, name = load_plan(plan, repo)
    if seeds:
        grid = with_seeds(grid, plan, seeds)
    targets = targets or grid.targets
    commit = _git(repo, "rev-parse", "HEAD").strip()
    _check_clean(repo, commit)
    if not (repo / ".dvc").is_dir():
        raise SweepError(f"{repo}: not a DVC repository (no .dvc/); run `dvc init` there first")
    cache = repo / ".dvc" / "cache"
    cells = plan_cells(grid, plan, repo, commit)
    workdir = (Path(workdir) if workdir is not None else repo / "sweeps" / name).resolve()
    log(f"{plan.name}: {len(cells)} cell(s), code commit {commit[:12]}, workspaces in {workdir}, cache {cache}")
    result = OneBoxResult(workdir, [c.name for c in cells])
    todo: list[CellItems] = []
    for cell in cells:
        ws = workdir / cell.name
        if ws.is_dir():
            share_cache(ws, cache)  # before its up-to-date check reads the cache
        fresh = prepare_workspace(ws, cell, str(repo), commit, targets)
        share_cache(ws, cache)
        if fresh:
            result.up_to_date.append(cell.name)
            log(f"  {cell.name}: up to date, nothing to run")
            continue
        try:
            items = stage_items(ws, targets)
        except ValueError as exc:
            raise GridError(f"{plan}: targets: {exc}") from None
        except Exception as exc:  # noqa: BLE001 - DVC's own errors (dvc.yaml vs the cell's params)
            raise SweepError(f"cell {cell.name}: DVC cannot read the pipeline in {ws}: {exc}") from None
        log(f"  {cell.name}: {len(items)} stage items")
        todo.append(CellItems(cell.name, ws, items))
    if todo:
        items, places = merged_items(todo)
        result.repro = repro_parallel(repo, items, jobs, echo=log, places=places)
    return result
