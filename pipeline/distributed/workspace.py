"""Per-cell workspaces: git clones of the code commit with a cell's params.yaml (the driver's
workspace of each cell and the workers' scratch clones), the DVC remote and command in them, the
cell's stage items read from DVC's own DAG, and the driver's checks and writes in a cell's
workspace (up to date or not, its final dvc.lock restored from the remote's run-cache)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from pipeline.distributed.errors import SweepError
from pipeline.distributed.grid import Cell

CELL_KEY = "mapex.sweepcell"  # git config key marking a directory as a sweep cell workspace


def _git(cwd: Path | str, *args: str, env: dict[str, str] | None = None, input: str | None = None) -> str:
    r = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, env=env, input=input)
    if r.returncode != 0:
        raise SweepError(f"git {' '.join(args)} (in {cwd}) failed: {r.stderr.strip() or r.stdout.strip()}")
    return r.stdout


def checkout_cell(clone: Path, commit: str, params_text: str) -> None:
    """Make `clone` the cell's checkout: `commit` (detached), the cell's params.yaml and the
    dvc.yaml planned for it (from the commit's stage catalogue, its code deps the commit's; a
    commit without a catalogue keeps its own dvc.yaml), no dvc.lock."""
    from pipeline.params.plan import write_plan

    _git(clone, "checkout", "--quiet", "--force", "--detach", commit)
    (clone / "params.yaml").write_text(params_text)
    catalogue = clone / "pipeline" / "params" / "stage_catalogue.yaml"
    dvc = clone / "dvc.yaml"
    if catalogue.is_file():
        write_plan(yaml.safe_load(params_text) or {}, clone / "params.yaml", clone)
    elif dvc.is_file() and "params.gen.yaml" in dvc.read_text():
        raise SweepError(f"{clone}: commit {commit[:12]} predates `mapex plan` (its dvc.yaml loads params.gen.yaml)")
    # else: a pipeline of the project's own dvc.yaml, not planned (kept as committed)
    (clone / "dvc.lock").unlink(missing_ok=True)


def _has_commit(clone: Path, commit: str) -> bool:
    return (
        subprocess.run(["git", "cat-file", "-e", f"{commit}^{{commit}}"], cwd=clone, capture_output=True).returncode
        == 0
    )


def _fetch_commit(clone: Path, source: str, commit: str) -> None:
    """Make `commit` available in `clone`: fetched from `source` by name if no branch has it."""
    if not _has_commit(clone, commit):
        _git(clone, "fetch", "--quiet", source)
    if not _has_commit(clone, commit):
        _git(clone, "fetch", "--quiet", source, commit)


def _clone_at(source: str, commit: str, dest: Path) -> None:
    """`git clone` source into dest, with `commit` available there."""
    _git(dest.parent, "clone", "--quiet", "--no-checkout", source, str(dest))
    _fetch_commit(dest, source, commit)


def configure_remote(workspace: Path, remote: str, options: tuple[tuple[str, str], ...] = ()) -> None:
    """Point the workspace's DVC at the shared remote (.dvc/config.local, which git ignores), with
    the remote's extra settings (e.g. endpointurl, access_key_id for an S3-compatible server)."""
    extra = "".join(f"    {k} = {v}\n" for k, v in options)
    (workspace / ".dvc" / "config.local").write_text(
        f"[core]\n    remote = mapex-sweep\n['remote \"mapex-sweep\"']\n    url = {remote}\n{extra}"
    )


def _dvc_bin() -> str:
    here = Path(sys.executable).with_name("dvc")
    return str(here) if here.is_file() else "dvc"


def _run_dvc(cwd: Path, env: dict[str, str], *args: str) -> str:
    r = subprocess.run([_dvc_bin(), *args], cwd=cwd, env=env, capture_output=True, text=True)
    out = r.stdout + r.stderr
    if r.returncode != 0:
        tail = "\n".join(out.strip().splitlines()[-40:])
        raise RuntimeError(f"dvc {' '.join(args)} exited with {r.returncode}:\n{tail}")
    return out


@dataclass(frozen=True)
class StageItem:
    """One stage item of a cell's DAG, as DVC sees it."""

    name: str  # dvc addressing, e.g. extract@0-td3-mapex
    stage: str  # dvc.yaml stage name, e.g. extract
    upstream: tuple[str, ...]  # direct upstream items
    pull: tuple[str, ...]  # upstream outputs inside a folder dep, and data-source files it reads (pulled first)
    signature: str  # what DVC's run-cache key depends on besides code: cmd, declared params, upstream, sources
    sources: tuple[str, ...] = ()  # the .dvc files (`dvc add`) of the data it reads, e.g. an imported model
    on_device: bool = False  # it computes on an accelerator when there is one (wants_device)


def wants_device(params: dict[str, dict[str, Any]]) -> bool:
    """Whether a stage item computes on an accelerator when one is there, read from what defines
    it: the params it lists (`params`: file -> listed key -> value, as DVC reads them). True when
    a params.yaml section it lists has a `device` setting in its model and that setting, the
    file's or else the model's default, after the overrides of a variant it lists
    (`variants.<name>`), is not cpu. So every stage that trains or extracts, variants included,
    qualifies by being one, and a stage told `device: cpu` (evaluate's default) does not; no list
    of stage names to keep beside dvc.yaml."""
    from pipeline.params.registry import section_models

    models = section_models()
    values = params.get("params.yaml") or {}
    sections: dict[str, dict[str, Any]] = {}
    overrides: dict[str, dict[str, Any]] = {}
    for key, value in values.items():
        head, _, rest = key.partition(".")
        if head == "variants" and rest and isinstance(value, dict):
            for section, over in value.items():
                if isinstance(over, dict):
                    overrides.setdefault(section, {}).update(over)
        elif not rest and isinstance(value, dict):
            sections.setdefault(head, {}).update(value)
        elif rest == "device":
            sections.setdefault(head, {})["device"] = value
    for section, body in sections.items():
        model = models.get(section)
        if model is None or "device" not in model.model_fields:
            continue
        device = {**body, **overrides.get(section, {})}.get("device", model.model_fields["device"].default)
        if device != "cpu":
            return True
    return False


def _name(stage: Any) -> str:
    """A stage's name in dvc.yaml; a .dvc file's stage (data added with `dvc add`) has none: its path."""
    return getattr(stage, "name", None) or stage.addressing


def stage_items(workspace: Path, targets: list[str] | None = None) -> list[StageItem]:
    """The cell's stage items in a topological order, from DVC's own index (dvc.yaml + params):
    all of them, or `targets` (stage names or items, as `dvc repro` takes them) and their upstream."""
    import networkx as nx
    from dvc.dependency.param import ParamsDependency
    from dvc.repo import Repo

    items = []
    signatures: dict[str, str] = {}
    with Repo(str(workspace)) as repo:
        graph = repo.index.graph  # edges point from a stage to the stages it depends on
        root = repo.root_dir
        if targets:
            keep = set()
            for t in targets:
                hits = [s for s in graph if not s.is_data_source and (s.name == t or s.name.split("@")[0] == t)]
                if not hits:
                    raise ValueError(
                        f"target {t!r} is no stage or stage item of dvc.yaml (have {sorted({_name(s).split('@')[0] for s in graph if not s.is_data_source})})"
                    )
                for s in hits:
                    keep |= {s} | nx.descendants(graph, s)
            graph = graph.subgraph(keep)
        # Ray starts ready tasks roughly in submission order: the longest chain of dependents first
        # (the critical path: training before the fidelity checks that nothing waits for).
        height: dict[Any, int] = {}
        for stage in nx.topological_sort(graph):  # dependents before their upstream
            height[stage] = 1 + max((height[d] for d in graph.predecessors(stage)), default=0)
        for stage in nx.lexicographical_topological_sort(
            graph.reverse(copy=False), key=lambda s: (-height[s], _name(s))
        ):
            if stage.is_data_source:
                continue  # a .dvc file (`dvc add`, such as a user's model): data, no item; its readers pull it
            ups = sorted((u for u in graph.successors(stage) if not u.is_data_source), key=lambda s: s.name)
            # Data a user tracked with `dvc add` and pushed: `dvc repro --single-item --pull` does not
            # fetch a dep that no pipeline stage writes, so the task pulls its .dvc file first; its
            # hash joins the signature (two cells with different models are different runs).
            data = {}
            for src in graph.successors(stage):
                if src.is_data_source:
                    for out in src.outs:
                        if any(
                            out.fs_path == d.fs_path
                            or out.fs.isin(d.fs_path, out.fs_path)
                            or out.fs.isin(out.fs_path, d.fs_path)
                            for d in stage.deps
                        ):
                            data[os.path.relpath(out.fs_path, root)] = (
                                os.path.relpath(src.path, root),
                                str(out.hash_info.value),
                            )
            # `dvc repro --pull` pulls a missing dep that is an upstream output (or inside one)
            # itself; a dep that is a folder holding outputs (report's data/evaluate) it cannot,
            # so the task pulls those outputs first.
            pull = set()
            for dep in stage.deps:
                for up in ups:
                    for out in up.outs:
                        if out.fs_path != dep.fs_path and out.fs.isin(out.fs_path, dep.fs_path):
                            pull.add(os.path.relpath(out.fs_path, root))
            params = {
                os.path.relpath(d.fs_path, root): d.read_params() for d in stage.deps if isinstance(d, ParamsDependency)
            }
            # DVC refuses to run a stage whose listed params the file leaves out: say so before anything runs
            for d in stage.deps:
                if isinstance(d, ParamsDependency):
                    missing = [p for p in d.params or [] if p not in params[os.path.relpath(d.fs_path, root)]]
                    if missing:
                        raise LookupError(
                            f"stage {stage.name} lists params {missing}, which {os.path.relpath(d.fs_path, root)} "
                            "leaves out (DVC refuses to run it)"
                        )
            key = json.dumps(
                {
                    "item": stage.name,
                    "cmd": stage.cmd,
                    "params": params,
                    "upstream": [signatures[u.name] for u in ups],
                    **({"sources": {k: h for k, (_, h) in sorted(data.items())}} if data else {}),
                },
                sort_keys=True,
                default=str,
            )
            signatures[stage.name] = hashlib.sha256(key.encode()).hexdigest()
            items.append(
                StageItem(
                    stage.name,
                    stage.name.split("@")[0],
                    tuple(u.name for u in ups),
                    tuple(sorted(pull | set(data))),
                    signatures[stage.name],
                    tuple(sorted({f for f, _ in data.values()})),
                    wants_device(params),
                )
            )
    return items


def prepare_workspace(ws: Path, cell: Cell, source: str, commit: str, targets: list[str] | None = None) -> bool:
    """Make `ws` the cell's checkout (see checkout_cell); return whether it is up to date.

    Up to date: it already was that checkout, with a dvc.lock that matches its files (`dvc
    status` clean), i.e. an earlier sweep completed this cell. A workspace that changes commit
    or params loses its outputs and dvc.lock (untracked files), keeping its DVC cache.
    """
    if ws.exists():
        if _git_config(ws, CELL_KEY) != cell.name:
            raise SweepError(
                f"{ws} exists and is not the sweep workspace of cell {cell.name}; move it or pick another --workdir"
            )
        _fetch_commit(ws, source, commit)
    else:
        ws.parent.mkdir(parents=True, exist_ok=True)
        _clone_at(source, commit, ws)
        _git(ws, "config", CELL_KEY, cell.name)
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ws, capture_output=True, text=True).stdout.strip()
    params = ws / "params.yaml"
    if (
        head == commit
        and params.is_file()
        and params.read_text() == cell.params_text
        and (ws / "dvc.lock").is_file()
        and _dvc_status_clean(ws, targets)
    ):
        return True
    _git(ws, "checkout", "--quiet", "--force", "--detach", commit)
    _git(ws, "clean", "-ffdxq", "-e", "/.dvc/cache/", "-e", "/.dvc/tmp/")
    checkout_cell(ws, commit, cell.params_text)
    return False


def _git_config(ws: Path, key: str) -> str | None:
    r = subprocess.run(["git", "config", "--get", key], cwd=ws, capture_output=True, text=True)
    return r.stdout.strip() if r.returncode == 0 else None


def _dvc_status_clean(ws: Path, targets: list[str] | None = None) -> bool:
    from dvc.repo import Repo

    try:
        with Repo(str(ws)) as repo:
            # targets as path:name, since DVC resolves a bare name against the working directory
            full = [f"{Path(repo.root_dir) / 'dvc.yaml'}:{t}" for t in targets] if targets else None
            return not repo.status(targets=full, with_deps=True)
    except Exception:  # noqa: BLE001 - a workspace DVC cannot read is simply not up to date
        return False


def write_lock(
    ws: Path, remote: str, targets: list[str] | None = None, remote_options: tuple[tuple[str, str], ...] = ()
) -> str:
    """`dvc repro --pull` in the cell workspace: every stage restored from the remote's run-cache,
    dvc.lock written once. `mapex` is shadowed by a failing stub, so nothing is recomputed here."""
    configure_remote(ws, remote, remote_options)
    (ws / "dvc.lock").unlink(missing_ok=True)
    stub_dir = Path(tempfile.mkdtemp(prefix="mapex-sweep-stub-"))
    try:
        stub = stub_dir / "mapex"
        stub.write_text(
            "#!/bin/sh\necho \"mapex repro --ray: this stage's run is not in the remote's run-cache; "
            'the driver does not compute stages (rerun the sweep)" >&2\nexit 3\n'
        )
        stub.chmod(0o755)
        env = dict(os.environ)
        env["PATH"] = f"{stub_dir}{os.pathsep}{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
        # With targets, DVC orders a small subgraph by iterating a set of stages, i.e. by Python's
        # per-process string hashes; a fixed seed makes the lock's stage order repeatable (a
        # serial `PYTHONHASHSEED=0 dvc repro <targets>` writes the same bytes). Without targets
        # the order is dvc.yaml's and the seed changes nothing.
        env["PYTHONHASHSEED"] = "0"
        return _run_dvc(ws, env, "repro", "--pull", *(targets or []))
    finally:
        shutil.rmtree(stub_dir, ignore_errors=True)
