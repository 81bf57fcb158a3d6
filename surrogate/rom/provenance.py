"""What a trained ROM was trained on, and the one command that makes it again.

Source: issue 15 ("a trained paper-scale ROM shipped with the package [...]
committed with its provenance: design, seeds, code version, and the one
command that regenerates it bit for bit on the same machine").

``training_provenance`` is written into the model file's header by
``minetwin rom train``: the data folder as given, the SHA-256 of its training
files (``doe.json`` and ``train/*.npz``, names and bytes), the design and
its runs (name, content key, seed, the git commit each DEM run was made at)
when the folder holds a design's ``manifest.json``, the source tree's git
commit and numpy version the model was fitted with, the options (with the
SHA-256 of a validation design's files, ``minetwin rom train --validation``),
and the command line. The fit is deterministic (SVD and a linear solve, no random
draw): the same data, options, code and machine give the same file.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from cosim import batch


def data_digest(directory) -> str:
    """SHA-256 over ``doe.json`` and every ``train/*.npz`` (sorted names and bytes)."""
    directory = Path(directory)
    digest = hashlib.sha256()
    for path in [directory / "doe.json", *sorted((directory / "train").glob("*.npz"))]:
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def _runs(directory: Path) -> tuple[dict, list]:
    manifest = directory / "manifest.json"
    if not manifest.is_file():  # a `rom evaluate --quick` folder: runs by file name
        return {}, [{"name": p.stem} for p in sorted((directory / "train").glob("*.npz"))]
    design = json.loads(manifest.read_text())
    runs = [{"name": r["name"], "key": r["key"], "seed": r["seed"],
             "git_commit": r.get("git_commit")} for r in design.get("runs", [])]
    return {"design": design.get("design"), "design_version": design.get("design_version")}, runs


def _flag_value(value) -> str:
    """A float as short as it reads back exactly (``100``, ``564.1891533925966``)."""
    if isinstance(value, float):
        short = f"{value:g}"
        return short if float(short) == value else repr(value)
    return str(value)


def regenerate_command(data, out, options: dict) -> str:
    """``minetwin rom train`` with ``data``, ``out`` and the options that were given."""
    flags = "".join(f" --{name.replace('_', '-')} {_flag_value(one)}"
                    for name, value in options.items() if value is not None
                    for one in (value if isinstance(value, list) else [value]))
    return f"minetwin rom train --data {data} --out {out}{flags}"


def training_provenance(data, out, options: dict) -> dict:
    """The provenance of a model trained on ``data`` into ``out`` (module docstring)."""
    design, runs = _runs(Path(data))
    provenance = {**design, "data": str(data), "data_sha256": data_digest(data), "runs": runs,
                  "code_version": batch.code_version(), "numpy": np.__version__,
                  "options": dict(options),
                  "regenerate": regenerate_command(data, out, options)}
    chosen_on = options.get("validation")
    if chosen_on is not None:  # the scenes the options were chosen on
        provenance["validation_sha256"] = (
            [data_digest(folder) for folder in chosen_on] if isinstance(chosen_on, list)
            else data_digest(chosen_on))
    return provenance
