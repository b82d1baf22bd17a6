"""Exporting a front: each non-dominated policy as a self-contained file (docs/import_export.md).

A population's actors are state dicts of this project's `Actor`; a user wants a file they can
load in their own code. `torchscript_bytes` turns a member's actor into TorchScript (the code
and weights in one file: `torch.jit.load` needs neither this project nor its classes), and
`onnx_export` writes ONNX where the optional `onnx` package is installed. Both map a batch of
observations (B, obs_dim) float32 to actions (B, act_dim) already in the env's bounds.
`check_export` reloads what was written and compares it with the member's actor.
"""

from __future__ import annotations

import io
from pathlib import Path

import torch

from pipeline.core.artifacts import ArtifactError
from pipeline.core.nets import ScriptedActor


def torchscript_bytes(actor) -> bytes:
    """The TorchScript file of `actor` (an `Actor`, scripted; a `ScriptedActor`: its own file)."""
    if isinstance(actor, ScriptedActor):
        return actor.state_dict()[ScriptedActor.KEY].numpy().tobytes()
    buf = io.BytesIO()
    torch.jit.save(torch.jit.script(actor.cpu().eval()), buf)
    return buf.getvalue()


def probe_batch(obs_dim: int, n: int = 64, seed: int = 0) -> torch.Tensor:
    """A fixed batch of observations to compare an export with its source (N(0, 2^2) entries)."""
    return torch.randn(n, obs_dim, generator=torch.Generator().manual_seed(seed)) * 2.0


def check_export(path: Path, data: bytes, actor, obs_dim: int, atol: float = 1e-6) -> float:
    """Reload the TorchScript `data` written to `path` and compare it with `actor` on a probe
    batch; returns the largest absolute action difference, raising ArtifactError above `atol`."""
    loaded = torch.jit.load(io.BytesIO(data), map_location="cpu")
    x = probe_batch(obs_dim)
    with torch.no_grad():
        diff = float((loaded(x) - actor(x)).abs().max())
    if not diff <= atol:
        raise ArtifactError(f"{path}: the exported actor differs from the population's by {diff:.3g} (> {atol})")
    return diff


def onnx_available() -> bool:
    try:
        import onnx  # noqa: F401
    except ImportError:
        return False
    return True


def onnx_bytes(actor, obs_dim: int) -> bytes:
    """The ONNX file of `actor` (opset 17, a dynamic batch axis); needs the `onnx` package."""
    buf = io.BytesIO()
    module = actor.module if isinstance(actor, ScriptedActor) else actor  # a user's TorchScript as itself
    torch.onnx.export(
        module.cpu().eval(),
        (torch.zeros(1, obs_dim),),
        buf,
        input_names=["obs"],
        output_names=["action"],
        dynamic_axes={"obs": {0: "batch"}, "action": {0: "batch"}},
        opset_version=17,
        dynamo=False,
    )
    return buf.getvalue()
