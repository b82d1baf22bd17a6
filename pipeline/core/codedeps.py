"""The in-project source files a module runs: the transitive closure of its imports.

Used twice, so the two cannot drift apart: a resumable stage hashes exactly these files
into its resume fingerprint, and `mapex plan` lists them as every DVC stage's code deps.
Only imports of this project's own packages (`pipeline`, `stages`) are followed; an import
of a package also runs its `__init__.py`, which is therefore part of the closure.
"""

from __future__ import annotations

import ast
from functools import lru_cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("pipeline", "stages")


def _module_file(name: str, root: Path = ROOT) -> Path | None:
    """The file of dotted module `name` under `root` (a module file or a package __init__)."""
    base = root.joinpath(*name.split("."))
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
def module_closure(module: str, root: Path = ROOT) -> tuple[str, ...]:
    """Sorted project-relative paths of every in-project file that importing `module` runs
    (the project's files under `root`: this checkout by default, a cell's clone for a sweep)."""
    seen: dict[str, Path] = {}
    todo = [module]
    while todo:
        name = todo.pop()
        for full in _with_parents(name):
            if full in seen:
                continue
            path = _module_file(full, root)
            if path is None:
                continue  # an attribute imported by name (`from x import func`), not a module
            seen[full] = path
            todo.extend(_imported_names(path, full))
    return tuple(sorted(str(p.relative_to(root)) for p in seen.values()))


def closure_files(module: str) -> list[Path]:
    """module_closure as absolute paths (for hashing into a fingerprint)."""
    return [ROOT / p for p in module_closure(module)]
