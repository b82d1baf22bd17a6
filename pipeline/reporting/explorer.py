"""The front explorer: one self-contained HTML page (hand-written SVG and JavaScript, no CDN, opens
from file://), made for comparing methods: one plot per seed with every method's front overlaid
(a legend toggles each method), axes with ticks and the objectives' names, starting policies as
stars drawn on top. With 3 objectives a seed gets its three pairwise projections and a 3-D view
that turns (drag to turn it yourself); with more, every pair. Hover a point to play its clip
(stage render) beside its returns and their spread, origin, parents, target weight, iteration,
exported file and the two lines of Python that load it; click to keep it. A preference control
(a weight per objective) picks the front policy of the methods shown with the best weighted
return, each objective's returns scaled to [0, 1] over those fronts, and plays its clip.

Every string that comes from params or artifacts (objective names, labels, origins, policy
names, paths) reaches the page as text: the data travels as JSON that cannot end its <script>
element (`script_json`), and the page's script writes it with textContent and setAttribute,
paths as percent-encoded relative URLs.
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


def _finite(x) -> float | None:
    """A number for the page's JSON: None where it is not finite (JSON has no NaN)."""
    x = float(x)
    return x if np.isfinite(x) else None


def point_record(run: FrontRun, i: int, clip: dict | None, export: str | None, export_file: str | None = None) -> dict:
    """What the page shows of member `i`: returns, spread, origin, ..., its clip's paths and
    returns, its exported file relative to the page (`export`, a link) and as the user's code
    names it (`export_file`, from the project's root)."""
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
        "returns": [_finite(x) for x in run.means[i]],
        "std": [_finite(x) for x in run.stds[i]],
        "clip": clip,
        "export": export,
        "export_file": export_file,
    }


def hex_colour(name: str) -> str:
    from matplotlib.colors import to_hex

    try:
        return to_hex(name)
    except ValueError:
        return "#808080"


def explorer_html(panels: list[dict], objective_names: list[str], title: str, note: str | None = None) -> str:
    """The page: `panels`, one per method and seed (method, label, colour, seed, points as
    `point_record` gives them), plotted per seed; `objective_names` name the axes; `note`, a line
    under the title (why there are no clips, where there are none)."""
    data = {"panels": panels, "objectives": objective_names}
    page = PAGE.replace("__TITLE__", html.escape(title)).replace("__DATA__", script_json(data))
    if note:
        page = page.replace("</h1>", f'</h1><p class="note" id="note">{html.escape(note)}</p>', 1)
    return page


# What a JSON text inside <script> must not hold literally: `<`, `>` and `&` (so that no `</script>`
# or `<!--` can end or bend the element) and U+2028/U+2029 (line breaks to older JavaScript parsers).
_SCRIPT_ESCAPES = {ord("<"): "\\u003c", ord(">"): "\\u003e", ord("&"): "\\u0026", 0x2028: "\\u2028", 0x2029: "\\u2029"}


def script_json(data) -> str:
    """`data` as JSON that can sit inside a <script> element whatever its strings hold: the
    characters HTML would read there are written as JSON's \\uXXXX escapes (the same value)."""
    return json.dumps(data, separators=(",", ":")).translate(_SCRIPT_ESCAPES)


PAGE = r"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>__TITLE__</title>
<style>
body{font:14px system-ui,sans-serif;margin:0;display:flex;color:#222}
#main{flex:1;padding:12px 16px;overflow:auto;height:100vh;box-sizing:border-box}
#side{width:420px;padding:12px;border-left:1px solid #ccc;height:100vh;box-sizing:border-box;overflow:auto}
h1{font-size:18px;margin:4px 0 6px}h2{font-size:15px;margin:14px 0 4px}
.bar{display:flex;flex-wrap:wrap;gap:6px 14px;align-items:center;margin:6px 0}
.legend button{font:inherit;border:1px solid #bbb;background:#fff;border-radius:4px;padding:2px 8px;cursor:pointer}
.legend button.off{opacity:.4;text-decoration:line-through}
.swatch{display:inline-block;width:11px;height:11px;border-radius:50%;margin-right:5px;vertical-align:-1px;border:1px solid #222}
.pref label{white-space:nowrap}.pref input[type=range]{width:110px;vertical-align:middle}
.plots{display:flex;flex-wrap:wrap;gap:8px}#seeds{display:flex;flex-wrap:wrap;gap:0 18px}
svg.plot{background:#fafafa;border:1px solid #ddd}
.pt{cursor:pointer;stroke:#222;stroke-width:.7}.pt.hollow{fill:#fff!important;stroke-width:1.5}
.pt.sel{stroke:#000;stroke-width:3}.pt.pick{stroke:#d00;stroke-width:3}
.gone{display:none}.tick{font-size:10px;fill:#555}.axis{font-size:12px;fill:#222}
video{width:100%;background:#000;min-height:150px}table{border-collapse:collapse;width:100%}
td{padding:2px 4px;border-bottom:1px solid #eee;vertical-align:top;overflow-wrap:anywhere}td:first-child{color:#666;white-space:nowrap}
pre{background:#f4f4f4;padding:6px;white-space:pre-wrap;overflow-wrap:anywhere;font-size:12px}
.note{color:#666;font-size:12px}
</style></head><body>
<div id="main"><h1>__TITLE__</h1>
<p class="note">One plot per seed: every method's non-dominated members (re-evaluated mean returns; a thin line joins
a method's front) and its starting policies as stars, drawn on top (hollow where dominated). Hover a point to play
its clip, click to keep it; the buttons show or hide a method.</p>
<div class="bar legend" id="legend"></div>
<div class="bar pref" id="pref"></div>
<div id="seeds"></div></div>
<div id="side"><video id="clip" muted loop playsinline controls></video>
<p id="noclip" class="note">Hover or click a point, or set the weights.</p><table id="info"></table>
<div id="load"></div></div>
<script id="data" type="application/json">__DATA__</script>
<script>
"use strict";
// Every string from params or artifacts goes in as text (textContent, setAttribute), never as
// markup; a path becomes a relative URL with each segment percent-encoded, so no scheme
// (javascript:) or quote in it can mean anything but a file's name.
const DATA = JSON.parse(document.getElementById("data").textContent);
const NS = "http://www.w3.org/2000/svg", N = DATA.objectives.length;
const url = (path) => path.split("/").map(encodeURIComponent).join("/");
const fmt = (x) => (x === null || x === undefined ? "n/a" : Math.abs(x) >= 100 ? x.toFixed(0) : x.toPrecision(3));
function el(tag, attrs, parent) {
  const e = document.createElementNS(NS, tag);
  for (const k in attrs) e.setAttribute(k, attrs[k]);
  if (parent) parent.appendChild(e);
  return e;
}
function tag(name, text, parent, cls) {
  const e = document.createElement(name);
  if (text !== undefined && text !== null) e.textContent = String(text);
  if (cls) e.className = cls;
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
function ticks(lo, hi, n) {  // about n round numbers (1, 2 or 5 x 10^k apart) within [lo, hi]
  const raw = (hi - lo) / n, mag = Math.pow(10, Math.floor(Math.log10(raw))), f = raw / mag;
  const step = (f < 1.5 ? 1 : f < 3.5 ? 2 : f < 7.5 ? 5 : 10) * mag, out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) out.push(Math.abs(v) < step * 1e-9 ? 0 : v);
  return out;
}
function span(values) {
  let lo = Math.min(...values), hi = Math.max(...values);
  if (!(hi - lo > 1e-9)) { lo -= 1; hi += 1; }
  const d = (hi - lo) * 0.06;
  return [lo - d, hi + d];
}

// every plotted point: one per member of a panel with finite returns; its SVG nodes in every view
const ITEMS = [], BY_KEY = new Map(), METHODS = [], SEEDS = [];
for (const panel of DATA.panels) {
  if (!METHODS.some((m) => m.method === panel.method)) METHODS.push({ method: panel.method, label: panel.label, colour: panel.colour });
  if (!SEEDS.includes(panel.seed)) SEEDS.push(panel.seed);
  for (const p of panel.points) {
    if (!p.returns.every((x) => typeof x === "number")) continue;
    const item = { panel: panel, p: p, key: panel.method + "/" + panel.seed + "/" + p.id, nodes: [] };
    ITEMS.push(item);
    BY_KEY.set(item.key, item);
  }
}
const RANGE = DATA.objectives.map((_, m) => span(ITEMS.map((it) => it.p.returns[m])));
const hidden = new Set();
let pinned = null, shown = null;

function marker(svg, item, cx, cy) {
  const p = item.p, spec = p.origin === "specialist";
  const node = spec ? el("polygon", { points: star(cx, cy, 9) }, svg) : el("circle", { cx: cx, cy: cy, r: 5 }, svg);
  node.setAttribute("fill", item.panel.colour);
  if (!p.on_front) node.style.stroke = item.panel.colour;  // hollow: the method's colour as its outline
  node.setAttribute("class", "pt" + (p.on_front ? "" : " hollow") + (hidden.has(item.panel.method) ? " gone" : ""));
  node.dataset.key = item.key;
  node.dataset.method = item.panel.method;
  const title = el("title", {}, node);
  title.textContent = item.panel.label + ", member " + p.id + (spec ? " (starting policy)" : "") + ": " + p.returns.map(fmt).join(", ");
  node.addEventListener("mouseenter", () => { if (!pinned) select(item); });
  node.addEventListener("click", (ev) => { ev.stopPropagation(); pinned = item.key; select(item); });
  item.nodes.push(node);
  return node;
}
// children first, starting policies last: a star stays on top of a child that lands on it
const drawOrder = (items) => items.slice().sort((a, b) => (a.p.origin === "specialist") - (b.p.origin === "specialist"));

function scatter(parent, items, i, j, W, H) {
  const L = 62, R = 14, T = 12, B = 44;
  const svg = el("svg", { width: W, height: H, class: "plot", "data-pair": i + "-" + j }, parent);
  const [x0, x1] = RANGE[i], [y0, y1] = RANGE[j];
  const sx = (x) => L + ((x - x0) / (x1 - x0)) * (W - L - R), sy = (y) => H - B - ((y - y0) / (y1 - y0)) * (H - B - T);
  el("rect", { x: L, y: T, width: W - L - R, height: H - B - T, fill: "#fff", stroke: "#999" }, svg);
  for (const v of ticks(x0, x1, Math.max(3, Math.round((W - L - R) / 80)))) {
    el("line", { x1: sx(v), y1: T, x2: sx(v), y2: H - B + 4, stroke: "#e4e4e4" }, svg);
    el("text", { x: sx(v), y: H - B + 16, "text-anchor": "middle", class: "tick" }, svg).textContent = fmt(v);
  }
  for (const v of ticks(y0, y1, Math.max(3, Math.round((H - B - T) / 60)))) {
    el("line", { x1: L - 4, y1: sy(v), x2: W - R, y2: sy(v), stroke: "#e4e4e4" }, svg);
    el("text", { x: L - 7, y: sy(v) + 3, "text-anchor": "end", class: "tick" }, svg).textContent = fmt(v);
  }
  el("text", { x: (L + W - R) / 2, y: H - 8, "text-anchor": "middle", class: "axis" }, svg).textContent = DATA.objectives[i];
  const yl = el("text", { x: 14, y: (T + H - B) / 2, "text-anchor": "middle", class: "axis", transform: "rotate(-90 14 " + (T + H - B) / 2 + ")" }, svg);
  yl.textContent = DATA.objectives[j];
  if (N === 2) for (const m of METHODS) {  // a method's front, joined in the order of objective 0
    const front = items.filter((it) => it.panel.method === m.method && it.p.on_front).sort((a, b) => a.p.returns[i] - b.p.returns[i]);
    if (front.length < 2) continue;
    const line = el("polyline", { points: front.map((it) => sx(it.p.returns[i]).toFixed(1) + "," + sy(it.p.returns[j]).toFixed(1)).join(" "),
      fill: "none", stroke: m.colour, "stroke-opacity": 0.55, "stroke-width": 1.5 }, svg);
    line.dataset.method = m.method;
    line.classList.add("frontline");
  }
  for (const it of drawOrder(items)) marker(svg, it, sx(it.p.returns[i]), sy(it.p.returns[j]));
}

function view3d(parent, items, W, H) {
  const svg = el("svg", { width: W, height: H, class: "plot view3d" }, parent);
  const norm = (m, v) => ((v - RANGE[m][0]) / (RANGE[m][1] - RANGE[m][0])) * 2 - 1;
  const state = { yaw: 0.7, pitch: 0.45, spin: true };
  const axes = [0, 1, 2].map((m) => {
    const ts = ticks(RANGE[m][0], RANGE[m][1], 4);
    return {
      line: el("line", { stroke: "#777" }, svg),
      label: Object.assign(el("text", { "text-anchor": "middle", class: "axis" }, svg), { textContent: DATA.objectives[m] }),
      ticks: ts.map((v) => ({ v: v, t: Object.assign(el("text", { "text-anchor": "middle", class: "tick" }, svg), { textContent: fmt(v) }) })),
    };
  });
  // the box's twelve edges, faint, for depth: pairs of corners that differ in one coordinate
  const corners = [];
  for (let c = 0; c < 8; c++) corners.push([c & 1 ? 1 : -1, c & 2 ? 1 : -1, c & 4 ? 1 : -1]);
  const edges = [];
  for (let a = 0; a < 8; a++) for (let b = a + 1; b < 8; b++) if ([1, 2, 4].includes(a ^ b)) edges.push([corners[a], corners[b], el("line", { stroke: "#ddd" }, svg)]);
  const layer = el("g", {}, svg);
  const drawn = drawOrder(items).map((it) => ({ it: it, node: marker(layer, it, 0, 0) }));
  function place(x, y, z) {  // orthographic: turn by yaw about the vertical axis, tilt by pitch
    const cy = Math.cos(state.yaw), syw = Math.sin(state.yaw), cp = Math.cos(state.pitch), sp = Math.sin(state.pitch);
    const xr = x * cy - y * syw, yr = x * syw + y * cy;
    const s = Math.min(W, H) * 0.27;
    return [W / 2 + s * xr, H / 2 - s * (z * cp - yr * sp), yr * cp + z * sp];
  }
  function draw() {
    for (const [a, b, line] of edges) {
      const [ax, ay] = place(...a), [bx, by] = place(...b);
      line.setAttribute("x1", ax); line.setAttribute("y1", ay); line.setAttribute("x2", bx); line.setAttribute("y2", by);
    }
    axes.forEach((a, m) => {
      const from = [-1, -1, -1], to = [-1, -1, -1];
      to[m] = 1;
      const [ax, ay] = place(...from), [bx, by] = place(...to), [lx, ly] = place(...to.map((v, k) => (k === m ? 1.22 : v)));
      a.line.setAttribute("x1", ax); a.line.setAttribute("y1", ay); a.line.setAttribute("x2", bx); a.line.setAttribute("y2", by);
      a.label.setAttribute("x", lx); a.label.setAttribute("y", ly);
      for (const t of a.ticks) {
        const q = [-1, -1, -1];
        q[m] = norm(m, t.v);
        const [tx, ty] = place(...q);
        t.t.setAttribute("x", tx); t.t.setAttribute("y", ty + 12);
      }
    });
    const depth = [];
    for (const d of drawn) {
      const [px, py, pz] = place(norm(0, d.it.p.returns[0]), norm(1, d.it.p.returns[1]), norm(2, d.it.p.returns[2]));
      if (d.node.tagName === "circle") { d.node.setAttribute("cx", px); d.node.setAttribute("cy", py); }
      else d.node.setAttribute("points", star(px, py, 9));
      depth.push([pz + (d.it.p.origin === "specialist" ? 10 : 0), d.node]);
    }
    depth.sort((a, b) => b[0] - a[0]).forEach(([, node]) => layer.appendChild(node));  // far first, stars last
  }
  let drag = null;
  svg.addEventListener("mousedown", (e) => { drag = [e.clientX, e.clientY]; state.spin = false; });
  window.addEventListener("mouseup", () => { drag = null; });
  svg.addEventListener("mousemove", (e) => {
    if (!drag) return;
    state.yaw += (e.clientX - drag[0]) * 0.01;
    state.pitch = Math.max(-1.4, Math.min(1.4, state.pitch + (e.clientY - drag[1]) * 0.01));
    drag = [e.clientX, e.clientY];
    draw();
  });
  svg.addEventListener("mouseenter", () => { state.spin = false; });
  svg.addEventListener("mouseleave", () => { if (!drag) state.spin = true; });
  const spin = () => { if (state.spin) { state.yaw += 0.008; draw(); } requestAnimationFrame(spin); };
  draw();
  requestAnimationFrame(spin);
}

function select(item) {
  shown = item;
  const p = item.p, panel = item.panel;
  document.querySelectorAll(".pt.sel").forEach((e) => e.classList.remove("sel"));
  item.nodes.forEach((e) => e.classList.add("sel"));
  const v = document.getElementById("clip"), note = document.getElementById("noclip");
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
  DATA.objectives.forEach((name, m) => rows.push([name, fmt(p.returns[m]) + " \u00b1 " + fmt(p.std[m])]));
  if (p.clip) rows.push(["clip's episode", p.clip.returns.map(fmt).join(", ") + " (" + p.clip.episode_steps + " steps)"]);
  rows.push(["origin", p.origin + (p.origin === "specialist" ? " of objective " + p.objective + " (" + p.policy_name + ")" : "")]);
  rows.push(["parents", p.parents.length ? p.parents.join(", ") : "-"]);
  rows.push(["target weight", p.target_weight ? p.target_weight.join(", ") : "-"]);
  rows.push(["iteration", p.iteration]);
  rows.push(["on the front", p.on_front ? "yes" : "no (dominated)"]);
  let link = "- (stage export did not write it: add the method to export.methods)";
  if (p.export) {
    link = document.createElement("a");
    link.setAttribute("href", url(p.export));
    link.textContent = p.export_file || p.export;
  }
  rows.push(["exported file", link]);
  const t = document.getElementById("info");
  t.replaceChildren(...rows.map(([name, value]) => {
    const tr = document.createElement("tr");
    tag("td", name, tr);
    const td = tag("td", null, tr);
    if (value instanceof Node) td.appendChild(value); else td.textContent = String(value);
    return tr;
  }));
  t.dataset.key = item.key;
  const load = document.getElementById("load");
  load.replaceChildren();
  if (p.export) {
    tag("div", "Load it (from the project's folder, no mapex needed):", load, "note");
    tag("pre", "import torch\npolicy = torch.jit.load(" + JSON.stringify(p.export_file || p.export) + ")", load).id = "loadcode";
  }
}

function visible(it) { return !hidden.has(it.panel.method); }
function toggle(method, button) {
  if (hidden.has(method)) hidden.delete(method); else hidden.add(method);
  button.classList.toggle("off", hidden.has(method));
  document.querySelectorAll("[data-method]").forEach((e) => { if (e.tagName !== "BUTTON") e.classList.toggle("gone", hidden.has(e.dataset.method)); });
  pick(false);
}

// The preference: a weight per objective; the front member of the methods shown with the best
// weighted sum of its returns, each objective scaled to [0, 1] over those members.
const weights = DATA.objectives.map(() => 1 / N);
function best() {
  const front = ITEMS.filter((it) => it.p.on_front && visible(it));
  if (!front.length) return null;
  const lo = DATA.objectives.map((_, m) => Math.min(...front.map((it) => it.p.returns[m])));
  const hi = DATA.objectives.map((_, m) => Math.max(...front.map((it) => it.p.returns[m])));
  let top = null, topScore = -Infinity;
  for (const it of front) {
    let score = 0;
    for (let m = 0; m < N; m++) score += weights[m] * (hi[m] > lo[m] ? (it.p.returns[m] - lo[m]) / (hi[m] - lo[m]) : 0);
    if (score > topScore) { top = it; topScore = score; }
  }
  return top;
}
function pick(play) {
  const top = best();
  document.querySelectorAll(".pt.pick").forEach((e) => e.classList.remove("pick"));
  const out = document.getElementById("picked");
  if (!top) { out.textContent = "no front shown"; delete out.dataset.key; return; }
  top.nodes.forEach((e) => e.classList.add("pick"));
  out.textContent = top.panel.label + ", seed " + top.panel.seed + ", member " + top.p.id;
  out.dataset.key = top.key;
  if (play) { pinned = top.key; select(top); }
}

const legend = document.getElementById("legend");
tag("span", "Methods:", legend, "note");
for (const m of METHODS) {
  const b = tag("button", null, legend);
  const sw = tag("span", null, b, "swatch");
  sw.style.background = m.colour;
  b.appendChild(document.createTextNode(m.label));
  b.dataset.method = m.method;
  b.addEventListener("click", () => toggle(m.method, b));
}
const pref = document.getElementById("pref");
tag("span", "Preference (weight per objective; returns scaled to [0, 1] over the fronts shown):", pref, "note");
DATA.objectives.forEach((name, m) => {
  const lab = tag("label", name + " ", pref);
  const input = document.createElement("input");
  input.setAttribute("type", "range"); input.setAttribute("min", "0"); input.setAttribute("max", "1"); input.setAttribute("step", "0.05");
  input.value = String(weights[m]);
  input.dataset.objective = String(m);
  input.classList.add("weight");
  lab.appendChild(input);
  const value = tag("span", weights[m].toFixed(2), lab);
  input.addEventListener("input", () => { weights[m] = Number(input.value); value.textContent = weights[m].toFixed(2); pick(true); });
});
tag("span", "best:", pref, "note");
const picked = tag("span", "", pref);
picked.id = "picked";

const seedsRoot = document.getElementById("seeds");
for (const seed of SEEDS) {
  const items = ITEMS.filter((it) => it.panel.seed === seed);
  const counts = METHODS.map((m) => m.label + " " + items.filter((it) => it.panel.method === m.method && it.p.on_front).length);
  const sec = tag("section", null, seedsRoot);
  sec.dataset.seed = String(seed);
  tag("h2", "seed " + seed + " (front sizes: " + counts.join(", ") + ")", sec);
  const row = tag("div", null, sec, "plots");
  if (N === 2) { scatter(row, items, 0, 1, 480, 380); sec.style.maxWidth = "484px"; }  // seeds side by side
  else {
    for (let i = 0; i < N; i++) for (let j = i + 1; j < N; j++) scatter(row, items, i, j, 340, 280);
    if (N === 3) view3d(row, items, 420, 400);
  }
}
if (!SEEDS.length) tag("p", "No front to show.", seedsRoot);
document.getElementById("main").addEventListener("click", (e) => { if (e.target.tagName === "svg") pinned = null; });
pick(false);
</script></body></html>
"""
