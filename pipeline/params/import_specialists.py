"""Section `import_specialists`: specialists trained elsewhere, one per objective at most (docs/import_export.md).

Each entry of `policies` names the policy file of one objective, its format (an SB3 model.zip
of TD3, DDPG or SAC; a CleanRL TD3, DDPG or SAC checkpoint; a TorchScript actor) and
optionally a buffer of its own in the project's Zarr format, with every objective's reward,
and the observation statistics of a model trained under SB3's VecNormalize (`normalize`; found
beside an SB3 model in rl-zoo3's layout when not given, pipeline.params.methods.normalize_file).
Without one, stage import_specialist collects `collect_rows` transitions of the policy in the
MO env with TD3's Gaussian exploration noise. Post-hoc critics for every objective are then
fitted on that buffer (stage fit_critics) and MAPEX-PostHoc extracts from them (method
mapex_posthoc_imported). `policies` may leave objectives out: their slots of the imported kind
are trained here by TD3 with sections `td3` and `train_specialist` (stage
train_specialist_imported), and their critics are fitted post hoc like the imported ones'.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal, get_args

from pydantic import Field, field_validator, model_validator

from pipeline.params.common import Strict

# The policy formats an import reads (pipeline/interop/readers.py reads these lists; the one place
# they are written), and those read into an `Actor` that observation statistics can precede.
ImportFormat = Literal["sb3", "cleanrl", "torchscript", "torch_export"]
IMPORT_FORMATS: tuple[str, ...] = get_args(ImportFormat)
NORMALIZABLE_FORMATS = ("sb3", "cleanrl")
# A grid cell's params arrive through git, so a file they name outside the repository (an absolute
# path, a `..` that climbs out, a link that leads out) is read only when the user running the
# stage says so in this environment variable (issue 57, item 4; docs/trust.md).
ALLOW_OUTSIDE = "MAPEX_ALLOW_OUTSIDE_PATHS"


def outside_problem(key: str, value: str, root: Path | None = None) -> str | None:
    """Why the path `value` of params key `key` is refused (None if it is inside the repository,
    the working directory `root`, or MAPEX_ALLOW_OUTSIDE_PATHS=1 allows it)."""
    if os.environ.get(ALLOW_OUTSIDE) == "1":
        return None
    root = (root or Path.cwd()).resolve()
    path = Path(os.path.expanduser(value))
    target = (path if path.is_absolute() else root / path).resolve()
    if target == root or root in target.parents:
        return None
    return (
        f"{key} = {value!r} is outside the repository ({root}): params can arrive through git (a grid cell's do), "
        f"so mapex reads a file outside only when you say so: set {ALLOW_OUTSIDE}=1 where you run it, or copy the "
        "file into the repository"
    )


class ImportedPolicyEntry(Strict):
    objective: int = Field(..., ge=0, description="the objective this specialist was trained for (its slot obj{k})")
    file: str = Field(..., min_length=1, description="the policy file, relative to the repository root (a DVC dep)")
    format: ImportFormat = Field(
        ...,
        description="sb3: model.zip of TD3/DDPG/SAC; cleanrl: .cleanrl_model of TD3/DDPG/SAC; torchscript: "
        "torch.jit.save; torch_export: a .pt2 file of torch.export.save (batch axis dynamic)",
    )
    buffer: str | None = Field(
        None,
        description="optional: a buffer.zarr of this policy's transitions in the project's format (full reward "
        "vectors); null: collect one",
    )
    normalize: str | Literal[False] | None = Field(
        None,
        description="optional: the observation statistics of a model trained under SB3's VecNormalize "
        "(vecnormalize.pkl, a DVC dep); null: the one rl-zoo3 saves beside an sb3 model, if any; false: none",
    )

    @model_validator(mode="after")
    def _normalizable(self) -> "ImportedPolicyEntry":
        if isinstance(self.normalize, str) and self.normalize.strip().lower() in ("none", "auto"):
            # YAML reads `none` as a string, which would become a DVC dep on a file of that name
            raise ValueError(
                f"normalize = {self.normalize!r} is a word of the command line (--normalize), not a file: write "
                "false for no statistics, or leave the key out to use the file rl-zoo3 saves beside an sb3 model"
            )
        if isinstance(self.normalize, str) and self.format not in NORMALIZABLE_FORMATS:
            raise ValueError(
                f"normalize = {self.normalize!r} for a {self.format} policy: statistics are read for sb3 and cleanrl "
                "models; a TorchScript or torch.export policy normalises inside its own module"
            )
        if isinstance(self.normalize, str) and not self.normalize.strip():
            raise ValueError("normalize is an empty path; give the statistics file, or false for none")
        for key in ("file", "buffer", "normalize"):
            value = getattr(self, key)
            if isinstance(value, str) and (problem := outside_problem(key, value)) is not None:
                raise ValueError(problem)
        return self


class ImportSpecialistsParams(Strict):
    policies: list[ImportedPolicyEntry] = Field(
        [], description="one entry per imported objective; objectives without one are trained here by TD3"
    )
    collect_rows: int = Field(
        25_000, gt=0, description="transitions collected per specialist without a buffer of its own"
    )
    exploration_noise: float = Field(
        0.1, ge=0, description="std of the Gaussian collection noise, times the action half-range (TD3's 0.1)"
    )
    checkpoint_every: int = Field(
        10_000, ge=0, description="collected rows between checkpoints (0: none); changes no artifact"
    )

    @model_validator(mode="after")
    def _written_out(self) -> "ImportSpecialistsParams":
        # stage import_specialist lists these two keys as DVC params, and DVC reads them from
        # params.yaml itself (no defaults there): with policies to import, they must be written
        missing = [k for k in ("collect_rows", "exploration_noise") if self.policies and k not in self.model_fields_set]
        if missing:
            raise ValueError(f"{missing} must be written out when policies are listed (dvc.yaml tracks them)")
        return self

    @field_validator("policies")
    @classmethod
    def _one_per_objective(cls, v: list[ImportedPolicyEntry]) -> list[ImportedPolicyEntry]:
        objectives = [p.objective for p in v]
        if len(set(objectives)) != len(objectives):
            raise ValueError(f"one policy per objective, got objectives {objectives}")
        return v
