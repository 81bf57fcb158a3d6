"""The stockpile client's checkpoint: data only, with a schema and a checksum.

It used to be a Python pickle, and unpickling a crafted file runs any code
its author chose. This format holds only JSON and raw numeric arrays, and
loading it runs no code from the file:

    line 1   header JSON: {"format": FORMAT, "version": VERSION, "sha256": hex,
             "tree_bytes": n, "arrays": [{"dtype", "shape", "nbytes"}, ...]}
    then     the object tree as JSON (n bytes), then each array's bytes in order

``sha256`` covers everything after the header line, so a truncated or
altered file is refused with the file's name. The tree encodes plain values
(None, bool, int, float, str; non-finite floats as ``{"$float": "inf"}``),
containers (``$list``, ``$tuple``, ``$dict`` as key/value pairs, ``$deque``,
``$set``), arrays (``{"$array": k}``, numeric dtypes only, never object
arrays), numpy scalars and dtypes, numpy random generators (bit generator
name and state), and instances of the project's own classes (``$obj``:
``module:qualname`` with the attributes), rebuilt with ``object.__new__`` and
their ``__dict__``: no constructor, ``__reduce__`` or ``__setstate__`` runs,
and only classes defined in the ``cosim`` and ``surrogate`` packages, or in the
module of a registered storage model (``cosim.storage.registered_models``: a
plug-in the user installed), are accepted. Shared references (the mixing
model's generator is the asset's) stay shared (``$id`` / ``$ref``).
"""

from __future__ import annotations

import collections
import hashlib
import importlib
import json
import math
import os
from pathlib import Path

import numpy as np

from cosim.errors import ValidationError

FORMAT = "minetwin-stockpile-checkpoint"
VERSION = 4
"""Raised whenever the state a storage model keeps changes, so that a checkpoint
written by an earlier MineTwin is refused by name instead of resuming a model
that lacks some of its state (3: the ROM's stacking order and move interval;
4: the ROM's transport, packing and projected face velocities)."""
ALLOWED_PACKAGES = ("cosim", "surrogate")
"""Only instances of classes defined in these packages are rebuilt."""
NUMERIC_KINDS = "biuf?"
"""Array dtype kinds a checkpoint may hold (no object, void or string arrays)."""
BIT_GENERATORS = ("PCG64", "PCG64DXSM", "Philox", "SFC64", "MT19937")


class CheckpointError(ValidationError):
    """A checkpoint file that cannot be read, naming the file."""

    def __init__(self, path: Path, detail: str):
        super().__init__("checkpoint", f"a stockpile checkpoint ({FORMAT} version {VERSION})",
                         f"{path}: {detail}")


# ------------------------------------------------------------------- writing
class _Encoder:
    def __init__(self):
        self.arrays: list[np.ndarray] = []
        self.ids: dict[int, int] = {}
        self.keep: list = []  # holds encoded objects alive so their ids stay unique

    def shared(self, value, encode) -> dict:
        key = id(value)
        if key in self.ids:
            return {"$ref": self.ids[key]}
        self.ids[key] = len(self.ids)
        self.keep.append(value)
        return {"$id": self.ids[key], **encode()}

    def encode(self, value):
        if value is None or isinstance(value, (bool, str)):
            return value
        if isinstance(value, int) and not isinstance(value, np.integer):
            return value
        if isinstance(value, float) and not isinstance(value, np.floating):
            return value if math.isfinite(value) else {"$float": repr(value)}
        if isinstance(value, np.ndarray):
            if value.dtype.kind not in NUMERIC_KINDS:
                raise TypeError(f"an array of dtype {value.dtype} (only numeric arrays)")
            return self.shared(value, lambda: self._array(value))
        if isinstance(value, np.generic):
            return {"$scalar": value.dtype.str, "value": self.encode(value.item())}
        if isinstance(value, np.dtype):
            return {"$dtype": value.str}
        if isinstance(value, list):
            return self.shared(value, lambda: {"$list": [self.encode(v) for v in value]})
        if isinstance(value, tuple):
            return {"$tuple": [self.encode(v) for v in value]}
        if isinstance(value, collections.deque):
            return self.shared(value, lambda: {"$deque": [self.encode(v) for v in value],
                                               "maxlen": value.maxlen})
        if isinstance(value, (set, frozenset)):
            return {"$set": [self.encode(v) for v in sorted(value)]}
        if isinstance(value, dict):
            return self.shared(value, lambda: {"$dict": [[self.encode(k), self.encode(v)]
                                                         for k, v in value.items()]})
        if isinstance(value, np.random.Generator):
            return self.shared(value, lambda: {
                "$rng": type(value.bit_generator).__name__,
                "state": self.encode(value.bit_generator.state)})
        cls = type(value)
        if _trusted_module(cls.__module__) and hasattr(value, "__dict__"):
            return self.shared(value, lambda: {
                "$obj": f"{cls.__module__}:{cls.__qualname__}",
                "attrs": {k: self.encode(v) for k, v in vars(value).items()}})
        raise TypeError(f"a {cls.__module__}.{cls.__qualname__}, which is not data")

    def _array(self, value: np.ndarray) -> dict:
        self.arrays.append(np.ascontiguousarray(value))
        return {"$array": len(self.arrays) - 1}


def save_checkpoint(path: Path, state) -> None:
    """Write ``state`` (a ``ClientState``) to ``path`` atomically and durably."""
    encoder = _Encoder()
    tree = json.dumps(encoder.encode(state), allow_nan=False, separators=(",", ":")).encode()
    # the arrays' own buffers, not copies (tobytes was a quarter of a checkpoint's
    # time on a 12,000-particle pile); nothing changes them while this runs
    # (a byte view of the flattened array: memoryview.cast refuses a shape with a zero)
    body = [tree] + [np.ascontiguousarray(a).reshape(-1).view(np.uint8) for a in encoder.arrays]
    digest = hashlib.sha256()
    for chunk in body:
        digest.update(chunk)
    header = {"format": FORMAT, "version": VERSION, "sha256": digest.hexdigest(),
              "tree_bytes": len(tree),
              "arrays": [{"dtype": a.dtype.str, "shape": list(a.shape), "nbytes": a.nbytes}
                         for a in encoder.arrays]}
    tmp = Path(f"{path}.tmp")
    with open(tmp, "wb") as handle:
        handle.write(json.dumps(header, allow_nan=False).encode() + b"\n")
        for chunk in body:
            handle.write(chunk)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


# ------------------------------------------------------------------- reading
def load_checkpoint(path: Path):
    """Read a checkpoint written by ``save_checkpoint``; ``CheckpointError`` if it is
    not one (another format such as a pickle, truncated, altered, unknown classes)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise CheckpointError(path, exc.strerror or str(exc)) from None
    line, newline, rest = data.partition(b"\n")
    try:
        header = json.loads(line.decode("utf-8")) if newline else None
    except (UnicodeDecodeError, ValueError):
        header = None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise CheckpointError(path, "not a checkpoint of this format (an old pickle checkpoint "
                                    "is not read: it could run code)")
    if header.get("version") != VERSION:
        raise CheckpointError(path, f"version {header.get('version')!r}, written by another "
                                    "MineTwin version whose stockpile state differs; start "
                                    "the stockpile without this checkpoint")
    if hashlib.sha256(rest).hexdigest() != header.get("sha256"):
        raise CheckpointError(path, "checksum mismatch (truncated or altered)")
    try:
        tree_bytes = int(header["tree_bytes"])
        arrays, offset = [], tree_bytes
        for spec in header["arrays"]:
            dtype = np.dtype(str(spec["dtype"]))
            if dtype.kind not in NUMERIC_KINDS:
                raise ValueError(f"array dtype {dtype}")
            count = int(np.prod(spec["shape"], dtype=np.int64))
            nbytes = int(spec["nbytes"])
            if nbytes != count * dtype.itemsize or offset + nbytes > len(rest):
                raise ValueError("array sizes do not match the file")
            arrays.append(np.frombuffer(rest, dtype=dtype, count=count, offset=offset)
                          .reshape(spec["shape"]).copy())
            offset += nbytes
        tree = json.loads(rest[:tree_bytes].decode("utf-8"))
        return _Decoder(arrays).decode(tree)
    except (KeyError, TypeError, ValueError, AttributeError, ImportError) as exc:
        raise CheckpointError(path, f"unreadable contents ({type(exc).__name__}: {exc})") from None


class _Decoder:
    def __init__(self, arrays: list[np.ndarray]):
        self.arrays = arrays
        self.objects: dict[int, object] = {}

    def decode(self, node):
        if not isinstance(node, dict):
            if isinstance(node, list):
                raise ValueError("a bare JSON list")
            return node
        if "$ref" in node:
            return self.objects[int(node["$ref"])]
        ident = node.get("$id")
        if "$float" in node:
            if node["$float"] not in ("inf", "-inf", "nan"):
                raise ValueError(f"float {node['$float']!r}")
            return float(node["$float"])
        if "$array" in node:
            return self._keep(ident, self.arrays[int(node["$array"])])
        if "$scalar" in node:
            dtype = np.dtype(str(node["$scalar"]))
            if dtype.kind not in NUMERIC_KINDS:
                raise ValueError(f"scalar dtype {dtype}")
            return dtype.type(self.decode(node["value"]))
        if "$dtype" in node:
            dtype = np.dtype(str(node["$dtype"]))
            if dtype.kind not in NUMERIC_KINDS:
                raise ValueError(f"dtype {dtype}")
            return dtype
        if "$tuple" in node:
            return tuple(self.decode(v) for v in node["$tuple"])
        if "$set" in node:
            return {self.decode(v) for v in node["$set"]}
        if "$list" in node:
            out = self._keep(ident, [])
            out.extend(self.decode(v) for v in node["$list"])
            return out
        if "$deque" in node:
            out = self._keep(ident, collections.deque(maxlen=node["maxlen"]))
            out.extend(self.decode(v) for v in node["$deque"])
            return out
        if "$dict" in node:
            out = self._keep(ident, {})
            for key, value in node["$dict"]:
                out[self.decode(key)] = self.decode(value)
            return out
        if "$rng" in node:
            if node["$rng"] not in BIT_GENERATORS:
                raise ValueError(f"bit generator {node['$rng']!r}")
            bit_generator = getattr(np.random, node["$rng"])()
            out = self._keep(ident, np.random.Generator(bit_generator))
            bit_generator.state = self.decode(node["state"])
            return out
        if "$obj" in node:
            out = self._keep(ident, object.__new__(_project_class(node["$obj"])))
            out.__dict__.update({k: self.decode(v) for k, v in node["attrs"].items()})
            return out
        raise ValueError(f"an unknown node {sorted(node)}")

    def _keep(self, ident, value):
        if ident is not None:
            self.objects[int(ident)] = value
        return value


def _trusted_module(module_name: str) -> bool:
    """A module of this project's packages, or the module of a registered storage model."""
    from cosim.storage import registered_models

    return (module_name.split(".")[0] in ALLOWED_PACKAGES
            or module_name in {ep.module for ep in registered_models().values()})


def _project_class(name: str) -> type:
    """The class ``module:qualname``, only from this project's packages."""
    module_name, _, qualname = str(name).partition(":")
    if not _trusted_module(module_name) or not qualname.isidentifier() \
            or module_name.endswith("__main__"):
        raise ValueError(f"class {name!r} is not one of this project's")
    cls = getattr(importlib.import_module(module_name), qualname, None)
    if not isinstance(cls, type) or cls.__module__ != module_name:
        raise ValueError(f"class {name!r} is not one of this project's")
    return cls
