"""Parameter tables of a scenario: pydantic v2 models that keep MineTwin's messages.

Every table is a ``Parameters`` model (``extra="forbid"``: an unknown key is
an error). Numbers are ``number(low, high, unit=...)``: a refusal reads
``assets.left.grade: must be finite and >= 0 and <= 1 (got 1.5)``, naming the
dotted key, the allowed range and the unit. ``check`` validates a table and
turns every pydantic error into a ``cosim.errors.ValidationError``, so one
pass reports all errors at once (``ValidationErrors``).

A check that needs several fields (a model validator) raises
``refuse(key, allowed, detail)``: the error names ``key`` inside the table.
"""

from __future__ import annotations

import math
import types
import typing
from typing import Annotated, Any

import pydantic
from pydantic import BaseModel, BeforeValidator, ConfigDict, model_validator
from pydantic_core import PydanticCustomError

from cosim.errors import ValidationError

MAX_LENGTH_M = 100_000.0
"""Longest ore body, face, belt or block [m] a scenario may set (100 km)."""
MAX_BLOCKS = 1_000_000
"""Most block-model cells along a source, and bins along a belt (each costs memory)."""


class Parameters(BaseModel):
    """Base of every parameter table: unknown keys are refused."""

    model_config = ConfigDict(extra="forbid", validate_default=False)


def refuse(key: str, allowed: str, detail: str = "") -> PydanticCustomError:
    """The error a validator raises for ``key`` (dotted, inside the table it checks)."""
    return PydanticCustomError("minetwin", "{key}: must be {allowed}",
                               {"key": key, "allowed": allowed, "detail": detail})


def refuse_from(error: ValidationError, prefix: str = "") -> PydanticCustomError:
    """``refuse`` for a ``ValidationError`` raised by a library check."""
    key = f"{prefix}.{error.field}" if prefix else error.field
    return refuse(key, error.allowed, error.detail)


def _range_text(low, high, low_open, unit) -> str:
    suffix = f" {unit}" if unit else ""
    parts = ["finite"]
    if low is not None:
        parts.append(f"{'>' if low_open else '>='} {low:g}")
    if high is not None:
        parts.append(f"<= {high:g}")
    return " and ".join(parts) + suffix


def number(low=None, high=None, *, low_open: bool = False, unit: str = "",
           integer: bool = False):
    """A float (or int) field in [low, high] (or (low, high]) with ``unit`` in messages."""

    def check(value):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise PydanticCustomError("minetwin", "must be {allowed}", {
                "key": "", "allowed": f"a number{' [' + unit + ']' if unit else ''}",
                "detail": f"got {value!r}"})
        if integer and not float(value).is_integer():
            raise PydanticCustomError("minetwin", "must be {allowed}", {
                "key": "", "allowed": "an integer", "detail": f"got {value!r}"})
        ok = math.isfinite(value) and (low is None or (value > low if low_open else value >= low)) \
            and (high is None or value <= high)
        if not ok:
            raise PydanticCustomError("minetwin", "must be {allowed}", {
                "key": "", "allowed": _range_text(low, high, low_open, unit),
                "detail": f"got {value!r}"})
        return int(value) if integer else float(value)

    return Annotated[int if integer else float, BeforeValidator(check)]


def _position(value):
    ok = isinstance(value, (list, tuple)) and len(value) in (2, 3) and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        for v in value)
    if not ok:
        raise PydanticCustomError("minetwin", "must be {allowed}", {
            "key": "", "allowed": "a list of 2 or 3 finite coordinates [m]",
            "detail": f"got {value!r}"})
    return [float(v) for v in value] + [0.0] * (3 - len(value))


Position = Annotated[list[float], BeforeValidator(_position)]
"""A point [m]: 2 or 3 coordinates (z = 0 when omitted)."""


def choice(*allowed: str):
    """A string among ``allowed``."""

    def check(value):
        if not isinstance(value, str) or value not in allowed:
            raise PydanticCustomError("minetwin", "must be {allowed}", {
                "key": "", "allowed": f"one of {list(allowed)}", "detail": f"got {value!r}"})
        return value

    return Annotated[str, BeforeValidator(check)]


def _text(value):
    if not isinstance(value, str) or not value:
        raise PydanticCustomError("minetwin", "must be {allowed}", {
            "key": "", "allowed": "a non-empty string", "detail": f"got {value!r}"})
    return value


Text = Annotated[str, BeforeValidator(_text)]


def _fmu_parameters(value):
    """FMU parameters as given (numbers, booleans, strings, or lists of them): the FMU
    checks each against its variable's type and range (``check_fmu_parameters``)."""
    if not isinstance(value, dict):
        raise PydanticCustomError("minetwin", "must be {allowed}", {
            "key": "", "allowed": "a table", "detail": f"got {value!r}"})
    for key, item in value.items():
        for entry in item if isinstance(item, list) else [item]:
            if not isinstance(entry, (bool, int, float, str)) or (
                    isinstance(entry, float) and not math.isfinite(entry)):
                raise refuse(key, "a finite number, a boolean, a string or a list of them",
                             f"got {item!r}")
    return dict(value)


FmuParameters = Annotated[dict[str, Any], BeforeValidator(_fmu_parameters)]


class FmuAssetParameters(Parameters):
    """Base of the table of an asset with an FMU (crusher, mill): ``parameters`` are
    checked against the FMU's declared variables and their min/max at load."""

    fmu: Text
    """A built FMU name (fmus/build) or an .fmu path."""
    parameters: FmuParameters = {}
    """FMU parameters (checked against the FMU's declared variables and ranges)."""

    @model_validator(mode="after")
    def _fmu(self):
        from cosim.fmu import check_fmu_parameters

        try:
            check_fmu_parameters(self.fmu, self.parameters)
        except ValidationError as exc:
            raise refuse_from(exc) from None
        return self


def _schedule(value):
    from cosim.storage import MAX_DISCHARGE_RATE

    ok = isinstance(value, list) and value and all(
        isinstance(row, (list, tuple)) and len(row) == 2 for row in value)
    if not ok:
        raise PydanticCustomError("minetwin", "must be {allowed}", {
            "key": "", "allowed": "a non-empty list of [time_s, rate_kg_s]",
            "detail": f"got {value!r}"})
    rows = []
    for k, (t, rate) in enumerate(value):
        for key, item, high, unit in (("t", t, None, "s"),
                                      ("rate", rate, MAX_DISCHARGE_RATE, "kg/s")):
            if isinstance(item, bool) or not isinstance(item, (int, float)) or not (
                    math.isfinite(item) and item >= 0 and (high is None or item <= high)):
                raise refuse(f"[{k}].{key}", _range_text(0.0, high, False, unit), f"got {item!r}")
        rows.append([float(t), float(rate)])
    return rows


Schedule = Annotated[list[list[float]], BeforeValidator(_schedule)]
"""A piecewise-constant feeder schedule [[time_s, rate_kg_s], ...] (rates <= 2000 kg/s)."""


# ------------------------------------------------------------------ error report
def _path(prefix: str, loc) -> str:
    path = prefix
    for part in loc:
        if isinstance(part, int):
            path += f"[{part}]"
        elif str(part).startswith("["):
            path += str(part)
        else:
            path += f".{part}" if path else str(part)
    return path


def _fields_at(model: type, loc) -> list[str] | None:
    """The keys allowed in the table at ``loc`` inside ``model`` (None: unknown)."""
    annotation: Any = model
    for part in loc:
        annotation = _unwrap(annotation)
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            field = annotation.model_fields.get(str(part))
            if field is None:
                return None
            annotation = field.annotation
            continue
        origin, args = typing.get_origin(annotation), typing.get_args(annotation)
        if origin in (dict, list) and args:
            annotation = args[-1]
            continue
        return None
    annotation = _unwrap(annotation)
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return sorted(annotation.model_fields)
    return None


def _unwrap(annotation):
    while True:
        origin = typing.get_origin(annotation)
        if origin is Annotated:
            annotation = typing.get_args(annotation)[0]
        elif origin in (typing.Union, types.UnionType):
            args = [a for a in typing.get_args(annotation) if a is not type(None)]
            annotation = args[0]
        else:
            return annotation


def errors_of(exc: pydantic.ValidationError, model: type, prefix: str = "") \
        -> list[ValidationError]:
    """Every error of a pydantic validation as a ``ValidationError`` naming its key."""
    found = []
    for error in exc.errors():
        loc = error["loc"]
        kind = error["type"]
        if kind == "minetwin":
            ctx = error["ctx"]
            key = ctx["key"]
            loc = [p for p in loc if not (isinstance(p, str) and p.startswith("function-"))]
            path = _path(prefix, loc)
            if key:
                path = path + key if key.startswith("[") else (f"{path}.{key}" if path else key)
            found.append(ValidationError(path, ctx["allowed"], ctx["detail"]))
        elif kind == "missing":
            found.append(ValidationError(_path(prefix, loc), "given", "missing required key"))
        elif kind == "extra_forbidden":
            allowed = _fields_at(model, loc[:-1])
            found.append(ValidationError(_path(prefix, loc),
                                         f"one of {allowed}" if allowed else "a known key",
                                         "unknown key"))
        elif kind in ("model_type", "dict_type", "model_attributes_type"):
            found.append(ValidationError(_path(prefix, loc), "a table",
                                         f"got {error['input']!r}"))
        elif kind == "list_type":
            found.append(ValidationError(_path(prefix, loc), "an array",
                                         f"got {error['input']!r}"))
        else:
            found.append(ValidationError(_path(prefix, loc), error["msg"].lower(),
                                         f"got {error['input']!r}"))
    return found


def check(model: type, table, prefix: str = ""):
    """``(parameters, errors)``: the validated model (None if it failed) and its errors."""
    if not isinstance(table, dict):
        return None, [ValidationError(prefix or "table", "a table", f"got {table!r}")]
    try:
        return model.model_validate(table), []
    except pydantic.ValidationError as exc:
        return None, errors_of(exc, model, prefix)
