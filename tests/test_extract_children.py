"""Children of one iteration: the K = 1 pin against the pre-batching code, and the stacked path."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import torch

from pipeline import extraction as ex
from pipeline.envs import make_env
from pipeline.evaluation import eval_seeds, evaluate_policy
from pipeline.nets import Actor, CriticEnsemble

OBS, ACT = 17, 6  # mo-halfcheetah-v5's dims, so children can be evaluated in the real env
RETURNS = np.array([[100.0, -300.0], [-5.0, -10.0], [60.0, -100.0]])  # 3 policies, all on the front

# Three settings that together reach every branch of the child's training.
CONFIGS = {
    "paper": dict(weight_norm="l2", max_grad_norm=None, recompute="every_step", norm="none"),
    "precursor": dict(weight_norm="l1", max_grad_norm=0.5, recompute="once", norm="zscore"),
    "range": dict(weight_norm="l2", max_grad_norm=0.5, recompute="every_step", norm="objective_range"),
}


def fixture_inputs():
    """Seeded toy inputs: buffers of 700 and 450 rows (so hybrid sizes differ with the weight),
    two critic ensembles (4 members: twin heads x 2 objectives) and three population actors."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(1234)
        critics = [CriticEnsemble(OBS, ACT, [32, 32], 4).eval() for _ in range(2)]
        actors = [Actor(OBS, ACT, [32, 32], [-1.0] * ACT, [1.0] * ACT).eval() for _ in range(3)]
    rng = np.random.default_rng(99)
    buffers = [
        {"obs": rng.normal(size=(n, OBS)).astype(np.float32), "action": rng.uniform(-1, 1, (n, ACT)).astype(np.float32)}
        for n in (700, 450)
    ]
    return buffers, critics, actors


def child_config(config: str, epochs: int = 2) -> ex.ChildConfig:
    c = CONFIGS[config]
    adv = ex.AdvantageConfig(epochs=epochs, beta=1.0, omega_max=20.0, lr=1e-3, batch_size=64,
                             max_grad_norm=c["max_grad_norm"], recompute=c["recompute"], norm=c["norm"])
    return ex.ChildConfig(hidden_sizes=(32, 32), child_buffer_size=600, weight_norm=c["weight_norm"], warmup_steps=25,
                          warmup_lr=1e-3, warmup_batch_size=64, adv=adv)


def digest(actor: Actor, rec: ex.ChildRecord, returns: np.ndarray) -> str:
    """sha256 over a child's weights, its record and its evaluation returns (every bit)."""
    h = hashlib.sha256()
    for k, v in sorted(actor.state_dict().items()):
        h.update(k.encode())
        h.update(v.detach().cpu().numpy().tobytes())
    h.update(repr((rec.parents, rec.counts.tolist(), sorted(rec.stats.items()))).encode())
    h.update(np.asarray(rec.weight, np.float64).tobytes())
    h.update(np.asarray(returns, np.float64).tobytes())
    return h.hexdigest()


def evaluate_short(actor: Actor) -> np.ndarray:
    envs = [make_env("mo-halfcheetah-v5", 30) for _ in range(2)]
    return evaluate_policy(actor, envs, eval_seeds(0, 0, 3, 2)).returns


# ---------------------------------------------------------------- K = 1: bitwise as before batching

# Digests of the child trained by `make_child` before children could be trained together
# (commit 635444e), recorded on this project's CPU machine with 1 torch thread, torch 2.13.0+cpu
# and numpy 2.4.6. They depend on: the CPU's floating-point kernels (MKL/oneDNN path), the
# thread count (set to 1 below), the torch and numpy versions (RNG streams, kernels), MuJoCo's
# version (the evaluation returns) and this fixture. The pin is skipped under other versions.
PIN_VERSIONS = ("2.13.0+cpu", "2.4.6")
PINNED = {
    "paper": "805fbe573cd8aa56b6384058cbae000b99bb0a2d7bfd857e4ef520e9c2a72394",
    "precursor": "f1aeea3f776a70ea65fd589dd625681dc8393616a66e89dbc1a6b25cb43c1e9a",
    "range": "24be279e4f42a1986c8de557e0d2eb41383b101579eee5d0ba5c74310f46078b",
}


@pytest.fixture
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.mark.skipif((torch.__version__, np.__version__) != PIN_VERSIONS, reason=f"pin recorded with torch/numpy {PIN_VERSIONS}")
@pytest.mark.parametrize("config", sorted(PINNED))
def test_one_child_is_bitwise_what_it_was_before_batching(config, one_thread):
    buffers, critics, actors = fixture_inputs()
    # what the stage runs for K = 1 on a CPU
    [(child, rec)] = ex.make_children(RETURNS, actors, buffers, critics, child_config(config), [ex.ChildSeeds(111, 222, 333)], "cpu")
    assert digest(child, rec, evaluate_short(child)) == PINNED[config]
