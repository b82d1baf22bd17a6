"""Networks: the deterministic actor and the batched critic ensemble.

The critic ensemble holds every critic of a specialist (twin heads for each objective it
covers) as stacked weight tensors, so all of them are evaluated by a few batched matmuls
and trained by one optimizer rather than by N modules in a Python loop.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import nn

from pipeline.core.pt2check import check_pt2
from pipeline.core.tscheck import check_torchscript


def mlp(in_dim: int, hidden_sizes: Sequence[int], out_dim: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    d = in_dim
    for h in hidden_sizes:
        layers += [nn.Linear(d, h), nn.ReLU()]
        d = h
    layers.append(nn.Linear(d, out_dim))
    return nn.Sequential(*layers)


class Actor(nn.Module):
    """Deterministic policy: obs (B, obs_dim) -> action (B, act_dim) inside [low, high]."""

    # runs with bfloat16 weights too (pipeline.core.precision.frozen): fp32 obs in, fp32 actions out
    TAKES_BF16 = True

    def __init__(self, obs_dim: int, act_dim: int, hidden_sizes: Sequence[int], low, high):
        super().__init__()
        self.net = mlp(obs_dim, hidden_sizes, act_dim)
        low_t = torch.as_tensor(low, dtype=torch.float32)
        high_t = torch.as_tensor(high, dtype=torch.float32)
        # Saved in the state dict so a checkpoint carries its own bounds.
        self.register_buffer("scale", (high_t - low_t) / 2)
        self.register_buffer("centre", (high_t + low_t) / 2)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        # obs in the weights' dtype (a no-op in fp32; bfloat16 for a copy made by
        # pipeline.core.precision.frozen); the action bounds are fp32, so the action is fp32.
        return self.centre + self.scale * torch.tanh(self.net(obs.to(self.net[0].weight.dtype)))


class NormalizedActor(Actor):
    """An `Actor` that normalises its raw observations first, with frozen statistics, as SB3's
    `VecNormalize` did for the policy it trained: z = clip((obs - mean) / std, -clip, clip),
    std = sqrt(var + epsilon), then the MLP, tanh, centre + scale (docs/import_export.md).

    The statistics are buffers in its state dict (`obs_mean`, `obs_std`, `obs_clip`), so every
    artifact and export of it (TorchScript, .pt2, ONNX) takes raw observations. They are kept
    and applied in float64, SB3's arithmetic, and z is cast back to the observations' dtype
    before the first layer: on the same raw observations the MLP sees exactly what SB3's
    policy saw. Built empty (statistics 0, 1, inf) to load a state dict into.
    """

    def __init__(
        self, obs_dim: int, act_dim: int, hidden_sizes: Sequence[int], low, high, mean=None, std=None, clip=None
    ):
        super().__init__(obs_dim, act_dim, hidden_sizes, low, high)
        f64 = torch.float64
        self.register_buffer(
            "obs_mean", torch.zeros(obs_dim, dtype=f64) if mean is None else torch.as_tensor(mean, dtype=f64)
        )
        self.register_buffer(
            "obs_std", torch.ones(obs_dim, dtype=f64) if std is None else torch.as_tensor(std, dtype=f64)
        )
        self.register_buffer("obs_clip", torch.tensor(math.inf if clip is None else float(clip), dtype=f64))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        z = (obs.to(torch.float64) - self.obs_mean) / self.obs_std
        z = torch.minimum(torch.maximum(z, -self.obs_clip), self.obs_clip)
        # z in the weights' dtype, as Actor does (obs is fp32 everywhere, so fp32 keeps its bits;
        # bfloat16 for a copy made by pipeline.core.precision.frozen, whose buffers stay as they are)
        return self.centre + self.scale * torch.tanh(self.net(z.to(self.net[0].weight.dtype)))


NORMALIZED_KEYS = ("obs_mean", "obs_std", "obs_clip")  # what a NormalizedActor's state dict adds to an Actor's


def hidden_sizes_of(actor: Actor) -> list[int]:
    """The hidden layer widths an `Actor` was built with (its `hidden_sizes`)."""
    return [m.out_features for m in actor.net if isinstance(m, nn.Linear)][:-1]


class ScriptedActor(nn.Module):
    """A deterministic policy brought in as TorchScript (`torch.jit.save` of a module mapping a
    batch of observations (B, obs_dim) to actions (B, act_dim) inside the env's bounds).

    Its state dict is the TorchScript file itself, as one uint8 tensor under "torchscript", so
    the artifacts that hold `Actor` state dicts (policy.pt, policies.pt, population.pt) hold it
    too and still load with weights_only=True. The bytes are kept exactly as given: saving
    twice writes the same artifact. Build one from bytes with `ScriptedActor.from_bytes`, or
    empty (`ScriptedActor()`) and fill it with `load_state_dict`.
    """

    KEY = "torchscript"

    def __init__(self, low=None, high=None) -> None:
        super().__init__()
        self.module: torch.jit.ScriptModule | None = None
        self._bytes = b""
        if low is not None and high is not None:
            # the env's bounds, as `Actor` holds them (children and TD3 target smoothing read them);
            # not in the state dict: they come from the artifact's metadata
            low_t, high_t = torch.as_tensor(low, dtype=torch.float32), torch.as_tensor(high, dtype=torch.float32)
            self.register_buffer("scale", (high_t - low_t) / 2, persistent=False)
            self.register_buffer("centre", (high_t + low_t) / 2, persistent=False)

    @classmethod
    def from_bytes(cls, data: bytes, low=None, high=None) -> "ScriptedActor":
        out = cls(low, high)
        out.load_state_dict({cls.KEY: torch.frombuffer(bytearray(data), dtype=torch.uint8)})
        return out

    def __deepcopy__(self, memo) -> "ScriptedActor":
        # a copy loaded afresh from the same bytes (copying a loaded ScriptModule leaves its
        # parameters non-leaf), on the device the original is on
        bounds = (self.centre - self.scale, self.centre + self.scale) if hasattr(self, "scale") else (None, None)
        bounds = tuple(None if b is None else b.cpu() for b in bounds)
        cls = type(self)
        out = cls.from_bytes(self._bytes, *bounds) if self.module is not None else cls(*bounds)
        device = self.scale.device if hasattr(self, "scale") else None
        out.train(self.training)
        return out.to(device) if device is not None else out

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        if self.module is None:
            raise RuntimeError(f"{type(self).__name__} holds no module yet (load_state_dict first)")
        return self.module(obs)

    def state_dict(self, *args, **kwargs) -> dict[str, torch.Tensor]:  # noqa: D102 (see the class)
        return {self.KEY: torch.frombuffer(bytearray(self._bytes), dtype=torch.uint8)}

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):  # noqa: D102
        import io

        if set(state_dict) != {self.KEY}:
            raise RuntimeError(
                f"a {type(self).__name__} state dict holds exactly {self.KEY!r}, got {sorted(state_dict)}"
            )
        data = state_dict[self.KEY].cpu().numpy().tobytes()
        self.module, self._bytes = self._load(io.BytesIO(data)), data  # on the CPU, like every artifact
        return torch.nn.modules.module._IncompatibleKeys([], [])

    @staticmethod
    def _load(f) -> nn.Module:
        """The module of a file's bytes (`f` a BytesIO). The archive's tensor records are checked
        first, every time (pipeline/core/tscheck.py: torch.jit.load trusts their sizes and can
        crash on a crafted one), whatever file or remote the bytes came from."""
        check_torchscript(f.getvalue(), "the TorchScript program")
        return torch.jit.load(f, map_location="cpu")


class ExportedActor(ScriptedActor):
    """A deterministic policy brought in as a `torch.export` program (`torch.export.save` of an
    ExportedProgram, a `.pt2` file, mapping (B, obs_dim) observations to actions (B, act_dim)
    inside the env's bounds; its batch axis exported as dynamic).

    Like `ScriptedActor`, its state dict is the file itself, as one uint8 tensor under
    "torch_export", kept byte for byte; the module it runs is the program's
    `torch.export.load(...).module()`. Such a module refuses `train()`/`eval()`; this one
    records the mode without passing it on (a program's graph has no training mode).
    """

    KEY = "torch_export"

    @staticmethod
    def _load(f) -> nn.Module:
        # a program from elsewhere can run Python while torch.export.load reads it: the archive is
        # inspected first, every time (pipeline/core/pt2check.py; docs/trust.md)
        check_pt2(f.getvalue())
        return torch.export.load(f).module()

    def train(self, mode: bool = True) -> "ExportedActor":
        self.training = bool(mode)
        return self


class CriticEnsemble(nn.Module):
    """`n_members` independent Q-networks Q_e(s, a), e = 0..n_members-1, as stacked weights.

    Member layout used throughout MAPEX: member 2*j + h is head h (0 or 1) of the j-th
    objective the ensemble covers. Layer l has weight (E, d_in, d_out) and bias (E, 1, d_out),
    initialised like `nn.Linear` (uniform in +-1/sqrt(d_in)).

    Q-values come out in fp32 whatever the weights' dtype (bfloat16 in a frozen copy) or an
    enclosing autocast (pipeline.core.precision).
    """

    TAKES_BF16 = True

    def __init__(self, obs_dim: int, act_dim: int, hidden_sizes: Sequence[int], n_members: int):
        super().__init__()
        self.n_members = n_members
        dims = [obs_dim + act_dim, *hidden_sizes, 1]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for d_in, d_out in zip(dims[:-1], dims[1:]):
            bound = 1.0 / math.sqrt(d_in)
            self.weights.append(nn.Parameter(torch.empty(n_members, d_in, d_out).uniform_(-bound, bound)))
            self.biases.append(nn.Parameter(torch.empty(n_members, 1, d_out).uniform_(-bound, bound)))

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Q of every member at the same (obs (B, o), action (B, a)) -> (E, B)."""
        x = torch.cat([obs, action], dim=-1).to(self.weights[0].dtype)
        # (B, d) @ (E, d, h) broadcasts to (E, B, h): one batched matmul for every member.
        # ReLU in place saves an allocation per layer; the matmuls that produce h do not keep
        # it for their backward, so autograd allows it.
        if x.dtype == torch.float32 and not torch.is_autocast_enabled(x.device.type):
            h = torch.relu_(torch.matmul(x, self.weights[0]) + self.biases[0])
        else:  # bf16: the bias added inside the matmul, one slow bf16 elementwise pass less on a CPU
            h = torch.relu_(torch.baddbmm(self.biases[0], x.expand(self.n_members, *x.shape), self.weights[0]))
        n = len(self.weights)
        for i in range(1, n):
            h = torch.baddbmm(self.biases[i], h, self.weights[i])
            if i < n - 1:
                h = torch.relu_(h)
        return h.squeeze(-1).float()  # Q in fp32 also from bf16 weights or autocast (no-op in fp32)

    def member(self, obs: torch.Tensor, action: torch.Tensor, e: int) -> torch.Tensor:
        """Q of member `e` alone at (obs (B, o), action (B, a)) -> (B,)."""
        h = torch.cat([obs, action], dim=-1).to(self.weights[0].dtype)
        n = len(self.weights)
        for i in range(n):
            h = torch.addmm(self.biases[i][e], h, self.weights[i][e])
            if i < n - 1:
                h = torch.relu_(h)
        return h.squeeze(-1).float()

    def twin_min(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Clipped double-Q estimate per covered objective: min over the two heads -> (n_obj, B)."""
        q = self.forward(obs, action)
        return q.view(self.n_members // 2, 2, -1).min(dim=1).values

    # -- several specialists' ensembles as one -------------------------------------------------

    @classmethod
    def stack(cls, ensembles: Sequence["CriticEnsemble"]) -> "CriticEnsemble":
        """One ensemble holding every member of `ensembles`, in order (group g = ensemble g)."""
        first = ensembles[0]
        out = cls.__new__(cls)
        nn.Module.__init__(out)
        out.n_members = sum(e.n_members for e in ensembles)
        out.weights = nn.ParameterList(
            [
                nn.Parameter(torch.cat([e.weights[i].detach() for e in ensembles]).clone())
                for i in range(len(first.weights))
            ]
        )
        out.biases = nn.ParameterList(
            [
                nn.Parameter(torch.cat([e.biases[i].detach() for e in ensembles]).clone())
                for i in range(len(first.biases))
            ]
        )
        return out

    def subset(self, start: int, stop: int) -> "CriticEnsemble":
        """A new ensemble with copies of members start..stop-1 (e.g. one specialist's group)."""
        out = CriticEnsemble.__new__(CriticEnsemble)
        nn.Module.__init__(out)
        out.n_members = stop - start
        out.weights = nn.ParameterList([nn.Parameter(w.detach()[start:stop].clone()) for w in self.weights])
        out.biases = nn.ParameterList([nn.Parameter(b.detach()[start:stop].clone()) for b in self.biases])
        return out

    def grouped(self, obs: torch.Tensor, action: torch.Tensor, members: torch.Tensor | None = None) -> torch.Tensor:
        """Q where group g of members sees its own batch: obs (G, B, o), action (G, B, a) -> (E', B).

        Without `members`, the E members split into G equal groups in order (group g = members
        g*E/G .. (g+1)*E/G - 1, one specialist's critics each). With `members` (G,) long, member
        members[g] alone sees batch g (e.g. each specialist's primary critic): -> (G, B).
        """
        x = torch.cat([obs, action], dim=-1).to(self.weights[0].dtype)  # (G, B, d)
        if members is None:
            ws, bs = list(self.weights), list(self.biases)
            per = self.n_members // x.shape[0]
            if per > 1:
                x = x.unsqueeze(1).expand(-1, per, -1, -1).reshape(self.n_members, *x.shape[1:])
        else:
            ws = [w.index_select(0, members) for w in self.weights]
            bs = [b.index_select(0, members) for b in self.biases]
        h = x
        n = len(ws)
        for i in range(n):
            h = torch.baddbmm(bs[i], h, ws[i])
            if i < n - 1:
                h = torch.relu_(h)
        return h.squeeze(-1).float()


class StackedActor(nn.Module):
    """S deterministic actors of one architecture as stacked weights: obs (S, B, o) -> (S, B, a).

    Built from S `Actor`s (so each keeps the initialisation it would have alone) and turned
    back into one with `unstack`, which is what the artifacts store. Layer l holds weight
    (S, d_in, d_out) and bias (S, 1, d_out); one batched matmul per layer serves every actor.
    """

    TAKES_BF16 = True

    def __init__(self, actors: Sequence[Actor]):
        super().__init__()
        if any(isinstance(a, NormalizedActor) for a in actors):
            # stacked weights hold no input statistics: a normalised actor would run without them
            raise ValueError("a NormalizedActor cannot be stacked (its observation statistics would be dropped)")
        linears = [[m for m in a.net if isinstance(m, nn.Linear)] for a in actors]
        self.hidden_sizes = [lin.out_features for lin in linears[0][:-1]]
        self.weights = nn.ParameterList(
            [
                nn.Parameter(torch.stack([ls[i].weight.detach().T for ls in linears]).contiguous())
                for i in range(len(linears[0]))
            ]
        )
        self.biases = nn.ParameterList(
            [
                nn.Parameter(torch.stack([ls[i].bias.detach()[None] for ls in linears]).clone())
                for i in range(len(linears[0]))
            ]
        )
        self.register_buffer("scale", torch.stack([a.scale[None] for a in actors]).clone())  # (S, 1, a)
        self.register_buffer("centre", torch.stack([a.centre[None] for a in actors]).clone())

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        h = obs.to(self.weights[0].dtype)  # see Actor.forward
        n = len(self.weights)
        for i in range(n):
            h = torch.baddbmm(self.biases[i], h, self.weights[i])
            if i < n - 1:
                h = torch.relu_(h)
        return self.centre + self.scale * torch.tanh(h)

    def unstack(self, s: int) -> Actor:
        """Actor s as a plain `Actor` on the CPU (the artifact format)."""
        obs_dim, act_dim = self.weights[0].shape[1], self.weights[-1].shape[2]
        centre, scale = self.centre[s, 0].cpu(), self.scale[s, 0].cpu()
        actor = Actor(obs_dim, act_dim, self.hidden_sizes, centre - scale, centre + scale)
        linears = [m for m in actor.net if isinstance(m, nn.Linear)]
        with torch.no_grad():
            for lin, w, b in zip(linears, self.weights, self.biases):
                lin.weight.copy_(w[s].T)
                lin.bias.copy_(b[s, 0])
            actor.scale.copy_(scale)
            actor.centre.copy_(centre)
        return actor
