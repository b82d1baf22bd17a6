"""Stage render and the explorer page, as a user sees them: real frames from MuJoCo's offscreen
renderer, and the page opened in a real headless browser (Debian's chromium) that clicks a point.

Skips, saying why, where no OpenGL backend renders MuJoCo or no chromium is installed.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from support.browser import changes, open_browser

from pipeline.core.envs import env_spec, make_env
from pipeline.core.nets import Actor
from pipeline.core.population import Member, save_population
from pipeline.evaluation.episodes import EvalResult
from pipeline.evaluation.render import Camera, Film, film_episode, gl_problem, make_render_env, root_body

ENV, STEPS = "mo-halfcheetah-v5", 30
FRAMES, WIDTH, HEIGHT = 8, 64, 48


@pytest.fixture(scope="module")
def gl() -> str:
    problem = gl_problem()
    if problem is not None:
        pytest.skip(f"no GL backend: {problem}")
    return os.environ["MUJOCO_GL"]


def write_front(root: Path, method: str = "mapex_td3", seed: int = 0) -> None:
    """A population of 4 random actors (2 specialists, 2 children; member 2 dominated) and evaluate's
    outputs for it, under root/fronts and root/evaluate."""
    from stages.evaluate import evaluated_csv

    env = make_env(ENV, STEPS)
    spec = env_spec(env, ENV, STEPS)
    env.close()
    torch.manual_seed(seed)
    meta = {"env_id": ENV, "n_objectives": 2, "seed": seed, "method": method, "params": {}}
    meta |= {"obs_dim": spec.obs_dim, "act_dim": spec.act_dim}
    meta |= {"action_low": list(spec.action_low), "action_high": list(spec.action_high)}
    members = []
    for i, ret in enumerate([[10.0, -50.0], [0.0, -5.0], [5.0, -60.0], [6.0, -20.0]]):
        actor = Actor(spec.obs_dim, spec.act_dim, [8, 8], spec.action_low, spec.action_high)
        for p in actor.parameters():  # large weights: actions far from zero, so the cheetah moves
            torch.nn.init.normal_(p, std=1.0)
        spec_member = i < 2
        members.append(
            Member(
                origin="specialist" if spec_member else "child",
                objective=i if spec_member else None,
                iteration=0 if spec_member else i - 1,
                parents=[] if spec_member else [0, 1],
                target_weight=None if spec_member else [0.6, 0.8],
                returns=ret,
                returns_std=[0.0, 0.0],
                eval_episodes=1,
                env_samples=i,
                hidden_sizes=[8, 8],
                actor={k: v.clone() for k, v in actor.state_dict().items()},
                policy_name="policy" if spec_member else None,
            )
        )
    pop = root / "fronts" / method / f"seed{seed}" / "population.pt"
    pop.parent.mkdir(parents=True)
    save_population(pop, members, meta)
    ev = root / "evaluate" / method / f"seed{seed}"
    ev.mkdir(parents=True)
    spread = np.array([1.0, 2.0])
    results = [EvalResult(np.stack([np.array(m.returns) - spread, np.array(m.returns) + spread]), 0) for m in members]
    (ev / "evaluated.csv").write_text(evaluated_csv(members, results))
    record = {"env_id": ENV, "method": method, "seed": seed, "episodes": 2, "population": len(members)}
    (ev / "evaluation.json").write_text(json.dumps(record | {"env_samples_evaluation": 0}))


def params_file(root: Path, **render) -> Path:
    p = {
        "env": {"id": ENV, "max_episode_steps": STEPS},
        "seeds": [0],
        "methods": ["mapex_td3"],
        "export": {"methods": ["mapex_td3"]},
        "export_methods": ["mapex_td3"],
        "render": {"methods": ["mapex_td3"], "frames": FRAMES, "width": WIDTH, "height": HEIGHT} | render,
    }
    path = root / "params.yaml"
    path.write_text(yaml.safe_dump(p))
    return path


def run_render(cli, root: Path, **render):
    args = ["render", "--fronts", root / "fronts", "--evaluated", root / "evaluate", "--out", root / "render"]
    return cli(*args, "--export", root / "export", "--params", params_file(root, **render))


@pytest.fixture(scope="module")
def rendered(gl, tmp_path_factory) -> Path:
    from typer.testing import CliRunner

    from stages.cli import app

    root = tmp_path_factory.mktemp("render")
    write_front(root)
    args = ["render", "--fronts", root / "fronts", "--evaluated", root / "evaluate", "--out", root / "render"]
    args += ["--export", root / "export", "--params", params_file(root)]
    result = CliRunner().invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, result.output
    return root


def test_render_films_every_front_member_with_real_frames(rendered):
    import imageio.v3 as iio

    clips = rendered / "render" / "clips" / "mapex_td3" / "seed0"
    # members 0, 1 and 3 are non-dominated (2 is dominated by 0): one clip each, nothing for 2
    assert sorted(p.name for p in clips.glob("*.mp4")) == ["member_0000.mp4", "member_0001.mp4", "member_0003.mp4"]
    for stem in ("member_0000", "member_0001", "member_0003"):
        frames = iio.imread(clips / f"{stem}.mp4")
        assert frames.shape == (FRAMES, HEIGHT, WIDTH, 3), frames.shape
        assert frames.std() > 5, "a blank clip"
        moved = [np.abs(frames[k + 1].astype(int) - frames[k].astype(int)).mean() for k in range(FRAMES - 1)]
        assert max(moved) > 0.5, f"{stem}: the frames do not change ({moved})"
        thumb = iio.imread(rendered / "render" / "thumbs" / "mapex_td3" / "seed0" / f"{stem}.png")
        assert thumb.shape == (HEIGHT, WIDTH, 3) and thumb.std() > 5
        rec = json.loads((clips / f"{stem}.json").read_text())
        assert rec["frames"] == FRAMES and rec["episode_steps"] == STEPS and len(rec["returns"]) == 2
    # different policies from the same reset seed: different episodes
    recs = [json.loads(p.read_text())["returns"] for p in sorted(clips.glob("*.json"))]
    assert len({tuple(r) for r in recs}) == 3, recs
    index = json.loads((rendered / "render" / "index.json").read_text())
    (panel,) = index["panels"]
    assert panel["front"] == [1, 3, 0]  # sorted by objective 0
    point = {p["id"]: p for p in panel["points"]}[3]
    assert point["export"] == "../export/mapex_td3/seed0/member_0003.pt" and point["parents"] == [0, 1]
    assert point["std"] == [1.0, 2.0]
    lines = (rendered / "render" / "fronts.csv").read_text().splitlines()
    assert lines[0] == "method,seed,id,origin,obj0,obj1,clip" and len(lines) == 4


def test_a_rerun_renders_only_what_is_missing_and_removes_what_no_front_lists(cli, rendered):
    clips = rendered / "render" / "clips" / "mapex_td3" / "seed0"
    before = {p.name: p.stat().st_mtime_ns for p in clips.iterdir()}
    (clips / "member_0001.mp4").unlink()
    (clips / "stale_0009.mp4").write_bytes(b"x")
    result = run_render(cli, rendered)
    assert result.exit_code == 0, result.output
    assert "1 clip(s) rendered in" in result.output and "2 kept" in result.output
    after = {p.name: p.stat().st_mtime_ns for p in clips.iterdir()}
    assert "stale_0009.mp4" not in after
    assert after["member_0000.mp4"] == before["member_0000.mp4"]  # untouched
    assert after["member_0001.mp4"] != before["member_0001.mp4"]


def test_render_refuses_a_method_that_does_not_run(cli, tmp_path):
    write_front(tmp_path)
    result = run_render(cli, tmp_path, methods=["morld"])
    assert result.exit_code == 2
    assert "render.methods lists ['morld']" in result.output


def test_no_gl_backend_is_one_line_naming_mujoco_gl(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "no-such-backend")
    problem = gl_problem()
    assert problem is not None and "MUJOCO_GL=no-such-backend" in problem and "render.methods: []" in problem
    assert "\n" not in problem


# -- the page in a real browser (Playwright driving Debian's chromium: tests/support/browser.py) --


def test_explorer_plays_the_clip_of_the_point_clicked(rendered, tmp_path):
    with open_browser() as new_page:
        page, watched = new_page(rendered / "render" / "explorer.html")
        page.wait_for_selector(".pt")
        # one plot (one seed), one projection for 2 objectives; the specialists are stars
        assert page.locator("section").count() == 1 and page.locator("svg.plot").count() == 1
        assert page.locator("polygon.pt").count() == 2
        key = "mapex_td3/0/3"
        page.hover(f".pt[data-key='{key}']")
        page.click(f".pt[data-key='{key}']")
        src = page.wait_for_function("document.getElementById('clip').currentSrc").json_value()
        assert src.endswith("clips/mapex_td3/seed0/member_0003.mp4"), src
        # the clip really loads and decodes in the browser (H.264), plays, and the table shows its record
        state = page.wait_for_function(
            "(() => { const v = document.getElementById('clip');"
            " return v.error ? 'error ' + v.error.code : (v.readyState >= 2 ? [v.videoWidth, v.videoHeight] : null); })()"
        ).json_value()
        assert state == [WIDTH, HEIGHT], state
        t0 = page.evaluate("document.getElementById('clip').currentTime")
        assert changes(page, "document.getElementById('clip').currentTime", t0), "the clip does not play"
        info = page.locator("#info").inner_text()
        assert "0.6, 0.8" in info and "0, 1" in info and "member_0003.pt" in info, info
        page.screenshot(path=str(tmp_path / "explorer.png"))
        assert (tmp_path / "explorer.png").stat().st_size > 5000
        assert not watched.network() and not watched.console_errors and not watched.page_errors, watched


def test_the_report_links_the_explorer_and_shows_the_fronts_ends_and_middle(rendered, tmp_path):
    from pipeline.reporting.gallery import gallery_markdown

    out = rendered / "report"
    text = gallery_markdown(rendered / "render", out, tmp_path, ["mapex_td3"], [0])
    assert "[The front explorer](../render/explorer.html)" in text
    # front sorted by objective 0: member 1 (lowest), 3 (middle), 0 (highest)
    for i in (1, 3, 0):
        assert f"(thumbs/mapex_td3_seed0_member_{i:04d}.png)" in text
        assert (tmp_path / "thumbs" / f"mapex_td3_seed0_member_{i:04d}.png").stat().st_size > 100
    assert text.index("member_0001.png") < text.index("member_0003.png") < text.index("member_0000.png")
    assert "(../render/clips/mapex_td3/seed0/member_0003.mp4)" in text
    assert gallery_markdown(rendered / "render", out, tmp_path, ["mapex_td3"], [1]).count("thumbs/") == 0


# -- the camera follows the robot ------------------------------------------------------------------

# An open-loop gait found by random search over sinusoids (one frequency, a phase and an amplitude
# per joint): it drives mo-halfcheetah-v5 11 to 19 m in 200 steps (10 s) from reset seeds 0 to 3.
GAIT_HZ = 3.43
GAIT_PHASE = [4.4, 0.81, 3.27, 0.42, 1.08, 1.97]
GAIT_AMP = [1.56, 1.43, 1.3, 0.77, 0.95, 1.53]
RUN_STEPS = 200


class Gait(torch.nn.Module):
    """A policy that ignores its observation: the gait's action at its own step count (dt 0.05 s)."""

    def __init__(self):
        super().__init__()
        self.t = 0

    def forward(self, obs):
        phase = 2 * np.pi * GAIT_HZ * self.t * 0.05 + np.array(GAIT_PHASE)
        self.t += 1
        return torch.as_tensor(np.clip(np.array(GAIT_AMP) * np.sin(phase), -1, 1), dtype=torch.float32)[None]


def project(scene, point: np.ndarray, width: int, height: int) -> tuple[float, float]:
    """The pixel (column, row from the top) where `point` (world, m) appears in a frame drawn from
    `scene`'s camera: MuJoCo's pinhole (its pose, and its frustum from the model's fovy)."""
    import mujoco

    cam = mujoco.mjv_averageCamera(scene.camera[0], scene.camera[1])  # what a mono frame is drawn from
    forward, up = np.array(cam.forward), np.array(cam.up)
    right = np.cross(forward, up)
    rel = point - np.array(cam.pos)
    depth = rel @ forward
    assert depth > cam.frustum_near, "behind the camera"
    half_h = (cam.frustum_top - cam.frustum_bottom) / 2
    x = (rel @ right) / depth * cam.frustum_near - cam.frustum_center
    y = (rel @ up) / depth * cam.frustum_near - (cam.frustum_top + cam.frustum_bottom) / 2
    return (1 + x / (half_h * width / height)) * width / 2, (1 - y / half_h) * height / 2


class Watching(Camera):
    """The stage's camera, noting after each frame where the root body appears in it and which
    body the segmentation pass draws at that pixel (0: the world, the floor)."""

    def __init__(self, env, film, fixed: bool = False):
        super().__init__(env, film)
        self.env, self.seen, self.xs = env, [], []
        if fixed:  # what the env's own render camera does: a free camera that stands still
            import mujoco

            self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
            self.camera.lookat[:] = env.unwrapped.data.subtree_com[root_body(self.model)]

    def frame(self, data):
        image = super().frame(data)
        root = root_body(self.model)
        u, v = project(self.scene, np.array(data.xpos[root]), image.shape[1], image.shape[0])
        self.renderer.enable_segmentation_rendering()
        seg = self.renderer.render()
        self.renderer.disable_segmentation_rendering()
        body = 0
        if 0 <= u < image.shape[1] and 0 <= v < image.shape[0]:
            r, c = int(v), int(u)
            patch = seg[max(r - 2, 0) : r + 3, max(c - 2, 0) : c + 3].reshape(-1, 2)
            bodies = [self.model.geom_bodyid[g] for g, kind in patch if kind == 5 and g >= 0]  # 5: mjOBJ_GEOM
            body = max(bodies, default=0)
        self.seen.append((u, v, body))
        self.xs.append(float(data.xpos[root][0]))
        return image


def film_the_gait(fixed: bool):
    film = Film(ENV, RUN_STEPS, None, 5, None, 160, 120, None, None, -15.0, 90.0, 0, 0, 0)
    env = make_render_env(film)
    camera = Watching(env, film, fixed)
    try:
        clip = film_episode(Gait(), env, camera, film)
    finally:
        camera.close()
        env.close()
    return clip, camera


def test_the_camera_keeps_a_fast_runner_in_the_frame(gl):
    clip, camera = film_the_gait(fixed=False)
    assert clip.steps == RUN_STEPS and len(clip.frames) == RUN_STEPS // 5 + 1
    assert camera.xs[-1] - camera.xs[0] > 5, f"the gait ran {camera.xs[-1] - camera.xs[0]:.1f} m, not fast enough"
    for k, (u, v, body) in enumerate(camera.seen):
        assert 0 <= u < 160 and 0 <= v < 120, f"frame {k}: the root body is drawn at ({u:.0f}, {v:.0f}), off the frame"
        assert body > 0, f"frame {k}: no robot drawn where the root body projects ({u:.0f}, {v:.0f})"


def test_a_camera_that_stands_still_loses_the_same_runner(gl):
    """The check above can fail: from a camera that stands still, the runner leaves the frame."""
    _, camera = film_the_gait(fixed=True)
    inside = [0 <= u < 160 and 0 <= v < 120 for u, v, _ in camera.seen]
    assert inside[0] and camera.seen[0][2] > 0  # the projection and the pixels agree at the start
    assert not all(inside), "a fixed camera kept the runner in view: the gait is too slow to test the camera"


def test_the_stage_page_shows_hostile_names_and_paths_as_text(cli, rendered, tmp_path):
    """End to end: objective names from params and an export folder whose name holds quotes,
    spaces and markup, through the stage into the page, shown as text with no script run."""
    hostile = ["<img src=x onerror=window.__pwned=1>", '"></script><script>window.__pwned=2</script>']
    for sub in ("fronts", "evaluate"):
        shutil.copytree(rendered / sub, tmp_path / sub)
    params = yaml.safe_load(params_file(tmp_path, processes=1).read_text())
    params["env"]["objective_names"] = hostile
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    export = tmp_path / 'it\'s an "export" <b>'
    args = [
        "render",
        "--fronts",
        tmp_path / "fronts",
        "--evaluated",
        tmp_path / "evaluate",
        "--out",
        tmp_path / "render",
    ]
    result = cli(*args, "--export", export, "--params", tmp_path / "params.yaml")
    assert result.exit_code == 0, result.output
    with open_browser() as new_page:
        page, watched = new_page(tmp_path / "render" / "explorer.html")
        page.wait_for_selector(".pt")
        page.click(".pt[data-key='mapex_td3/0/3']")
        info = page.locator("#info").inner_text()
        assert all(name in info for name in hostile), info
        assert page.locator("#info a").inner_text().endswith("member_0003.pt")
        assert page.locator("svg.plot text.axis").all_text_contents() == hostile
        assert page.evaluate("window.__pwned") is None
        assert page.evaluate("document.querySelectorAll('img, b').length") == 0
        assert not watched.dialogs and not watched.console_errors and not watched.page_errors, watched
        assert not watched.network(), watched.requests


def test_a_process_that_imported_mujoco_before_choosing_gl_still_draws(gl):
    """MuJoCo fixes its GL context class when first imported; a process that built an env (and so
    imported mujoco) before MUJOCO_GL was chosen must still draw with the chosen backend (it used
    to abort in mjr_makeContext, reaching for GLFW without a display)."""
    import subprocess
    import sys

    script = (
        "import os\n"
        "from pipeline.core.envs import make_env\n"
        f"make_env({ENV!r}, 5).close()\n"  # imports mujoco with MUJOCO_GL unset
        "from pipeline.evaluation.render import Camera, Film, choose_gl, make_render_env\n"
        "choose_gl()\n"
        f"film = Film({ENV!r}, 5, None, 1, None, 32, 24, None, None, -15.0, 90.0, 0, 0, 0)\n"
        "env = make_render_env(film); env.reset(seed=0)\n"
        "cam = Camera(env, film); image = cam.frame(env.unwrapped.data); cam.close()\n"
        "print('drew', image.shape, int(image.max()))\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).parents[1]), env.get("PYTHONPATH", "")])
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "drew (24, 32, 3)" in done.stdout and not done.stdout.strip().endswith(" 0"), done.stdout
