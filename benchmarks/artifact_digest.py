"""Digest of a pipeline's data/ directory, file by file, without what only records provenance.

Used to show that a change which should not change behaviour (a refactor, a move, a
formatting pass) leaves every artifact the same: run the same tiny preset before and after
(benchmarks/tiny_repro.sh) and compare the digests this prints.

What is hashed:
- torch files (.pt): every tensor's dtype, shape and bytes, and every other value, walked in
  key order;
- Zarr stores (.zarr): every array's dtype, shape and bytes and the attributes;
- JSON files: the parsed document, canonically dumped;
- everything else (CSV, Markdown, PNG): the raw bytes.
What only records provenance (git commit, library versions, device), which differs between two
checkouts of the same code by definition, is left out: the records under DATA_DIR/provenance/
(pipeline.core.provenance), and, in data written before provenance moved there, metadata keys
named `provenance` and the score stage's provenance.json files. The report's Markdown shows
the records, so report.md differs between commits too.

Usage: python benchmarks/artifact_digest.py DATA_DIR [--alias OLD=NEW ...] [--skip KEY ...] > digests.txt

--alias reads a key OLD as NEW (in torch files and JSON) and --skip leaves KEY out, to compare
artifacts across a deliberate rename of a metadata key (e.g. `--alias variant=method --skip
format_version`, the population format 2 -> 3 change): every other byte must still agree.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import torch
import zarr

SKIP_KEYS = {"provenance"}
SKIP_FILES = {"provenance.json"}  # the score stage's chain of records, before data/provenance/
ALIASES: dict[str, str] = {}


def _walk(h, obj) -> None:
    if isinstance(obj, torch.Tensor):
        t = obj.detach().cpu().contiguous()
        h.update(f"T{t.dtype}{tuple(t.shape)}".encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    elif isinstance(obj, np.ndarray):
        h.update(f"A{obj.dtype}{obj.shape}".encode())
        h.update(np.ascontiguousarray(obj).tobytes())
    elif isinstance(obj, dict):
        named = {ALIASES.get(k, k): v for k, v in obj.items() if k not in SKIP_KEYS}
        for k in sorted(named, key=str):
            h.update(f"K{k!r}".encode())
            _walk(h, named[k])
    elif isinstance(obj, (list, tuple)):
        h.update(f"L{len(obj)}".encode())
        for v in obj:
            _walk(h, v)
    else:
        h.update(f"V{obj!r}".encode())


def digest_pt(path: Path) -> str:
    h = hashlib.sha256()
    _walk(h, torch.load(path, map_location="cpu", weights_only=True))
    return h.hexdigest()


def digest_zarr(path: Path) -> str:
    h = hashlib.sha256()
    group = zarr.open_group(str(path), mode="r")
    _walk(h, dict(group.attrs))
    for name in sorted(group.array_keys()):
        h.update(f"N{name}".encode())
        _walk(h, np.asarray(group[name][...]))
    return h.hexdigest()


def digest_json(path: Path) -> str:
    def strip(obj):
        if isinstance(obj, dict):
            return {ALIASES.get(k, k): strip(v) for k, v in obj.items() if k not in SKIP_KEYS}
        if isinstance(obj, list):
            return [strip(v) for v in obj]
        return obj

    return hashlib.sha256(json.dumps(strip(json.loads(path.read_text())), sort_keys=True).encode()).hexdigest()


def digests(root: Path) -> dict[str, str]:
    out: dict[str, str] = {}
    for path in sorted(root.rglob("*")):
        rel = str(path.relative_to(root))
        if path.relative_to(root).parts[0] == "provenance" or path.name in SKIP_FILES:
            continue  # provenance records
        if any(part.endswith(".zarr") for part in path.relative_to(root).parts[:-1]):
            continue  # inside a Zarr store: hashed as a whole
        if path.is_dir() and path.suffix == ".zarr":
            out[rel] = digest_zarr(path)
        elif path.is_file() and path.suffix == ".pt":
            out[rel] = digest_pt(path)
        elif path.is_file() and path.suffix == ".json":
            out[rel] = digest_json(path)
        elif path.is_file():
            out[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def main(argv: list[str]) -> int:
    import argparse

    ap = argparse.ArgumentParser(description="Digest of a data/ directory, without provenance.")
    ap.add_argument("data", type=Path)
    ap.add_argument("--alias", action="append", default=[], metavar="OLD=NEW", help="read metadata key OLD as NEW")
    ap.add_argument("--skip", action="append", default=[], metavar="KEY", help="leave metadata key KEY out")
    args = ap.parse_args(argv)
    if not args.data.is_dir():
        ap.error(f"{args.data}: not a directory")
    ALIASES.update(a.split("=", 1) for a in args.alias)
    SKIP_KEYS.update(args.skip)
    table = digests(args.data)
    for rel, d in table.items():
        print(f"{d}  {rel}")
    total = hashlib.sha256("".join(f"{d}{r}" for r, d in table.items()).encode()).hexdigest()
    print(f"{total}  (all {len(table)} files)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
