"""Section `render`: which fronts stage render films, and how (pipeline/evaluation/render.py).

Every member of a listed front plays one deterministic episode from the same reset seed, so
clips compare like with like. `methods: []` renders nothing; the stage still writes the
explorer page (every front of `methods` x `seeds`, without clips).
"""

from __future__ import annotations

from pydantic import Field, field_validator

from pipeline.params.common import Strict


class RenderParams(Strict):
    methods: list[str] = Field(
        [], description="methods whose fronts are filmed (each must be in `methods`); [] = no clips"
    )
    seeds: list[int] | None = Field(None, description="seeds whose fronts are filmed (each in `seeds`); null = all")
    frames: int | None = Field(
        200, gt=0, description="frames per clip (the first ones of the episode); null = the whole capped episode"
    )
    every: int = Field(1, ge=1, description="one frame every this many env steps (2 halves a clip's frames per step)")
    fps: int | None = Field(None, gt=0, le=120, description="clip frame rate; null = the env's real time / every")
    width: int = Field(320, ge=16, le=1920, description="frame width in pixels (even: H.264 needs it)")
    height: int = Field(240, ge=16, le=1080, description="frame height in pixels (even: H.264 needs it)")
    camera: str | int | None = Field(
        None,
        description="a camera of the env's MuJoCo model (name or id); null = one that follows the robot's root body",
    )
    distance: float | None = Field(
        None, gt=0, description="the following camera's distance in metres; null = the env's default camera's"
    )
    elevation: float = Field(
        -15.0, ge=-90, le=90, description="the following camera's elevation in degrees (<0: from above)"
    )
    azimuth: float = Field(
        90.0, ge=-360, le=360, description="the following camera's azimuth in degrees (90: from the side)"
    )
    shadow_size: int = Field(
        1024, ge=0, le=8192, description="shadow map texels per side (MuJoCo's default 4096 costs 3x); 0 = no shadows"
    )
    samples: int = Field(0, ge=0, le=16, description="anti-aliasing samples per pixel (MuJoCo's default 4 costs 2x)")
    processes: int = Field(2, ge=1, le=64, description="clips filmed side by side in this many processes")
    episode_seed: int = Field(0, ge=0, description="the env reset seed of every member's rendered episode")

    @field_validator("methods")
    @classmethod
    def _unique(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError(f"entries must be unique, got {v}")
        return v

    @field_validator("width", "height")
    @classmethod
    def _even(cls, v: int) -> int:
        if v % 2:
            raise ValueError(f"must be even (H.264 encodes 2x2 blocks of colour), got {v}")
        return v
