"""The one loop of every long run: `Run`, the verbs each run has, and `drive`, which steps one.

Every long stage (extract, mopderl, morld, train_pderl, train_specialist, import_specialist)
hands its run to `drive`, which owns everything around the steps, the same way for all of them:

1. resume: the run is restored from its checkpoint when one fits (pipeline.core.resume.resume,
   the `resumed(run)` line said through the checkpoint's `say`), else made fresh and `start()`ed;
   when the env cannot be checkpointed (`problem`, e.g. a non-MuJoCo env: pipeline.core.envstate.
   env_checkpoint_problem) it is always fresh and never saved;
2. inside pipeline.core.signals.sigterm_deferred, after `start()` and after every `step()`: the
   `hooks` (`hook(run)`, e.g. a check on the run's state), then progress, then a safe point
   (`Checkpoint.safe_point`): the checkpoint is written where `run.checkpoint_due()` and on
   SIGTERM, which then stops the run with `Stopped` ("WHO: SIGTERM: checkpoint written at
   WHERE (PATH); rerun to resume", or without a checkpoint: "WHO: SIGTERM at WHERE: no
   checkpoint (PROBLEM)");
3. once `done`: `finish()`, then the caller's `save(run)` writes the outputs (still deferred: a
   SIGTERM after the last safe point lets them be written), then the checkpoint is removed
   (`Checkpoint.clear`); `close()` in any case;
4. a TrainingDiverged raised by any of it is named after `stage` and the checkpoint it keeps
   (`TrainingDiverged.within`; no path when the run never checkpoints).

Progress goes through `send(kind, value)`, the channel of stages.common.Relay (a stage's bar,
or a worker process's pipe to it): ("steps", n) adds n units (frames, steps, children, rows),
("returns", text) sets the bar's postfix. `drive` reports the units `run.progress()` counts
after the start (or the resume) and after every step; a run whose steps are long also calls
its `on_progress` (set by `drive`) whenever its units advance mid-step, e.g. after every
episode, so the bar moves during a step.

A run (`Run`) has these verbs and nothing else is asked of it:

- `start()`: the work before the first step (e.g. evaluating the starting policies); called
  on a fresh run only, never on a resumed one;
- `step()`: one unit of the loop (an iteration, a generation, an exchange, an env step);
- `done`: whether the loop has ended;
- `finish()`: the work after the last step (a final evaluation, the final finiteness check);
- `progress() -> (units, postfix)`: the units done so far (what the bar counts) and the
  postfix to show after a step ("" leaves it as it is);
- `checkpoint_due() -> bool`: whether the point just reached (after `start()` or a `step()`)
  is a periodic checkpoint (cadences differ: every iteration, every checkpoint_every
  generations, exchanges or env steps);
- `where() -> str`: that point in words, for the SIGTERM line ("generation 4", "step 2000");
- `state_dict()` / `load_state_dict(state)`: the whole state, as pipeline.core.resume saves it;
- `close()`: release what the run holds (envs);
- `on_progress`: an attribute, None or the callable `drive` sets (see above).

`run_to_end` is the same loop bare (no checkpoint, no SIGTERM, no progress), for library
callers and tests that step a run themselves.
"""

from __future__ import annotations

from typing import Any, Callable, Protocol, Sequence, TypeVar

from pipeline.core.finite import TrainingDiverged
from pipeline.core.resume import Checkpoint, resume
from pipeline.core.signals import Stopped, sigterm_deferred, stop_requested


class Run(Protocol):
    """What `drive` steps; see the module docstring."""

    on_progress: Callable[[], None] | None

    @property
    def done(self) -> bool: ...

    def start(self) -> None: ...

    def step(self) -> Any: ...

    def finish(self) -> None: ...

    def progress(self) -> tuple[int, str]: ...

    def checkpoint_due(self) -> bool: ...

    def where(self) -> str: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...

    def close(self) -> None: ...


R = TypeVar("R", bound=Run)
Send = Callable[[str, Any], None]


def fmt_vec(v) -> str:
    """A return vector as a progress line shows it: [12.3, -4.0]."""
    return "[" + ", ".join(f"{x:.1f}" for x in v) + "]"


class _Meter:
    """The units of `run` reported to `send` so far; `report` sends the rest."""

    def __init__(self, run: Run, send: Send, every: int) -> None:
        self.run, self.send, self.every, self.shown = run, send, every, 0

    def report(self, after_step: bool = True, force: bool = False) -> None:
        units, postfix = self.run.progress()
        pending = units - self.shown
        if after_step and postfix:
            force = True
        if pending and (force or pending >= self.every):
            self.send("steps", pending)
            self.shown = units
        if after_step and postfix:
            self.send("returns", postfix)


def drive(
    fresh: Callable[[], R],
    ckpt: Checkpoint,
    *,
    who: str,
    stage: str,
    resumed: Callable[[R], str],
    save: Callable[[R], None],
    send: Send,
    problem: str | None = None,
    periodic: bool = True,
    hooks: Sequence[Callable[[R], None]] = (),
    every: int = 1,
) -> R:
    """Run `fresh()` (or its checkpointed state in `ckpt`) to its end, then `save(run)` and
    clear `ckpt`; returns the finished (closed) run. See the module docstring.

    who: the run in the SIGTERM line ("extract mapex_td3 seed 0"); stage: the stage a
    TrainingDiverged is named after ("extract mapex_td3"); resumed(run): the line said on
    resuming; send: the progress channel; problem: why the run cannot be checkpointed (None:
    it can); periodic: whether the run writes periodic checkpoints at all (if not, and none
    was resumed, a divergence names no checkpoint); hooks: called with the run after every
    step, before its progress and safe point; every: units to gather between two ("steps", n)
    reports when a step has no postfix to show (a worker's pipe need not carry every env step).
    """
    if problem is None:
        run, was_resumed = resume(ckpt, fresh)
    else:
        run, was_resumed = fresh(), False
    if was_resumed:
        ckpt.say(resumed(run))
    meter = _Meter(run, send, every)
    run.on_progress = lambda: meter.report(after_step=False, force=True)

    def safe_point() -> None:
        if problem is None:
            ckpt.safe_point(run, who, run.where(), run.checkpoint_due())
        elif stop_requested():
            raise Stopped(f"{who}: SIGTERM at {run.where()}: no checkpoint ({problem})")

    try:
        with sigterm_deferred():
            meter.report(after_step=False, force=True)
            if not was_resumed:
                run.start()
                meter.report(after_step=False, force=True)
                safe_point()
            while not run.done:
                run.step()
                for hook in hooks:
                    hook(run)
                meter.report(force=run.done)
                safe_point()
            run.finish()
            meter.report(after_step=False, force=True)
            # still deferred: a SIGTERM after the last safe point lets the outputs be written
            save(run)
            ckpt.clear()
    except TrainingDiverged as exc:
        checkpoints = problem is None and (periodic or ckpt.good)
        raise exc.within(stage, ckpt.path if checkpoints else None, ckpt.good) from None
    finally:
        run.on_progress = None
        run.close()
    return run


def run_to_end(run: R, hooks: Sequence[Callable[[R], None]] = (), fresh: bool = True) -> R:
    """Step `run` to its end as `drive` does, without checkpoints, SIGTERM safe points or
    progress: `start()` if `fresh` (False: a restored run), then `step()` and the `hooks` until
    `done`, then `finish()`. Returns the run (not closed)."""
    if fresh:
        run.start()
    while not run.done:
        run.step()
        for hook in hooks:
            hook(run)
    run.finish()
    return run
