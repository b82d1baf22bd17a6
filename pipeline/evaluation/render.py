"""Filming a policy: one deterministic episode rendered offscreen, written as an H.264 MP4 clip
and a PNG thumbnail, with the episode's returns (stage render, docs/artifacts.md).

MuJoCo draws offscreen through the OpenGL backend named by MUJOCO_GL. `choose_gl` picks one
before anything imports mujoco's renderer: the one the user set, else EGL (Mesa's software EGL
works with no GPU), else OSMesa; each is tried in a child process, so a backend that fails
leaves this process clean for the next. Where none works, `RenderError` is one line naming
MUJOCO_GL, what was tried and what to install.

`Camera` draws the env's MuJoCo state with its own `mujoco.Renderer` and, by default, a tracking
camera on the robot's root body (the env's render camera stands still, and a runner leaves its
frame within a second). `film_clips` films a list of members with one env and camera: stage
render runs it in several processes at once (pipeline.core.workers).

The clips are encoded by imageio-ffmpeg (its wheel carries its own ffmpeg) in one thread with
the bit-exact flags, so the same frames give the same bytes.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.core.artifacts import TMP_SUFFIX, write_bytes_atomic
from pipeline.core.envs import EnvError, quiet_settotalmass, reward_dim

RENDER_VERSION = 2  # part of every clip's key: bump when the same inputs would film differently
BACKENDS = ("egl", "osmesa")
# PyOpenGL must load the same platform as MuJoCo's context (glfw needs no override).
PYOPENGL_PLATFORM = {"egl": "egl", "osmesa": "osmesa"}
_PROBE = "import mujoco; c = mujoco.GLContext(16, 16); c.make_current(); c.free(); print('ok')"


def _bind_gl_backend() -> None:
    """Make `mujoco.Renderer` create its context with the backend MUJOCO_GL names now.

    MuJoCo picks its GL context class once, when `mujoco` is first imported, from MUJOCO_GL as it
    was then. A process that imported mujoco before `choose_gl` set MUJOCO_GL (every env build
    imports it) would otherwise draw with the default (GLFW, which needs a display) and abort in
    `mjr_makeContext`. The context class `Renderer` reads is set to the one MUJOCO_GL names."""
    backend = os.environ.get("MUJOCO_GL", "").lower().strip()
    if backend == "egl":
        from mujoco.egl import GLContext
    elif backend == "osmesa":
        from mujoco.osmesa import GLContext
    else:
        return  # glfw or the platform's default: what mujoco chose at import
    try:
        from mujoco.rendering.classic import gl_context
    except ImportError:  # an older layout: mujoco.gl_context is what Renderer reads
        from mujoco import gl_context
    gl_context.GLContext = GLContext


class RenderError(EnvError):
    """No OpenGL backend can draw MuJoCo frames offscreen here (the message says what to install)."""


def _probe(backend: str) -> str | None:
    """None if a fresh process can make a MuJoCo GL context with `backend`, else why not (one line)."""
    env = dict(os.environ, MUJOCO_GL=backend)
    if backend in PYOPENGL_PLATFORM:
        env["PYOPENGL_PLATFORM"] = PYOPENGL_PLATFORM[backend]
    try:
        done = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        return "no context within 60 s"
    if done.returncode == 0 and done.stdout.strip().endswith("ok"):
        return None
    lines = [ln for ln in done.stderr.strip().splitlines() if ln.strip()]
    return lines[-1][:160] if lines else f"exit code {done.returncode}"


def gl_problem() -> str | None:
    """None when some backend renders (and MUJOCO_GL then names it), else the one-line reason."""
    given = os.environ.get("MUJOCO_GL")
    tried = [given] if given else list(BACKENDS)
    why = {}
    for backend in tried:
        why[backend] = _probe(backend)
        if why[backend] is None:
            os.environ["MUJOCO_GL"] = backend
            if backend in PYOPENGL_PLATFORM:
                os.environ.setdefault("PYOPENGL_PLATFORM", PYOPENGL_PLATFORM[backend])
            return None
    what = "; ".join(f"MUJOCO_GL={b}: {w}" for b, w in why.items())
    hint = (
        "unset MUJOCO_GL to let render try egl and osmesa, or "
        if given
        else "install Mesa's EGL (Debian/Ubuntu: apt-get install libegl1 libgl1-mesa-dri) or OSMesa (libosmesa6), or "
    )
    return f"no OpenGL backend can render MuJoCo offscreen ({what}); {hint}set render.methods: [] to skip the clips"


def choose_gl() -> str:
    """The MUJOCO_GL backend to render with (set in os.environ); RenderError where none works."""
    problem = gl_problem()
    if problem is not None:
        raise RenderError(problem)
    return os.environ["MUJOCO_GL"]


@dataclass(frozen=True)
class Film:
    """How a clip is filmed (section `render` less the choice of fronts)."""

    env_id: str
    max_episode_steps: int
    frames: int | None
    every: int
    fps: int | None
    width: int
    height: int
    camera: str | int | None  # a camera of the model (name or id); None = follow the root body
    distance: float | None  # the following camera's distance (m); None = the env's default camera's
    elevation: float  # degrees (negative: looking down)
    azimuth: float  # degrees (90: from the side, the robot running to the right)
    shadow_size: int  # shadow map texels per side; 0 = no shadows
    samples: int  # multisample anti-aliasing samples; 0 = none
    episode_seed: int
    reward_terms: tuple = ()  # env.reward_terms (dicts): a single-objective env's objectives


def is_mujoco(env) -> bool:
    """Whether `env` is a MuJoCo env (a model and data that `Camera` can draw)."""
    return hasattr(env.unwrapped, "model") and hasattr(env.unwrapped, "data")


def make_render_env(film: Film):
    """The env of `film`: a MuJoCo env as it is (its model and data are drawn by `Camera`), any
    other env built with render_mode="rgb_array" (it draws its own frames: `EnvFrames`); with
    film.reward_terms, made multi-objective as every stage makes it."""
    import gymnasium as gym
    import mo_gymnasium

    from pipeline.core.envs import RewardTermsReward, _import_env_module

    quiet_settotalmass()
    if ":" in film.env_id:
        _import_env_module(film.env_id)

    def build(**kwargs):
        try:
            return mo_gymnasium.make(film.env_id, max_episode_steps=film.max_episode_steps, **kwargs)
        except (gym.error.Error, TypeError, ValueError) as exc:
            raise EnvError(f"env.id = {film.env_id!r}: cannot build it to render ({exc})") from None

    env = build()
    if not is_mujoco(env):
        env.close()
        env = build(render_mode="rgb_array")
    return RewardTermsReward(env, film.reward_terms) if film.reward_terms else env


class EnvFrames:
    """The frames of an env that is not MuJoCo: what its own `render()` returns in
    render_mode="rgb_array" (Gymnasium's contract: an (H, W, 3) uint8 image), at its own size
    (render.width and render.height are the MuJoCo camera's)."""

    def __init__(self, env, film: Film):
        self.env = env

    def frame(self, data=None) -> np.ndarray:
        image = self.env.render()
        if image is None:
            raise RenderError("the env's render() returned nothing in render_mode='rgb_array'")
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] not in (3, 4) or image.shape[0] < 2 or image.shape[1] < 2:
            raise RenderError(f"the env's render() returned an array of shape {image.shape}, not an RGB image")
        return np.ascontiguousarray(image[:, :, :3]).astype(np.uint8)

    def close(self) -> None:
        pass


def frame_source(env, film: Film):
    """What draws `env`'s frames: a MuJoCo `Camera`, else the env itself (`EnvFrames`)."""
    return Camera(env, film) if is_mujoco(env) else EnvFrames(env, film)


def needs_gl(film: Film) -> bool:
    """Whether filming `film`'s env needs an OpenGL backend (a MuJoCo env does; others draw themselves)."""
    env = make_render_env(film)
    try:
        return is_mujoco(env)
    finally:
        env.close()


def render_problem(film: Film) -> str | None:
    """None if this machine can film `film`'s env, else why not, in one line: for a MuJoCo env no
    OpenGL backend (gl_problem), for another env a render() that gives no RGB image. The
    MuJoCo backend is chosen only for a MuJoCo env (choose_gl); another env needs none."""
    try:
        env = make_render_env(film)
    except EnvError as exc:
        return str(exc)
    try:
        if is_mujoco(env):
            return gl_problem()
        env.reset(seed=film.episode_seed)
        try:
            EnvFrames(env, film).frame()
        except RenderError as exc:
            return f"env.id = {film.env_id!r} cannot be filmed: {exc}"
        except Exception as exc:  # noqa: BLE001 - the env's own render(): one line, never a failed stage
            return f"env.id = {film.env_id!r} cannot be filmed: render() failed ({type(exc).__name__}: {exc})"
        return None
    finally:
        env.close()


def root_body(model) -> int:
    """The first body attached to the world: the robot's root (the torso of the locomotion envs)."""
    roots = [b for b in range(1, model.nbody) if model.body_parentid[b] == 0]
    if not roots:
        raise EnvError("the MuJoCo model has no body but the world: nothing to follow")
    return roots[0]


class Camera:
    """Draws `film.width` x `film.height` RGB frames of a MuJoCo env's state, offscreen.

    By default a tracking camera (mujoco.mjtCamera.mjCAMERA_TRACKING) follows the robot: it
    looks at the centre of mass of the root body's subtree from `distance`, `elevation` and
    `azimuth`, so a runner stays in the frame however far it goes (the env's own render camera
    stands still: a fast runner left its frame within a second). `film.camera` names a camera
    of the model instead. Shadows (`shadow_size`) and anti-aliasing (`samples`) are what a
    software renderer pays for most: MuJoCo's defaults (a 4096-texel shadow map, 4 samples)
    cost about 50 ms a frame here, 1024 texels and none about 17 (docs/benchmarks.md).
    """

    def __init__(self, env, film: Film):
        import mujoco

        self.model = env.unwrapped.model
        quality = self.model.vis.quality
        quality.shadowsize = max(film.shadow_size, 1)
        quality.offsamples = film.samples
        g = self.model.vis.global_
        g.offwidth, g.offheight = max(g.offwidth, film.width), max(g.offheight, film.height)
        _bind_gl_backend()
        self.renderer = mujoco.Renderer(self.model, film.height, film.width)
        self.shadows = film.shadow_size > 0
        if film.camera is None:
            cam = mujoco.MjvCamera()
            cam.type = mujoco.mjtCamera.mjCAMERA_TRACKING
            cam.trackbodyid = root_body(self.model)
            default = getattr(getattr(env.unwrapped, "mujoco_renderer", None), "default_cam_config", None) or {}
            cam.distance = (
                film.distance if film.distance is not None else default.get("distance", self.model.stat.extent)
            )
            cam.elevation, cam.azimuth = film.elevation, film.azimuth
            self.camera = cam
        else:
            kind = "name" if isinstance(film.camera, str) else "id"
            known = [self.model.camera(c).name for c in range(self.model.ncam)]
            ok = film.camera in known if kind == "name" else 0 <= film.camera < self.model.ncam
            if not ok:
                raise EnvError(f"render.camera = {film.camera!r}: {film.env_id} has no camera of that {kind} ({known})")
            self.camera = film.camera

    @property
    def scene(self):
        """The scene last drawn (its `camera` pair holds the pose and frustum the frame was drawn with)."""
        return self.renderer.scene

    def frame(self, data) -> np.ndarray:
        """The (height, width, 3) uint8 image of `data`, the env's current state."""
        import mujoco

        self.renderer.update_scene(data, camera=self.camera)
        self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = self.shadows
        return self.renderer.render()

    def close(self) -> None:
        self.renderer.close()


def clip_fps(film: Film, env) -> int:
    """Frames per second: the params' fps, else the env's real time (its render_fps / every)."""
    if film.fps is not None:
        return film.fps
    real = env.metadata.get("render_fps") or 30
    return max(1, round(real / film.every))


@dataclass(frozen=True)
class Clip:
    frames: np.ndarray  # (T, H, W, 3) uint8
    returns: np.ndarray  # (n_objectives,) undiscounted return of the whole episode
    steps: int  # env steps of the episode (the cap or termination)
    rendered_steps: int  # env steps the frames cover


@torch.no_grad()
def film_episode(actor, env, camera: Camera | EnvFrames, film: Film, on_frame=None) -> Clip:
    """One deterministic episode of `actor` from reset seed `film.episode_seed`, to its end (its
    returns), with a frame after the reset and after every `film.every`-th step until
    `film.frames` frames (all of the episode's when None). `on_frame()` is called per frame."""
    obs, _ = env.reset(seed=film.episode_seed)
    data = getattr(env.unwrapped, "data", None)  # a MuJoCo env's state (EnvFrames draws the env itself)
    frames = [camera.frame(data)]
    if on_frame:
        on_frame()
    want = film.frames
    n_obj = reward_dim(env)
    returns = np.zeros(n_obj)
    steps = rendered = 0
    done = False
    while not done:
        action = actor(torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0))[0].numpy()
        obs, r, terminated, truncated, _ = env.step(action)
        returns += r
        steps += 1
        done = terminated or truncated
        if (want is None or len(frames) < want) and steps % film.every == 0:
            frames.append(camera.frame(data))
            rendered = steps
            if on_frame:
                on_frame()
    return Clip(np.stack(frames).astype(np.uint8), returns, steps, rendered)


def mp4_bytes(frames: np.ndarray, fps: int, path_hint: Path) -> bytes:
    """`frames` (T, H, W, 3) uint8 as an H.264 MP4 (yuv420p, +faststart for browsers), bit-exact."""
    import imageio_ffmpeg

    t, h, w, _ = frames.shape
    tmp = path_hint.with_name(path_hint.name + TMP_SUFFIX + ".mp4")
    tmp.parent.mkdir(parents=True, exist_ok=True)
    try:
        writer = imageio_ffmpeg.write_frames(
            str(tmp),
            (w, h),
            fps=fps,
            codec="libx264",
            pix_fmt_out="yuv420p",
            macro_block_size=2,
            ffmpeg_log_level="error",
            output_params=[
                "-threads",
                "1",
                "-movflags",
                "+faststart",
                "-map_metadata",
                "-1",
                "-fflags",
                "+bitexact",
                "-flags:v",
                "+bitexact",
            ],  # fmt: skip
        )
        writer.send(None)
        for frame in frames:
            writer.send(np.ascontiguousarray(frame))
        writer.close()
        return tmp.read_bytes()
    finally:
        tmp.unlink(missing_ok=True)


def png_bytes(frame: np.ndarray) -> bytes:
    import imageio.v3 as iio

    return iio.imwrite("<bytes>", frame, extension=".png")


def clip_key(member_actor: dict[str, torch.Tensor], hidden_sizes: list[int], meta: dict, film: Film) -> str:
    """What a clip depends on, hashed: the actor's weights, the env and how it is filmed."""
    h = hashlib.sha256()
    spec = {k: meta.get(k) for k in ("env_id", "obs_dim", "act_dim", "action_low", "action_high")}
    filmed = {k: v for k, v in film.__dict__.items() if not (k == "reward_terms" and not v)}  # as before terms existed
    h.update(json.dumps([RENDER_VERSION, spec, list(hidden_sizes), filmed], sort_keys=True).encode())
    for name in sorted(member_actor):
        tensor = member_actor[name].detach().cpu().contiguous()
        h.update(name.encode())
        h.update(str(tensor.dtype).encode())
        h.update(tensor.view(torch.uint8).numpy().tobytes() if tensor.numel() else b"")
    return h.hexdigest()


def write_clip(clip: Clip, fps: int, mp4: Path, png: Path, record: Path, info: dict) -> dict:
    """Write the clip's MP4, its thumbnail (the middle frame) and its record (`info` plus the
    episode's returns, steps and frames), each atomically, the record last: a record stands
    for a whole clip. Returns the record."""
    write_bytes_atomic(mp4, mp4_bytes(clip.frames, fps, mp4))
    png.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(png, png_bytes(clip.frames[len(clip.frames) // 2]))
    doc = info | {
        "returns": [float(x) for x in clip.returns],
        "episode_steps": clip.steps,
        "rendered_steps": clip.rendered_steps,
        "frames": int(len(clip.frames)),
        "fps": fps,
        "width": int(clip.frames.shape[2]),
        "height": int(clip.frames.shape[1]),
    }
    write_bytes_atomic(record, (json.dumps(doc, indent=2) + "\n").encode())
    return doc


def film_clips(film: Film, jobs: list[tuple], gl_threads: int, threads: int, send=None) -> None:
    """Film and write every job, one env and camera for all: a job is (member, meta, (mp4, png,
    record) paths, info), filmed with `film_episode` and written with `write_clip`. Runs in a
    worker process of stage render (pipeline.core.workers) or in the stage itself. The software
    renderer draws with `gl_threads` threads (Mesa's LP_NUM_THREADS, unless set) and torch
    computes the actions with `threads`. `send("steps", 1)` after each clip and
    `send("returns", "<ms> ms/frame")` with the drawing cost so far."""
    from pipeline.core.population import member_actor

    os.environ.setdefault("LP_NUM_THREADS", str(gl_threads))
    torch.set_num_threads(threads)
    env = make_render_env(film)
    camera = frame_source(env, film)
    try:
        fps = clip_fps(film, env)
        spent, frames = 0.0, 0
        for member, meta, (mp4, png, record), info in jobs:
            t0 = time.perf_counter()
            clip = film_episode(member_actor(member, meta), env, camera, film)
            spent += time.perf_counter() - t0
            frames += len(clip.frames)
            write_clip(clip, fps, mp4, png, record, info)
            if send:
                send("steps", 1)
                send("returns", f"{1000 * spent / frames:.0f} ms/frame")
    finally:
        camera.close()
        env.close()
