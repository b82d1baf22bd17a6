"""The front explorer: one self-contained HTML page (hand-written SVG and JavaScript, no CDN, opens
from file://) with one panel per method and seed. Hover a point to play its clip (stage render)
beside its returns and their spread, origin, parents, target weight, iteration and exported
file; click to keep it. With N objectives a panel draws every pair of them (N = 3: three
projections). Starting policies are stars, as in the report's figures.
"""

from __future__ import annotations

import html
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.core.artifacts import ArtifactError
from pipeline.core.pareto import pareto_mask
from pipeline.core.population import Member, load_population
from pipeline.evaluation.evaluated import META_KEYS, read_evaluated, read_std


@dataclass
class FrontRun:
    """One method and seed: its members, their re-evaluated returns and its front (sorted by obj0)."""

    method: str
    seed: int
    members: list[Member]
    meta: dict
    means: np.ndarray
    stds: np.ndarray
    front: list[int] = field(default_factory=list)


def load_front_run(population: Path, evaluated: Path) -> FrontRun:
    """A population and its evaluate outputs; the front is as stage score and export compute it."""
    members, meta = load_population(population, META_KEYS)
    if not members:
        raise ArtifactError(f"{population}: population has no members")
    n_obj = meta["n_objectives"]
    means = read_evaluated(evaluated / "evaluated.csv", members, n_obj)
    stds = read_std(evaluated / "evaluated.csv", n_obj)
    front = np.flatnonzero(pareto_mask(means))
    front = front[np.argsort(means[front, 0], kind="stable")]
    return FrontRun(meta["method"], int(meta["seed"]), members, meta, means, stds, [int(i) for i in front])


def ends_and_middle(front: list[int]) -> list[int]:
    """The front's two ends (lowest and highest objective 0) and its middle member, distinct."""
    if not front:
        return []
    picks = [front[0], front[len(front) // 2], front[-1]]
    return list(dict.fromkeys(picks))


def point_record(run: FrontRun, i: int, clip: dict | None, export: str | None) -> dict:
    """What the page shows of member `i`: returns, spread, origin, ..., its clip's paths and returns."""
    m = run.members[i]
    return {
        "id": i,
        "on_front": i in run.front,
        "origin": m.origin,
        "objective": m.objective,
        "policy_name": m.policy_name,
        "iteration": m.iteration,
        "parents": list(m.parents),
        "target_weight": None if m.target_weight is None else [round(float(x), 4) for x in m.target_weight],
        "returns": [float(x) for x in run.means[i]],
        "std": [float(x) for x in run.stds[i]],
        "clip": clip,
        "export": export,
    }


def hex_colour(name: str) -> str:
    from matplotlib.colors import to_hex

    try:
        return to_hex(name)
    except ValueError:
        return "#808080"


def explorer_html(panels: list[dict], objective_names: list[str], title: str) -> str:
    """The page: `panels` (method, label, colour, seed, points as `point_record` gives them)."""
    data = {"panels": panels, "objectives": objective_names}
    return PAGE.replace("__TITLE__", html.escape(title)).replace("__DATA__", script_json(data))


# What a JSON text inside <script> must not hold literally: `<`, `>` and `&` (so that no `</script>`
# or `<!--` can end or bend the element) and U+2028/U+2029 (line breaks to older JavaScript parsers).
_SCRIPT_ESCAPES = {ord("<"): "\\u003c", ord(">"): "\\u003e", ord("&"): "\\u0026", 0x2028: "\\u2028", 0x2029: "\\u2029"}


def script_json(data) -> str:
    """`data` as JSON that can sit inside a <script> element whatever its strings hold: the
    characters HTML would read there are written as JSON's \\uXXXX escapes (the same value)."""
    return json.dumps(data, separators=(",", ":")).translate(_SCRIPT_ESCAPES)


PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>__TITLE__</title>
<style>
body{font:14px system-ui,sans-serif;margin:0;display:flex;color:#222}
#panels{flex:1;padding:12px;overflow:auto;height:100vh;box-sizing:border-box}
#side{width:360px;padding:12px;border-left:1px solid #ccc;height:100vh;box-sizing:border-box;overflow:auto}
section{margin-bottom:18px}h2{font-size:15px;margin:4px 0}
svg{background:#fafafa;border:1px solid #ddd;margin:0 8px 8px 0}
.pt{cursor:pointer;stroke:#222;stroke-width:.6}.pt.off{fill-opacity:.25}.pt.sel{stroke:#000;stroke-width:2.5}
video{width:100%;background:#000;min-height:120px}table{border-collapse:collapse;width:100%}
td{padding:2px 4px;border-bottom:1px solid #eee;vertical-align:top;overflow-wrap:anywhere}td:first-child{color:#666;white-space:nowrap}
.note{color:#666;font-size:12px}
</style></head><body>
<div id="panels"><h1 style="font-size:18px">__TITLE__</h1>
<p class="note">Each panel is one method and seed: its non-dominated members (re-evaluated mean returns), and its
starting policies as stars (hollow where dominated). Hover a point to play its clip; click to keep it.</p></div>
<div id="side"><video id="clip" muted loop playsinline controls></video>
<p id="noclip" class="note">Hover or click a point.</p><table id="info"></table></div>
<script id="data" type="application/json">__DATA__</script>
<script>
"use strict";
const DATA = JSON.parse(document.getElementById("data").textContent);
const NS = "http://www.w3.org/2000/svg", W = 300, H = 240, PAD = 42;
let pinned = null;
const fmt = (x) => (Math.abs(x) >= 100 ? x.toFixed(0) : x.toPrecision(3));
function el(tag, attrs, parent) {
  const e = document.createElementNS(NS, tag);
  for (const k in attrs) e.setAttribute(k, attrs[k]);
  if (parent) parent.appendChild(e);
  return e;
}
function star(cx, cy, r) {
  const p = [];
  for (let k = 0; k < 10; k++) {
    const a = Math.PI / 2 + (k * Math.PI) / 5, rr = k % 2 ? r * 0.45 : r;
    p.push((cx + rr * Math.cos(a)).toFixed(1) + "," + (cy - rr * Math.sin(a)).toFixed(1));
  }
  return p.join(" ");
}
// Every string from params or artifacts reaches the page as text (textContent, setAttribute),
// never as markup; a path becomes a relative URL with each segment percent-encoded, so no
// scheme (javascript:) or quote in it can mean anything but the file's name.
const url = (path) => path.split("/").map(encodeURIComponent).join("/");
const nodesByKey = new Map();
function show(panel, p, node) {
  const v = document.getElementById("clip"), note = document.getElementById("noclip");
  document.querySelectorAll(".pt.sel").forEach((e) => e.classList.remove("sel"));
  (nodesByKey.get(node.dataset.key) || []).forEach((e) => e.classList.add("sel"));
  if (p.clip) {
    if (v.getAttribute("src") !== url(p.clip.mp4)) { v.setAttribute("src", url(p.clip.mp4)); v.load(); }
    v.play().catch(() => {});
    note.textContent = "";
  } else {
    v.removeAttribute("src"); v.load();
    note.textContent = p.on_front ? "No clip: stage render did not film this front (render.methods, render.seeds)."
                                  : "No clip: only the front's members are filmed.";
  }
  const rows = [["method", panel.label + " (seed " + panel.seed + ")"], ["member", p.id]];
  DATA.objectives.forEach((name, m) => rows.push([name, fmt(p.returns[m]) + " \\u00b1 " + fmt(p.std[m])]));
  if (p.clip) rows.push(["clip's episode", p.clip.returns.map(fmt).join(", ") + " (" + p.clip.episode_steps + " steps)"]);
  rows.push(["origin", p.origin + (p.origin === "specialist" ? " of objective " + p.objective + " (" + p.policy_name + ")" : "")]);
  rows.push(["parents", p.parents.length ? p.parents.join(", ") : "-"]);
  rows.push(["target weight", p.target_weight ? p.target_weight.join(", ") : "-"]);
  rows.push(["iteration", p.iteration]);
  rows.push(["on the front", p.on_front ? "yes" : "no (dominated)"]);
  let link = "- (stage export did not run for it)";
  if (p.export) {
    link = document.createElement("a");
    link.setAttribute("href", url(p.export));
    link.textContent = p.export;
  }
  rows.push(["exported file", link]);
  const t = document.getElementById("info");
  t.replaceChildren(...rows.map(([name, value]) => {
    const tr = document.createElement("tr"), a = document.createElement("td"), b = document.createElement("td");
    a.textContent = String(name);
    if (value instanceof Node) b.appendChild(value); else b.textContent = String(value);
    tr.append(a, b);
    return tr;
  }));
  t.dataset.key = node.dataset.key;
}
function plot(panel, i, j, parent) {
  const svg = el("svg", { width: W, height: H, "data-pair": i + "-" + j }, parent);
  const xs = panel.points.map((p) => p.returns[i]), ys = panel.points.map((p) => p.returns[j]);
  const span = (a) => { let lo = Math.min(...a), hi = Math.max(...a); if (hi - lo < 1e-9) { lo -= 1; hi += 1; }
    const d = (hi - lo) * 0.06; return [lo - d, hi + d]; };
  const [x0, x1] = span(xs), [y0, y1] = span(ys);
  const sx = (x) => PAD + ((x - x0) / (x1 - x0)) * (W - PAD - 10), sy = (y) => H - PAD + 10 - ((y - y0) / (y1 - y0)) * (H - PAD);
  el("line", { x1: PAD, y1: H - PAD + 10, x2: W - 10, y2: H - PAD + 10, stroke: "#999" }, svg);
  el("line", { x1: PAD, y1: 10, x2: PAD, y2: H - PAD + 10, stroke: "#999" }, svg);
  const lab = (x, y, s, rot) => { const t = el("text", { x: x, y: y, "font-size": 11, "text-anchor": "middle", fill: "#444" }, svg);
    if (rot) t.setAttribute("transform", "rotate(-90 " + x + " " + y + ")"); t.textContent = s; };
  lab((W + PAD) / 2, H - 6, DATA.objectives[i]); lab(12, (H - PAD) / 2 + 10, DATA.objectives[j], true);
  lab(PAD, H - PAD + 24, fmt(x0)); lab(W - 22, H - PAD + 24, fmt(x1));
  const order = panel.points.map((p, k) => k).sort((a, b) => (panel.points[a].on_front ? 1 : 0) - (panel.points[b].on_front ? 1 : 0));
  for (const k of order) {
    const p = panel.points[k], cx = sx(p.returns[i]), cy = sy(p.returns[j]);
    const node = p.origin === "specialist"
      ? el("polygon", { points: star(cx, cy, 9), fill: p.on_front ? panel.colour : "#fff" }, svg)
      : el("circle", { cx: cx, cy: cy, r: 5, fill: panel.colour }, svg);
    node.setAttribute("class", "pt" + (p.on_front ? "" : " off"));
    node.dataset.key = panel.method + "/" + panel.seed + "/" + p.id;
    if (!nodesByKey.has(node.dataset.key)) nodesByKey.set(node.dataset.key, []);
    nodesByKey.get(node.dataset.key).push(node);
    node.dataset.clip = p.clip ? p.clip.mp4 : "";
    const title = el("title", {}, node);
    title.textContent = "member " + p.id + ": " + p.returns.map(fmt).join(", ");
    node.addEventListener("mouseenter", () => { if (!pinned) show(panel, p, node); });
    node.addEventListener("click", () => { pinned = node.dataset.key; show(panel, p, node); });
  }
}
const root = document.getElementById("panels");
for (const panel of DATA.panels) {
  const s = document.createElement("section");
  const h = document.createElement("h2");
  h.textContent = panel.label + " \\u2014 seed " + panel.seed + " (" + panel.points.filter((p) => p.on_front).length + " on the front"
    + (panel.points.some((p) => p.clip) ? ", filmed" : "") + ")";
  s.appendChild(h);
  const n = DATA.objectives.length;
  for (let i = 0; i < n; i++) for (let j = i + 1; j < n; j++) plot(panel, i, j, s);
  root.appendChild(s);
}
if (!DATA.panels.length) { const none = document.createElement("p"); none.textContent = "No front to show."; root.appendChild(none); }
</script></body></html>
"""
