"""Stage render: a clip of every front policy (MP4 + thumbnail + returns) and the explorer page."""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path
from typing import Optional

import typer

from pipeline.core.artifacts import ArtifactError, write_text_atomic
from pipeline.core.envs import objective_names
from pipeline.core.provenance import write_provenance
from pipeline.core.workers import split_evenly
from pipeline.evaluation.render import (
    Film,
    choose_gl,
    clip_key,
    film_clips,
    needs_gl,
    render_problem,
)
from pipeline.params import ParamsError
from pipeline.params.render import RenderParams
from pipeline.params.variants import parse_variants
from pipeline.reporting.explorer import explorer_html, hex_colour, load_front_run, point_record
from pipeline.reporting.presentation import colour, label, use_variants
from stages.common import PARAMS_OPTION, PROVENANCE_OPTION, progress, read_params, reports_errors, run_parts

INDEX_FORMAT = "mapex.render"
INDEX_VERSION = 1


def fronts_csv(panels: list[dict], n_obj: int) -> str:
    """Every front member of every panel, one row each (the DVC plot of the fronts)."""
    objs = [f"obj{m}" for m in range(n_obj)]
    lines = [",".join(["method", "seed", "id", "origin", *objs, "clip"])]
    for p in panels:
        for pt in p["points"]:
            if pt["on_front"]:
                clip = pt["clip"]["mp4"] if pt["clip"] else ""
                row = [
                    p["method"],
                    str(p["seed"]),
                    str(pt["id"]),
                    pt["origin"],
                    *(repr(x) for x in pt["returns"]),
                    clip,
                ]
                lines.append(",".join(row))
    return "\n".join(lines) + "\n"


def prune(out: Path, keep: set[Path]) -> None:
    """Remove what an earlier run left under OUT/clips and OUT/thumbs that this run does not list."""
    for sub in ("clips", "thumbs"):
        for path in sorted((out / sub).rglob("*"), reverse=True) if (out / sub).is_dir() else []:
            if path.is_file() and path not in keep:
                path.unlink()
            elif path.is_dir() and not any(path.iterdir()):
                path.rmdir()


@reports_errors
def render(
    fronts: Path = typer.Option(..., help="root of the fronts, holding METHOD/seedS/population.pt"),
    evaluated: Path = typer.Option(..., help="root of the evaluate outputs, holding METHOD/seedS/evaluated.csv"),
    out: Path = typer.Option(..., help="output folder: explorer.html, fronts.csv, index.json, clips/, thumbs/"),
    export_root: Path = typer.Option(
        Path("data/export"), "--export", help="where stage export writes (linked from the page when export ran)"
    ),
    params: Path = PARAMS_OPTION,
    provenance: Optional[Path] = PROVENANCE_OPTION,
) -> None:
    """Film every non-dominated member of the fronts of render.methods x render.seeds and write
    the explorer page of every method and seed params.yaml runs.

    Each member plays one deterministic episode from reset seed render.episode_seed, to its
    end (the episode's returns), filmed offscreen (MUJOCO_GL: egl, else osmesa, unless set)
    by a camera that follows the robot (render.camera: null) for its first render.frames frames
    at render.width x render.height, render.processes clips at a time. Per member:
    OUT/clips/METHOD/seedS/member_<id>.mp4 (H.264) and .json (its episode's returns, steps,
    frames, the clip's key), OUT/thumbs/METHOD/seedS/member_<id>.png (the middle frame).

    A clip is rendered only when its record is missing or its key (the actor's weights, the
    env, the render params) differs, and what no front lists any more is removed (run by hand;
    under dvc repro, DVC clears OUT first and its run-cache restores earlier renders). Every file is written whole (atomically), each
    record after its clip. OUT/explorer.html (self-contained: open it from file://),
    OUT/fronts.csv (the DVC plot) and OUT/index.json are rewritten last.
    """
    raw, env_p, cfg, run_p = read_params(params, "render", RenderParams)
    use_variants(parse_variants(run_p.variants))  # the variants' labels and colours
    exported = set(run_p.export_methods)  # export.methods, as the generated list (always in the file)
    stray = [m for m in cfg.methods if m not in run_p.methods]
    if stray:
        raise ParamsError(f"{params}: render.methods lists {stray}, which methods = {run_p.methods} does not run")
    film_seeds = run_p.seeds if cfg.seeds is None else cfg.seeds
    stray = [s for s in film_seeds if s not in run_p.seeds]
    if stray:
        raise ParamsError(f"{params}: render.seeds lists {stray}, which seeds = {run_p.seeds} does not run")
    film = Film(
        env_p.id, env_p.max_episode_steps, cfg.frames, cfg.every, cfg.fps, cfg.width, cfg.height, cfg.camera,
        cfg.distance, cfg.elevation, cfg.azimuth, cfg.shadow_size, cfg.samples, cfg.episode_seed,
        tuple(t.model_dump() for t in env_p.reward_terms or ()),
    )  # fmt: skip
    runs = [
        load_front_run(fronts / m / f"seed{s}" / "population.pt", evaluated / m / f"seed{s}")
        for m in run_p.methods
        for s in run_p.seeds
    ]
    for r in runs:
        if r.meta["env_id"] != env_p.id:
            raise ArtifactError(
                f"{fronts / r.method / f'seed{r.seed}'}: made on {r.meta['env_id']}, env.id is {env_p.id}"
            )
    jobs = [(r, i) for r in runs if r.method in cfg.methods and r.seed in film_seeds for i in r.front]
    out.mkdir(parents=True, exist_ok=True)
    records: dict[tuple[str, int, int], dict] = {}
    keep: set[Path] = set()
    todo = []
    for r, i in jobs:
        stem = Path(r.method) / f"seed{r.seed}" / f"member_{i:04d}"
        paths = (out / "clips" / f"{stem}.mp4", out / "thumbs" / f"{stem}.png", out / "clips" / f"{stem}.json")
        keep.update(paths)
        key = clip_key(r.members[i].actor, r.members[i].hidden_sizes, r.meta, film)
        old = json.loads(paths[2].read_text()) if paths[2].is_file() else {}
        if old.get("key") == key and paths[0].is_file() and paths[1].is_file():
            records[(r.method, r.seed, i)] = old
        else:
            todo.append((r, i, key, paths))
    # An env that cannot be filmed here gets the explorer without clips and one line saying why
    # (render_problem); a MuJoCo env needs an OpenGL backend (choose_gl), any other draws itself.
    no_clips = render_problem(film) if todo else None
    if no_clips is not None:
        typer.echo(f"render: no clips ({no_clips}); the explorer shows the fronts without them", err=True)
        keep -= {p for *_, paths in todo for p in paths}
        todo = []
    backend = (choose_gl() if needs_gl(film) else "the env's own rgb_array") if todo else None
    if todo:
        jobs_of = [
            [(r.members[i], r.meta, paths, {"method": r.method, "seed": r.seed, "id": i, "episode_seed": film.episode_seed,
              "key": key}) for r, i, key, paths in part]
            for part in split_evenly(todo, cfg.processes)
        ]  # fmt: skip
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        gl_threads = max(1, cores // len(jobs_of))  # Mesa's rasteriser threads per process
        t0 = time.perf_counter()
        with progress(len(todo), f"render ({backend}, {len(jobs_of)} process(es))", unit="clip") as bar:
            run_parts(film_clips, [(film, jobs, gl_threads) for jobs in jobs_of], bar, lambda k: f"render part {k}", "")
        spent = time.perf_counter() - t0
    for r, i, key, (mp4, png, rec) in todo:
        records[(r.method, r.seed, i)] = json.loads(rec.read_text())
    prune(out, keep)
    names = objective_names(env_p.id, runs[0].means.shape[1], env_p.objective_names)
    panels = []
    for r in runs:
        points = []
        for i in sorted(set(r.front) | {k for k, m in enumerate(r.members) if m.origin == "specialist"}):
            rec = records.get((r.method, r.seed, i))
            stem = f"{r.method}/seed{r.seed}/member_{i:04d}"
            clip = None
            if rec is not None:
                clip = {"mp4": f"clips/{stem}.mp4", "thumb": f"thumbs/{stem}.png"}
                clip |= {k: rec[k] for k in ("returns", "episode_steps", "frames", "fps")}
            export = export_file = None
            if r.method in exported and i in r.front:
                export_file = export_root / r.method / f"seed{r.seed}" / f"member_{i:04d}.pt"
                export = os.path.relpath(export_file, out)
            points.append(point_record(r, i, clip, export, None if export_file is None else export_file.as_posix()))
        panels.append(
            {
                "method": r.method,
                "label": label(r.method),
                "colour": hex_colour(colour(r.method)),
                "seed": r.seed,
                "front": r.front,
                "points": points,
            }
        )
    index = {"format": INDEX_FORMAT, "format_version": INDEX_VERSION, "objectives": names, "panels": panels}
    if no_clips is not None:
        index["no_clips"] = no_clips
    write_text_atomic(out / "index.json", json.dumps(index, indent=1) + "\n")
    write_text_atomic(out / "fronts.csv", fronts_csv(panels, len(names)))
    write_text_atomic(
        out / "explorer.html",
        explorer_html(
            panels, names, f"MAPEX fronts on {env_p.id}", None if no_clips is None else f"No clips: {no_clips}"
        ),
    )
    for stale in (out / "clips", out / "thumbs"):
        if stale.is_dir() and not any(stale.iterdir()):
            shutil.rmtree(stale)
    write_provenance(provenance, "render", "cpu")
    rate = (
        f" in {spent:.1f} s with {backend if backend.startswith('the env') else 'MUJOCO_GL=' + backend}" if todo else ""
    )
    typer.echo(
        f"render: {len(todo)} clip(s) rendered{rate}, {len(jobs) - len(todo)} kept; {out / 'explorer.html'}", err=True
    )
