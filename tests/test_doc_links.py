"""Every relative link of the tracked Markdown documents leads somewhere: the file exists and,
where the link names an anchor, a heading of that file has it (GitHub's rule: lower case, spaces
to hyphens, punctuation other than hyphens and underscores dropped)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)|!\[[^\]]*\]\(([^)\s]+)\)")


def slug(heading: str) -> str:
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading.strip().lower())
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    fenced = False
    for line in path.read_text().splitlines():
        if line.startswith("```"):
            fenced = not fenced
        m = None if fenced else re.match(r"#{1,6} (.+)", line)
        if m:
            base = slug(m.group(1))
            n = seen.get(base, 0)
            seen[base] = n + 1
            out.add(base if n == 0 else f"{base}-{n}")
        out.update(re.findall(r'<a (?:id|name)="([^"]+)"', line))
    return out


def documents() -> list[Path]:
    """The tracked Markdown prose. Not the studies' evidence under presets/studies/evidence/: its
    reports are data/report/report.md copied out of a run, whose links lead into that run's
    data/render and to figures git does not keep (docs/figures/ keeps those a document shows)."""
    listed = subprocess.run(["git", "ls-files", "*.md"], cwd=ROOT, capture_output=True, text=True, check=True)
    paths = [Path(p) for p in listed.stdout.split()]
    prose = [p for p in paths if p.parts[:3] != ("presets", "studies", "evidence")]
    return [ROOT / p for p in prose if (ROOT / p).is_file()]


def test_slug_follows_githubs_rule():
    assert slug("10. mapex or MORL/D? The pipeline at 300,000-frame specialists") == (
        "10-mapex-or-morld-the-pipeline-at-300000-frame-specialists"
    )
    assert slug("Hybrid extraction (not in the paper)") == "hybrid-extraction-not-in-the-paper"
    assert slug("The study's `extract` keys") == "the-studys-extract-keys"
    assert slug("Keep-best checks: `keep_best.csv`") == "keep-best-checks-keep_bestcsv"


def test_every_relative_link_of_the_documents_resolves():
    broken = []
    docs = documents()
    assert any(p.name == "README.md" for p in docs) and len(docs) > 5
    for doc in docs:
        text = re.sub(r"```.*?```", "", doc.read_text(), flags=re.S)
        for m in LINK.finditer(text):
            target = m.group(1) or m.group(2)
            if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
                continue
            file, _, anchor = target.partition("#")
            dest = (doc.parent / file).resolve() if file else doc
            if not dest.exists():
                broken.append(f"{doc.relative_to(ROOT)}: {target} (no such file)")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                broken.append(f"{doc.relative_to(ROOT)}: {target} (no heading with that anchor)")
    assert not broken, "\n".join(broken)
