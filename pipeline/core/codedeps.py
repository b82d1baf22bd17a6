"""The in-project source files a module runs: the transitive closure of its imports.

Used twice, so the two cannot drift apart: a resumable stage hashes exactly these files
into its resume fingerprint, and a test checks that every DVC stage lists them as deps.
Only imports of this project's own packages (`pipeline`, `stages`) are followed; an import
of a package also runs its `__init__.py`, which is therefore part of the closure.
"""

from __future__ import annotations

import ast
from functools import lru_cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("pipeline", "stages")
# dvc.yaml stages that run another stage's command (stage name -> stages/<module>.py); every
# other stage runs stages/<its name>.py.
STAGE_MODULES = {
    "extract_posthoc": "extract",
    "warmup_only": "extract",
    "critic_fidelity_posthoc": "critic_fidelity",
    "import_specialist_buffered": "import_specialist",
    "train_specialist_imported": "train_specialist",
    "train_specialist_variant": "train_specialist",
    "extract_variant": "extract",
    "interpolate_variant": "interpolate",
}


def stage_module(stage: str) -> str:
    """The module a dvc.yaml stage runs: 'extract_posthoc' -> 'stages.extract'."""
    return f"stages.{STAGE_MODULES.get(stage, stage)}"


def _module_file(name: str) -> Path | None:
    """The file of dotted module `name` under ROOT (a module file or a package __init__)."""
    base = ROOT.joinpath(*name.split("."))
    if base.with_suffix(".py").is_file():
        return base.with_suffix(".py")
    if (base / "__init__.py").is_file():
        return base / "__init__.py"
    return None


def _with_parents(name: str) -> list[str]:
    """'pipeline.params.extract' -> ['pipeline', 'pipeline.params', 'pipeline.params.extract']."""
    parts = name.split(".")
    return [".".join(parts[: i + 1]) for i in range(len(parts))]


def _imported_names(path: Path, module: str) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    is_pkg = path.name == "__init__.py"
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative import: resolve against this module's package
                pkg = module.split(".") if is_pkg else module.split(".")[:-1]
                pkg = pkg[: len(pkg) - (node.level - 1)]
                base = ".".join(pkg + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            names.add(base)
            # `from pipeline import specialist` imports the submodule pipeline.specialists.td3_training
            names.update(f"{base}.{a.name}" for a in node.names if a.name != "*")
    return {n for n in names if n.split(".")[0] in PACKAGES}


@lru_cache(maxsize=None)
def module_closure(module: str) -> tuple[str, ...]:
    """Sorted project-relative paths of every in-project file that importing `module` runs."""
    seen: dict[str, Path] = {}
    todo = [module]
    while todo:
        name = todo.pop()
        for full in _with_parents(name):
            if full in seen:
                continue
            path = _module_file(full)
            if path is None:
                continue  # an attribute imported by name (`from x import func`), not a module
            seen[full] = path
            todo.extend(_imported_names(path, full))
    return tuple(sorted(str(p.relative_to(ROOT)) for p in seen.values()))


def closure_files(module: str) -> list[Path]:
    """module_closure as absolute paths (for hashing into a fingerprint)."""
    return [ROOT / p for p in module_closure(module)]


# The line above each stage's code deps in dvc.yaml: they are generated, not written by hand.
CODE_MARKER = "      # generated: the code this stage imports (python -m pipeline.core.codedeps); do not edit\n"


def sync_dvc_yaml(path: Path | None = None) -> list[str]:
    """Rewrite the code deps of every stage in dvc.yaml to its import closure plus stages/cli.py,
    and put each stage's `deps` last, so that a reader sees its matrix, cmd, params and outs first.

    Line-based, so comments and data deps stay as written; code deps go after the data deps,
    sorted, below CODE_MARKER. Returns the names of the stages whose deps changed (moving the
    block does not count).
    """
    path = path or ROOT / "dvc.yaml"
    lines = path.read_text().splitlines(keepends=True)
    # the `stages:` mapping runs to the next top-level key (plots:, vars:, ...) or the end
    first = next((i for i, line in enumerate(lines) if line.rstrip() == "stages:"), len(lines))
    last = next((i for i in range(first + 1, len(lines)) if lines[i].strip() and not lines[i][0].isspace()), len(lines))
    starts = [i for i in range(first + 1, last) if _stage_line(lines[i])]
    out: list[str] = lines[: starts[0]] if starts else list(lines)
    changed: list[str] = []
    for n, start in enumerate(starts):
        end = starts[n + 1] if n + 1 < len(starts) else last
        block = lines[start:end]
        tail: list[str] = []
        while block and not block[-1].strip():  # blank lines between stages stay between them
            tail.insert(0, block.pop())
        stage = block[0].strip()[:-1]
        at = next((i for i, line in enumerate(block) if line.rstrip() == "    deps:"), None)
        if at is None:
            out += block + tail + (lines[last:] if n + 1 == len(starts) else [])
            continue
        stop = at + 1
        while stop < len(block) and block[stop].startswith(("      - ", "      #")):  # entries and comments
            stop += 1
        entries = block[at + 1 : stop]
        # comments stay with the data deps; the marker is rewritten above the code deps
        data = [b for b in entries if not b[8:].startswith(("pipeline/", "stages/")) and b != CODE_MARKER]
        code = sorted(set(module_closure(stage_module(stage))) | {"stages/cli.py"})
        new = data + [CODE_MARKER] + [f"      - {c}\n" for c in code]
        if new != entries:
            changed.append(stage)
        out += block[:at] + block[stop:] + [block[at]] + new + tail
        if n + 1 == len(starts):
            out += lines[last:]  # what follows the stages
    path.write_text("".join(out))
    return changed


def _stage_line(line: str) -> bool:
    """Whether `line` opens a stage of dvc.yaml's `stages:` mapping (two-space indented key)."""
    return line.startswith("  ") and not line.startswith("   ") and line.rstrip().endswith(":") and "#" not in line


if __name__ == "__main__":  # python -m pipeline.core.codedeps: bring dvc.yaml's code deps up to date
    print("updated:", ", ".join(sync_dvc_yaml()) or "nothing")
