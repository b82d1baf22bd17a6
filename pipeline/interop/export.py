"""Exporting a front: each non-dominated policy as a self-contained file (docs/import_export.md).

A population's actors are state dicts of this project's `Actor`; a user wants a file they can
load in their own code. `torchscript_bytes` turns a member's actor into TorchScript (the code
and weights in one file: `torch.jit.load` needs neither this project nor its classes),
`torch_export_bytes` into a `torch.export` program (`.pt2`: `torch.export.load(...).module()`,
PyTorch's successor to TorchScript), and `onnx_bytes` into ONNX where the optional `onnx`
package is installed. All map a batch of observations (B, obs_dim) float32, any B, to actions
(B, act_dim) already in the env's bounds. `check_export` reloads what was written and
compares it with the member's actor.

A member imported as TorchScript is written back as its own file and has no `.pt2` (torch.export
does not take a TorchScript module); one imported as a `.pt2` program is written back as its own
file, and its TorchScript and ONNX files are traced from it.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import torch

from pipeline.core.artifacts import ArtifactError
from pipeline.core.nets import ExportedActor, ScriptedActor

LOADERS = {
    "torchscript": lambda data: ScriptedActor._load(io.BytesIO(data)),  # records checked before it loads
    "torch_export": lambda data: ExportedActor._load(io.BytesIO(data)),  # inspected before it loads
}


def _traced(actor: ExportedActor, obs_dim: int) -> torch.jit.ScriptModule:
    """A program's module as TorchScript, traced on a batch of 3 (a batch of 1 or 2 could be
    taken for a constant); `check_export` then compares it on a batch of 64."""
    with torch.no_grad(), warnings.catch_warnings():
        # the program's input guards read shapes as Python values: the tracer warns of each
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        return torch.jit.trace(actor.module, (torch.zeros(3, obs_dim),), check_trace=False)


def torchscript_bytes(actor, obs_dim: int) -> bytes:
    """The TorchScript file of `actor` (an `Actor`, scripted; a `ScriptedActor`: its own file;
    an `ExportedActor`: its program traced)."""
    if isinstance(actor, ExportedActor):
        module = _traced(actor, obs_dim)
    elif isinstance(actor, ScriptedActor):
        return actor.state_dict()[ScriptedActor.KEY].numpy().tobytes()
    else:
        module = torch.jit.script(actor.cpu().eval())
    buf = io.BytesIO()
    torch.jit.save(module, buf)
    return buf.getvalue()


def torch_export_bytes(actor, obs_dim: int) -> bytes | None:
    """The `.pt2` file (torch.export.save) of `actor`, its batch axis dynamic: an `Actor`
    exported; an `ExportedActor`: its own file; None for a `ScriptedActor` (a user's
    TorchScript, which torch.export cannot take)."""
    if isinstance(actor, ExportedActor):
        return actor.state_dict()[ExportedActor.KEY].numpy().tobytes()
    if isinstance(actor, ScriptedActor):
        return None
    batch = torch.export.Dim("batch")
    program = torch.export.export(actor.cpu().eval(), (torch.zeros(2, obs_dim),), dynamic_shapes=({0: batch},))
    buf = io.BytesIO()
    torch.export.save(program, buf)
    return buf.getvalue()


def probe_batch(obs_dim: int, n: int = 64, seed: int = 0) -> torch.Tensor:
    """A fixed batch of observations to compare an export with its source (N(0, 2^2) entries)."""
    return torch.randn(n, obs_dim, generator=torch.Generator().manual_seed(seed)) * 2.0


def check_export(path: Path, data: bytes, actor, obs_dim: int, atol: float = 1e-6, kind: str = "torchscript") -> float:
    """Reload the `kind` file (a key of LOADERS) `data` written to `path` and compare it with
    `actor` on a probe batch; returns the largest absolute action difference, raising
    ArtifactError above `atol`."""
    loaded = LOADERS[kind](data)
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
    if isinstance(actor, ExportedActor):
        module = _traced(actor, obs_dim)  # a program's module refuses eval(), which the exporter calls
    else:
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
