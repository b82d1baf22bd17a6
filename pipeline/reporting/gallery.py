"""The report's link to the front explorer (stage render) and thumbnails of each filmed front's
two ends and middle, copied into the report folder so that it stays self-contained."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from pipeline.core.artifacts import ArtifactError
from pipeline.reporting.explorer import ends_and_middle
from pipeline.reporting.presentation import label


def gallery_markdown(render: Path, out: Path, tmp: Path, methods: list[str], seeds: list[int]) -> str:
    """The report's section on RENDER (stage render's folder): a link to its explorer.html
    (relative to OUT, the report folder) and, per filmed front of `methods` x `seeds`, the
    thumbnails of its lowest and highest objective-0 members and its middle one, copied to
    TMP/thumbs/ (TMP becomes OUT). Empty where RENDER holds no explorer."""
    index_path = render / "index.json"
    if not (render / "explorer.html").is_file() or not index_path.is_file():
        return ""
    try:
        index = json.loads(index_path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ArtifactError(f"{index_path}: cannot be read as JSON ({exc})") from None
    link = Path(os.path.relpath(render / "explorer.html", out)).as_posix()
    lines = [
        "## Watch the fronts",
        "",
        f"[The front explorer]({link}) (open it in a browser; it works offline): one plot per seed with "
        "every method's front; hover a point to play its policy's clip beside its returns, origin and parents, "
        "or set a weight per objective to pick a trade-off.",
        "",
    ]
    names = index.get("objectives", [])
    for panel in index.get("panels", []):
        if panel["method"] not in methods or panel["seed"] not in seeds:
            continue
        points = {p["id"]: p for p in panel["points"]}
        picks = [i for i in ends_and_middle(panel["front"]) if points[i]["clip"]]
        if not picks:
            continue
        cells, captions = [], []
        for i, where in zip(picks, ("lowest", "middle", "highest") if len(picks) == 3 else ("lowest", "highest")):
            p = points[i]
            name = f"{panel['method']}_seed{panel['seed']}_member_{i:04d}.png"
            (tmp / "thumbs").mkdir(exist_ok=True)
            shutil.copyfile(render / p["clip"]["thumb"], tmp / "thumbs" / name)
            clip = Path(os.path.relpath(render / p["clip"]["mp4"], out)).as_posix()
            cells.append(f"[![member {i}](thumbs/{name})]({clip})")
            returns = ", ".join(f"{x:.0f}" for x in p["returns"])
            captions.append(f"member {i} ({where} {names[0] if names else 'objective 0'}): {returns}")
        lines += [
            f"{label(panel['method'])}, seed {panel['seed']}:",
            "",
            "| " + " | ".join(captions) + " |",
            "|" + "---|" * len(cells),
            "| " + " | ".join(cells) + " |",
            "",
        ]
    return "\n".join(lines) + "\n"
