"""The preamble and the closing record that the stages training specialists share
(train_specialist, train_pderl): what they read and check before training, and the provenance
record they write after. A module of its own, imported by those two stages only, so that no
other stage's code deps grow by it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import torch

from pipeline.core.envs import EnvSpec
from pipeline.core.precision import resolve
from pipeline.core.provenance import write_provenance
from pipeline.core.seeding import select_device
from pipeline.evaluation.preflight import specialists_to_train
from pipeline.params import ParamsError, section
from pipeline.params.td3 import TD3Params


@dataclass(frozen=True)
class Training:
    """What a stage that trains specialists (train_specialist, train_pderl) reads before it
    trains: its params (StageParams), the `td3` section (the RL agent both train), the env spec,
    the objectives to train with their names (pipeline.evaluation.preflight.specialists_to_train)
    and the device; `precision()` and `record()` are what both state about the run at the end."""

    params: Any  # stages.common.StageParams: raw, env, cfg, run
    td3: TD3Params
    spec: EnvSpec
    objectives: list[int]
    names: list[str]
    device: torch.device

    def precision(self) -> str:
        return resolve(self.params.cfg.precision, self.device, max(self.td3.hidden_sizes))

    def record(self, provenance: Path | None, stage: str) -> None:
        """The run's provenance record (pipeline.core.provenance), when --provenance names a file."""
        write_provenance(provenance, stage, self.device, self.precision())


def training_inputs(
    stage: Any, path: Path, objective: list[int] | None, check: Callable[[Any, TD3Params], None]
) -> Training:
    """The preamble of a training stage, after stages.common.read_params gave `stage` (raw, env,
    cfg, run): the `td3` section, `check(cfg, td3)` (its ValueError becomes one ParamsError line
    naming the file), the env and the objectives to train (--objective, else params'
    objectives), and the device (cfg.device)."""
    td3 = section(stage.raw, "td3", TD3Params, path)
    try:
        check(stage.cfg, td3)
    except ValueError as exc:
        raise ParamsError(f"{path}: {exc}") from None
    spec, objectives, names = specialists_to_train(stage.env, path, objective, stage.run.objectives)
    return Training(stage, td3, spec, objectives, names, select_device(stage.cfg.device))
