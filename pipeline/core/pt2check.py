"""A look inside a `torch.export` archive (`.pt2`) before `torch.export.load` reads it
(docs/trust.md, "torch.export files").

Why: `torch.export.load` (torch 2.13) is not a data reader. It unpickles, with
`weights_only=False`, every weight or tensor constant its config marks `use_pickle`, and with
plain `pickle.loads` every "opaque object" constant; it loads TorchScript objects for
"custom object" constants; it retries the sample inputs with `weights_only=False` when the safe
reader refuses them; it hands every symbolic-shape expression of the graph to
`sympy.sympify`, which evaluates Python; and it resolves a node's target by walking attributes
from the `torch` module, so a target such as `torch.os.system` is reachable. A file from
elsewhere (a user's import, or an artifact pulled from a shared DVC remote whose member holds
`.pt2` bytes) can therefore run code while it loads or runs. Every path that turns `.pt2` bytes
into a module in this project (`nets.ExportedActor`, the export stage's check) calls
`check_pt2` first, every time, whatever file the bytes came from.

What passes is what a policy exported with `torch.export.export` + `torch.export.save` holds:
a zip in the current archive format with one program named "model", weights and tensor
constants stored raw (described by their JSON configs, never pickled), sample inputs that the
safe reader `torch.load(weights_only=True)` accepts, node targets among the ATen operators and
`_operator`'s plain functions, and shape expressions made of sympy constructors and symbol
names only. Anything else is refused with one line naming the archive member and what it
holds. The check reads the archive; it never unpickles anything but through
`weights_only=True`.
"""

from __future__ import annotations

import io
import json
import re
import zipfile
from typing import Any

import torch

from pipeline.core.artifacts import ArtifactError

# an exported policy is kilobytes to a few MB; the cap bounds what a crafted archive can make
# the reader inflate (zip members are checked by their declared and actual sizes)
MAX_UNPACKED = 512 << 20
MAX_MEMBERS = 4096
MODEL = "model"

# node targets a policy's program may call: ATen operators (C++ kernels, no Python) and the
# plain functions of `_operator` that exported graphs use on tuples and symbolic sizes
# (names may start with one underscore, as aten._assert_tensor_metadata does; never two: the
# deserializer resolves a target by getattr, and a dunder would leave the operator namespace)
_TARGET = re.compile(r"torch\.ops\.aten\.(?!__)[A-Za-z_][A-Za-z0-9_]*(\.(?!__)[A-Za-z_][A-Za-z0-9_]*)?")
_OPERATOR_TARGETS = {
    "_operator.getitem",
    "_operator.add",
    "_operator.sub",
    "_operator.mul",
    "_operator.floordiv",
    "_operator.truediv",
    "_operator.mod",
    "_operator.neg",
    "_operator.pow",
    "_operator.eq",
    "_operator.ne",
    "_operator.lt",
    "_operator.le",
    "_operator.gt",
    "_operator.ge",
}
# what a symbolic-shape expression (sympy's srepr, e.g. "Symbol('s31', positive=True,
# integer=True)") may name: sympy's constructors of integer arithmetic and torch's sympy
# functions, their assumption keywords, and symbols (s0, u3, ...). No attribute access, no
# subscripts, no other name: sympify evaluates what it is given.
_SYMPY_NAMES = {
    "Symbol", "Integer", "Rational", "Float", "Add", "Mul", "Pow", "Max", "Min", "Abs", "Mod",
    "Eq", "Ne", "Lt", "Le", "Gt", "Ge", "StrictLessThan", "StrictGreaterThan", "LessThan",
    "GreaterThan", "Equality", "Unequality", "And", "Or", "Not", "true", "false", "oo", "zoo",
    "nan", "Infinity", "NegativeInfinity", "S", "One", "Zero", "NegativeOne", "Half",
    "FloorDiv", "ModularIndexing", "Where", "PythonMod", "CleanDiv", "CeilToInt", "FloorToInt",
    "CeilDiv", "LShift", "RShift", "PowByNatural", "FloatPow", "FloatTrueDiv", "IntTrueDiv",
    "IsNonOverlappingAndDenseIndicator", "TruncToFloat", "TruncToInt", "RoundToInt",
    "RoundDecimal", "ToFloat", "Identity", "OpaqueUnaryFn_sqrt", "BitwiseFn_bitwise_and",
    "BitwiseFn_bitwise_or", "BitwiseFn_bitwise_xor",
    "positive", "negative", "integer", "real", "finite", "nonnegative", "nonpositive", "even",
    "odd", "zero", "nonzero", "True", "False", "None",
}  # fmt: skip
_SYMBOL = re.compile(r"[a-z]\d+")
_TOKEN = re.compile(
    r"\s+|(?P<num>\d+(\.\d+)?(e[+-]?\d+)?)|(?P<str>'[A-Za-z][A-Za-z0-9_]*')|(?P<name>[A-Za-z_][A-Za-z0-9_]*)"
    r"|(?P<op>\*\*|//|==|!=|<=|>=|[-+*/%(),=<>&|~])"
)


class _Refused(Exception):
    pass


def _expr_ok(text: str) -> str | None:
    """None if shape expression `text` holds only the tokens above, else the first refused."""
    pos = 0
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None:
            return text[pos : pos + 20]
        if m.group("name") and m.group("name") not in _SYMPY_NAMES and not _SYMBOL.fullmatch(m.group("name")):
            return m.group("name")
        pos = m.end()
    return None


def _walk(obj: Any, path: str, member: str) -> None:
    """Check every node target and shape expression of a program's JSON."""
    if isinstance(obj, dict):
        for key, value in obj.items():
            if key == "target" and isinstance(value, str):
                if not (_TARGET.fullmatch(value) or value in _OPERATOR_TARGETS):
                    raise _Refused(
                        f"member {member!r} calls {value!r} ({path}); only ATen operators and "
                        "_operator's arithmetic are accepted in a policy's program"
                    )
            elif key == "expr_str" and isinstance(value, str):
                bad = _expr_ok(value)
                if bad is not None:
                    raise _Refused(
                        f"member {member!r} holds the shape expression {value[:80]!r}, which names {bad!r}; "
                        "only sympy's arithmetic and symbol names are accepted (sympify evaluates it)"
                    )
            else:
                _walk(value, f"{path}.{key}", member)
    elif isinstance(obj, list):
        for value in obj:
            _walk(value, path, member)


def _config(zf: zipfile.ZipFile, name: str, kind: str) -> dict[str, Any]:
    try:
        config = json.loads(zf.read(name)).get("config")
    except (ValueError, AttributeError) as exc:
        raise _Refused(f"member {name!r} is not the JSON of a {kind} config ({exc})") from None
    if not isinstance(config, dict):
        raise _Refused(f"member {name!r} has no 'config' mapping")
    for fqn, entry in config.items():
        if not isinstance(entry, dict):
            raise _Refused(f"member {name!r}: entry {fqn!r} is not a mapping")
        if entry.get("use_pickle", False) is not False:
            raise _Refused(
                f"member {name!r}: {kind} {fqn!r} is stored pickled (use_pickle), which torch.export.load "
                "unpickles with weights_only=False; refused unread"
            )
        path_name = entry.get("path_name")
        if kind == "constant" and not (isinstance(path_name, str) and path_name.startswith("tensor_")):
            raise _Refused(
                f"member {name!r}: constant {fqn!r} is stored as {path_name!r}, an object torch.export.load "
                "unpickles (only raw tensor constants are accepted); refused unread"
            )
        if entry.get("tensor_meta") is None:
            raise _Refused(f"member {name!r}: {kind} {fqn!r} has no tensor_meta (a raw tensor needs one)")
    return config


def _inspect(data: bytes) -> None:
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
        infos = zf.infolist()
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise _Refused(f"not a zip archive ({exc})") from None
    if not infos:
        raise _Refused("an empty archive")
    if len(infos) > MAX_MEMBERS:
        raise _Refused(f"{len(infos)} members; a policy's program has a dozen")
    total = sum(i.file_size for i in infos)
    if total > MAX_UNPACKED:
        raise _Refused(f"{total} bytes unpacked; refused above {MAX_UNPACKED}")
    names = [i.filename for i in infos]
    root = names[0].split("/", 1)[0]
    if any(not n.startswith(root + "/") for n in names):
        raise _Refused(f"members outside the archive's root folder {root!r}")
    rel = {n[len(root) + 1 :]: n for n in names}
    if "archive_format" not in rel:
        # without it torch.export.load falls back to the pre-2.8 zip format (pickled state dicts)
        raise _Refused("no 'archive_format' member: not the current torch.export.save format")
    if zf.read(rel["archive_format"]).strip() != b"pt2":
        raise _Refused(f"member {rel['archive_format']!r} does not say 'pt2'")
    models = sorted(r for r in rel if r.startswith("models/"))
    if models != [f"models/{MODEL}.json"]:
        raise _Refused(f"programs {models}; expected exactly one, models/{MODEL}.json")
    for r, full in rel.items():
        if r.startswith(("data/aotinductor/", "data/executorch/", "data/mtia/", "data/xl_model_weights/")):
            raise _Refused(f"member {full!r} holds compiled code or an unsupported payload")
        if r in (f"data/weights/{MODEL}.pt", f"data/constants/{MODEL}.pt"):
            raise _Refused(f"member {full!r} is a pickled state dict of the legacy format; refused unread")
        if r.startswith("data/constants/") and not (r.startswith("data/constants/tensor_") or r.endswith(".json")):
            raise _Refused(f"member {full!r} is a pickled constant object; refused unread")
    for kind, config in (("weight", "data/weights/model_weights_config.json"), ("constant", "data/constants/model_constants_config.json")):  # fmt: skip
        if config not in rel:
            raise _Refused(f"no {config!r} member")
        _config(zf, rel[config], kind)
    sample = f"data/sample_inputs/{MODEL}.pt"
    if sample in rel:
        # torch retries these with weights_only=False when the safe reader refuses them
        try:
            torch.load(io.BytesIO(zf.read(rel[sample])), weights_only=True)
        except Exception as exc:  # any refusal of the safe reader is a refusal here
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:120]
            raise _Refused(
                f"member {rel[sample]!r} is not plain tensors ({first}); torch.export.load would unpickle it "
                "with weights_only=False"
            ) from None
    member = rel[f"models/{MODEL}.json"]
    try:
        program = json.loads(zf.read(member))
    except (ValueError, RecursionError) as exc:
        raise _Refused(f"member {member!r} is not JSON ({str(exc)[:80]})") from None
    _walk(program, "", member)


def check_pt2(data: bytes) -> None:
    """Raise ArtifactError (one line, naming the archive member and what it holds) unless
    `data`, the bytes of a `.pt2` file, is a torch.export program that `torch.export.load` can
    read without unpickling anything or evaluating text (module docstring). Callers name the
    file in front of the message."""
    try:
        _inspect(data)
    except _Refused as exc:
        raise ArtifactError(f"torch.export archive refused: {exc}") from None
    except (zipfile.BadZipFile, zipfile.LargeZipFile, ValueError, OSError, EOFError, KeyError, RecursionError) as exc:
        raise ArtifactError(
            f"torch.export archive refused: unreadable ({type(exc).__name__}: {str(exc)[:120]})"
        ) from None
