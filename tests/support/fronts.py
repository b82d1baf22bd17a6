"""Synthetic fronts for the explorer page: no training, no MuJoCo. Each method and seed gets two
or three starting policies (one per objective, at the ends) and children on a curved front, as
stage render's panels hold them (`pipeline.reporting.explorer.point_record`'s keys)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.evaluation.render import mp4_bytes
from pipeline.reporting.explorer import hex_colour
from pipeline.reporting.presentation import colour, label


def tiny_mp4(path: Path, shade: int, size: tuple[int, int] = (64, 48), frames: int = 8) -> None:
    """A real H.264 clip (a bar moving across a flat colour), so the browser has frames to decode."""
    w, h = size
    video = np.full((frames, h, w, 3), shade, np.uint8)
    bar = max(w // frames, 2)
    for t in range(frames):
        video[t, :, bar * t : bar * t + bar] = 255 - shade
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(mp4_bytes(video, 8, path))


def point(i: int, returns, origin="child", objective=None, policy_name=None, clip=None, export=None) -> dict:
    n = len(returns)
    return {
        "id": i,
        "on_front": True,
        "origin": origin,
        "objective": objective,
        "policy_name": policy_name,
        "iteration": 0 if origin == "specialist" else i,
        "parents": [] if origin == "specialist" else [0, 1],
        "target_weight": None if origin == "specialist" else [round(1 / n, 4)] * n,
        "returns": [float(x) for x in returns],
        "std": [abs(float(x)) * 0.05 + 1 for x in returns],
        "clip": clip,
        "export": export,
        "export_file": None if export is None else export.removeprefix("../"),
    }


SCALE = {2: np.array([2500.0, 1500.0]), 3: np.array([2500.0, 1500.0, 900.0])}
OFFSET = {2: np.array([0.0, -1600.0]), 3: np.array([0.0, -1600.0, 0.0])}


def synthetic_panels(
    root: Path, n_obj: int, methods: list[str], seeds: list[int], children: int = 6, clips: bool = True
) -> list[dict]:
    """Panels for `methods` x `seeds`: per panel n_obj starting policies and `children` children on
    the front sum_m (x_m)^2 = 1 (scaled), a dominated starting policy where the draw puts one;
    every front member filmed (a tiny clip under root/clips/) when `clips`, and "exported"."""
    rng = np.random.default_rng(0)
    panels = []
    for k, method in enumerate(methods):
        for seed in seeds:
            pts = []
            quality = 0.75 + 0.08 * k + 0.03 * rng.standard_normal()
            for m in range(n_obj):  # a specialist: nearly all of objective m
                x = np.full(n_obj, 0.08) + 0.04 * rng.random(n_obj)
                x[m] = quality
                pts.append(("specialist", m, x))
            for _ in range(children):
                d = np.abs(rng.standard_normal(n_obj)) + 0.2
                pts.append(("child", None, quality * d / np.linalg.norm(d) * (0.9 + 0.1 * rng.random())))
            returns = np.array([x for *_, x in pts]) * SCALE[n_obj] + OFFSET[n_obj]
            on_front = [not any(np.all(o >= r) and np.any(o > r) for o in returns) for r in returns]
            points = []
            for i, ((origin, obj, _), r, front) in enumerate(zip(pts, returns, on_front)):
                stem = f"{method}/seed{seed}/member_{i:04d}"
                clip = None
                if clips and front:
                    tiny_mp4(root / "clips" / f"{stem}.mp4", 30 + 20 * (i % 8))
                    clip = {"mp4": f"clips/{stem}.mp4", "thumb": f"thumbs/{stem}.png", "returns": list(r)}
                    clip |= {"episode_steps": 750, "frames": 8, "fps": 8}
                p = point(i, r, origin, obj, "policy" if origin == "specialist" else None, clip)
                p["on_front"] = bool(front)
                if front:
                    p["export"] = f"../export/{stem}.pt"
                    p["export_file"] = f"data/export/{stem}.pt"
                points.append(p)
            front_ids = sorted((i for i, f in enumerate(on_front) if f), key=lambda i: returns[i, 0])
            panels.append(
                {
                    "method": method,
                    "label": label(method),
                    "colour": hex_colour(colour(method)),
                    "seed": seed,
                    "front": front_ids,
                    "points": points,
                }
            )
    return panels


def preferred(panels: list[dict], weights, hidden: tuple[str, ...] = ()) -> str:
    """The key (method/seed/id) of the front member with the best weighted return, each objective
    scaled to [0, 1] over the front members of the methods not hidden: computed with numpy,
    apart from the page's script (first of equals in panel order, as the page does)."""
    keys, rows = [], []
    for panel in panels:
        if panel["method"] in hidden:
            continue
        for p in panel["points"]:
            if p["on_front"]:
                keys.append(f"{panel['method']}/{panel['seed']}/{p['id']}")
                rows.append(p["returns"])
    r = np.array(rows)
    lo, hi = r.min(axis=0), r.max(axis=0)
    scores = np.where(hi > lo, (r - lo) / np.where(hi > lo, hi - lo, 1), 0.0) @ np.asarray(weights, float)
    top, second = np.sort(scores)[::-1][:2]
    assert top - second > 1e-6, f"weights {weights}: two members tie ({top}, {second}); choose other weights"
    return keys[int(np.argmax(scores))]
