"""A `.pt2` file from elsewhere cannot run code through `torch.export.load`: the archive is
inspected first (pipeline/core/pt2check.py), wherever its bytes come from (an import, a
policy.pt or a population member pulled from a DVC remote).

Each attack is rebuilt here from a genuine `torch.export.save` archive, and one test shows
that torch itself runs the planted code when handed the file unchecked, so the refusals below
are refusals of live attacks."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from pipeline.core.artifacts import ArtifactError
from pipeline.core.checkpoint import FORMAT_VERSION, POLICY_FORMAT, load_policy
from pipeline.core.nets import ExportedActor
from pipeline.core.population import Member, member_actor
from pipeline.core.pt2check import check_pt2

OBS, ACT = 5, 2


class _Planted:
    """Pickles to a call of `exec` that writes the file named by `marker`."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (exec, (f"open({self.marker!r}, 'w').write('ran')",))


def genuine() -> bytes:
    torch.manual_seed(0)
    module = nn.Sequential(nn.Linear(OBS, 8), nn.ReLU(), nn.Linear(8, ACT), nn.Tanh()).eval()
    program = torch.export.export(module, (torch.zeros(3, OBS),), dynamic_shapes=({0: torch.export.Dim("batch")},))
    buf = io.BytesIO()
    torch.export.save(program, buf)
    return buf.getvalue()


def rewrite(data: bytes, change) -> bytes:
    """The archive with `change(members: dict[relative name, bytes], root)` applied."""
    src = zipfile.ZipFile(io.BytesIO(data))
    root = src.namelist()[0].split("/", 1)[0]
    members = {n[len(root) + 1 :]: src.read(n) for n in src.namelist()}
    change(members, root)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as dst:
        for name, content in members.items():
            dst.writestr(f"{root}/{name}", content)
    return out.getvalue()


def planted_pickle(marker: Path) -> bytes:
    buf = io.BytesIO()
    torch.save(_Planted(marker), buf)
    return buf.getvalue()


def pickled_weight(marker: Path):
    def change(m, root):
        config = json.loads(m["data/weights/model_weights_config.json"])
        config["config"]["0.weight"]["use_pickle"] = True
        m["data/weights/model_weights_config.json"] = json.dumps(config).encode()
        m["data/weights/" + config["config"]["0.weight"]["path_name"]] = planted_pickle(marker)

    return change


def opaque_constant(marker: Path):
    def change(m, root):
        import pickle

        m["data/constants/opaque_obj_0"] = pickle.dumps(_Planted(marker))
        m["data/constants/model_constants_config.json"] = json.dumps(
            {"config": {"planted": {"path_name": "opaque_obj_0", "is_param": False, "use_pickle": True}}}
        ).encode()

    return change


def pickled_sample_inputs(marker: Path):
    def change(m, root):
        m["data/sample_inputs/model.pt"] = planted_pickle(marker)

    return change


def evaluated_expression(marker: Path):
    def change(m, root):
        text = m["models/model.json"].decode()
        planted = f"__import__('builtins').exec(\\\"open({str(marker)!r}, 'w').write('ran')\\\") or Symbol('s31')"
        assert "Symbol('s31', positive=True, integer=True)" in text
        m["models/model.json"] = text.replace("Symbol('s31', positive=True, integer=True)", planted, 1).encode()

    return change


def foreign_target(marker: Path):
    def change(m, root):
        text = m["models/model.json"].decode()
        m["models/model.json"] = text.replace("torch.ops.aten.relu.default", "torch.os.system", 1).encode()

    return change


ATTACKS = {
    "pickled weight": (pickled_weight, "is stored pickled (use_pickle)"),
    "opaque constant": (opaque_constant, "is a pickled constant object"),
    "pickled sample inputs": (pickled_sample_inputs, "is not plain tensors"),
    "evaluated shape expression": (evaluated_expression, "which names '__import__'"),
    "foreign node target": (foreign_target, "calls 'torch.os.system'"),
}


@pytest.fixture(scope="module")
def program() -> bytes:
    return genuine()


def test_a_genuine_program_passes_and_runs(program):
    check_pt2(program)
    actor = ExportedActor.from_bytes(program, [-1.0] * ACT, [1.0] * ACT)
    out = actor(torch.zeros(4, OBS))
    assert out.shape == (4, ACT) and torch.isfinite(out).all()


@pytest.mark.parametrize("attack", ["pickled weight", "pickled sample inputs", "evaluated shape expression"])
def test_torch_itself_runs_the_planted_code(attack, program, tmp_path):
    """Without the inspection, torch.export.load (in a child process) runs what the file plants:
    these are live attacks, not files torch would refuse anyway."""
    marker = tmp_path / "ran"
    path = tmp_path / "planted.pt2"
    path.write_bytes(rewrite(program, ATTACKS[attack][0](marker)))
    subprocess.run(
        [sys.executable, "-c", f"import torch\ntry:\n torch.export.load({str(path)!r})\nexcept Exception:\n pass"],
        capture_output=True,
        timeout=120,
    )
    assert marker.exists(), f"{attack}: torch no longer runs this planted code; the test needs a new attack"


@pytest.mark.parametrize("attack", sorted(ATTACKS))
def test_every_path_refuses_the_planted_archive_in_one_line(attack, program, tmp_path):
    make, says = ATTACKS[attack]
    marker = tmp_path / "ran"
    data = rewrite(program, make(marker))
    with pytest.raises(ArtifactError) as err:
        check_pt2(data)
    assert says in str(err.value) and "\n" not in str(err.value)
    # the module every loader builds
    with pytest.raises(ArtifactError, match="torch.export archive refused"):
        ExportedActor.from_bytes(data, [-1.0] * ACT, [1.0] * ACT)
    # a policy.pt from a remote: weights_only=True on the outer file, a program inside
    meta = {"architecture": "torch_export", "obs_dim": OBS, "act_dim": ACT, "hidden_sizes": []}
    meta |= {"action_low": [-1.0] * ACT, "action_high": [1.0] * ACT, "env_id": "x", "max_episode_steps": 1}
    policy = tmp_path / "policy.pt"
    state = {ExportedActor.KEY: torch.frombuffer(bytearray(data), dtype=torch.uint8)}
    torch.save({"format": POLICY_FORMAT, "format_version": FORMAT_VERSION, "meta": meta, "actor": state}, policy)
    with pytest.raises(ArtifactError) as err:
        load_policy(policy)
    assert str(err.value).startswith(f"{policy}: actor: torch.export archive refused") and says in str(err.value)
    # a population member holding the bytes, whatever its metadata says
    member = Member("start", 0, 0, [], None, [0.0, 0.0], [0.0, 0.0], 1, 0, [8], actor={ExportedActor.KEY: torch.frombuffer(bytearray(data), dtype=torch.uint8)})  # fmt: skip
    with pytest.raises(ArtifactError, match="a start member \\(iteration 0\\): torch.export archive refused"):
        member_actor(member, meta)
    assert not marker.exists()


@pytest.mark.parametrize(
    "change, says",
    [
        (lambda m, r: m.pop("archive_format"), "no 'archive_format' member"),
        (lambda m, r: m.update({"data/weights/model.pt": b"x"}), "legacy format"),
        (lambda m, r: m.update({"models/other.json": b"{}"}), "expected exactly one"),
        (lambda m, r: m.update({"data/aotinductor/model/x.so": b"\x7fELF"}), "compiled code"),
    ],
)
def test_archives_of_other_shapes_are_refused(change, says, program):
    with pytest.raises(ArtifactError, match=says):
        check_pt2(rewrite(program, change))


def test_not_an_archive_and_a_bomb_are_refused(program, monkeypatch):
    with pytest.raises(ArtifactError, match="not a zip archive"):
        check_pt2(b"plain text, not a program")
    with pytest.raises(ArtifactError, match="not a zip archive"):
        check_pt2(program[: len(program) // 2])
    import pipeline.core.pt2check as mod

    monkeypatch.setattr(mod, "MAX_UNPACKED", 1000)
    with pytest.raises(ArtifactError, match="bytes unpacked; refused above 1000"):
        check_pt2(program)


def test_expression_tokens():
    from pipeline.core.pt2check import _expr_ok

    assert _expr_ok("Symbol('s31', positive=True, integer=True)") is None
    assert _expr_ok("Max(2, Symbol('s0', positive=True, integer=True)) + 3*FloorDiv(s1, 2)") is None
    assert _expr_ok("Symbol('s0').__class__") is not None  # attribute access
    assert _expr_ok("eval('1')") == "eval"
    assert _expr_ok("Symbol('s0')[0]") is not None  # subscripts
    assert np.all([_expr_ok(t) is not None for t in ("lambda: 0", "open('x')", "Symbol('a b')")])


def test_targets():
    from pipeline.core.pt2check import _TARGET

    assert _TARGET.fullmatch("torch.ops.aten.linear.default")
    assert _TARGET.fullmatch("torch.ops.aten._assert_tensor_metadata.default")
    for bad in ("torch.os.system", "torch.ops.aten.__class__", "torch.ops.aten.linear.__init__", "torch.ops.myns.op"):
        assert not _TARGET.fullmatch(bad), bad
