"""FMUs as co-simulation components: load, validate, parameterise and step any
FMI 2.0 or FMI 3.0 Co-Simulation FMU through fmpy's low-level API.

Source: the FMI standard (FMI 2.0.4 and FMI 3.0.1, Co-Simulation chapters:
doStep, fmi2Discard with fmi2GetBooleanStatus(fmi2Terminated), fmi3DoStep's
terminateSimulation / eventHandlingNeeded / earlyReturn, event mode) and
fmus/README.md (the crusher/mill interface convention).

API (stable; other modules rely on it)::

    from cosim.fmu import FmuComponent, CRUSHER_INTERFACE, MILL_INTERFACE, fmu_path
    crusher = FmuComponent(fmu_path("crusher"), interface=CRUSHER_INTERFACE,
                           name="crusher_fmu", parameters={"gap_width": 0.25})
    crusher.set_input("speed", 10.0)
    crusher.set_input("zone_hardness_mass", np.zeros(16))
    crusher.step(t, dt)
    crusher.outputs()   # {"torque": float, "power": float, "energy": float,
                        #  "fragmentation_map": (16, 16) array}
    crusher.finish()

* ``fmu_path(name, fmi=3)`` -> ``fmus/build/<name>.fmu`` (FMI 3.0) or
  ``fmus/build/<name>-fmi2.fmu`` (``fmi=2``); a missing file is an error
  telling to run ``minetwin fmus build``.
* Every variable type: FMI 3 Float32/Float64, Int8..UInt64, Boolean, String,
  Binary, Enumeration; FMI 2 Real, Integer, Boolean, String, Enumeration
  (``FmuComponent.variables[name].type`` uses the FMI 3 names: Real is
  Float64, Integer is Int32). Outputs come back as Python floats, ints (exact,
  also for 64-bit), bools, str and bytes, arrays as numpy arrays of the
  matching dtype; an Enumeration is its integer value and
  ``item_name(variable, value)`` gives the item's name. ``set_input`` and
  parameters check the type and range (an Int8 takes integers in -128..127, a
  Boolean only bools, an Enumeration one of its item values or names).
* Arrays: FMI 3.0 array variables, or FMI 2.0 scalars ``x[1]``..``x[16]`` and
  ``x[1,1]``..``x[16,16]`` (1-based, row-major: the Modelica convention). Either
  way ``set_input`` takes and ``outputs`` returns numpy arrays of the declared
  shape (0-based).
* Validation at load against an interface (a tuple of ``VariableSpec``): every
  missing variable, wrong causality, wrong type or wrong array size is listed
  in one ``FmuInterfaceError`` naming the FMU file. A broken archive (not a
  zip, a member failing its CRC, a corrupt deflate stream) or a missing binary
  for this platform is a ``ValidationError`` naming the .fmu path (and the
  platforms the FMU has); no extracted folder is left behind on any failure.
* A failing FMI call (e.g. ``doStep``) raises ``FmuCallError`` with the FMU's
  own log message; inside ``Master.run`` this stops the run and the recorded
  data stays readable.
* A stop request (FMI 3 ``terminateSimulation``; FMI 2 ``fmi2Discard`` with
  ``fmi2Terminated``) is not an error: ``stop_request`` is set to a
  ``StopRequest`` (the FMU's last successful time and why) and the master
  ends the run there.
* FMI 3 event mode: an FMU with ``hasEventMode`` is instantiated with event
  mode and early return; an event inside a communication step ends doStep
  early, the component runs the event iteration (``fmi3EnterEventMode``,
  ``fmi3UpdateDiscreteStates`` until no update is needed,
  ``fmi3EnterStepMode``) and completes the step, as fmpy's ``simulate_fmu``
  with ``use_event_mode=True, early_return_allowed=True``; ``events_handled``
  counts them. (FMI 2 Co-Simulation has no event mode: the FMU handles its
  events inside ``doStep``.)
* Interfaces by asset role (``crusher``, ``mill``, or a package's own) and FMU files a
  package ships are registered through entry points (``cosim.fmu_registry``).
* ``describe_fmu(path)`` (``minetwin fmus info``) lists an FMU's attributes
  and variables without instantiating it.
"""

from __future__ import annotations

import ctypes
import re
import shutil
import tempfile
import warnings
import weakref
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from fmpy.fmi1 import FMICallException

from cosim.errors import ValidationError
from cosim.master import Component, StopRequest

BUILD_DIR = Path(__file__).resolve().parent.parent / "fmus" / "build"
"""Where ``minetwin fmus build`` writes the FMUs."""

FMI2_DISCARD = 2
FMI2_LAST_SUCCESSFUL_TIME = 2  # fmi2StatusKind
FMI2_TERMINATED = 3


@dataclass(frozen=True)
class VariableSpec:
    """One variable an asset needs from an FMU (type in FMI 3 names: Float64, Int32, ...)."""

    name: str
    causality: str  # "parameter", "input" or "output"
    shape: tuple[int, ...] = ()
    unit: str = ""
    type: str = "Float64"


N = 16
CRUSHER_INTERFACE = (
    VariableSpec("speed", "input", (), "rad/s"),
    VariableSpec("zone_hardness_mass", "input", (N,), "kg"),
    VariableSpec("torque", "output", (), "N.m"),
    VariableSpec("power", "output", (), "W"),
    VariableSpec("energy", "output", (), "J"),
    VariableSpec("fragmentation_map", "output", (N, N), "1"),
)
"""What a crusher asset needs (fmus/README.md, "Crusher")."""

MILL_INTERFACE = (
    VariableSpec("speed_setpoint", "input", (), "rad/s"),
    VariableSpec("charge_mass", "input", (N,), "kg"),
    VariableSpec("breakage_rate", "output", (N,), "1/s"),
    VariableSpec("daughter_fraction", "output", (N, N), "1"),
    VariableSpec("escape_rate", "output", (N,), "1/s"),
    VariableSpec("speed", "output", (), "rad/s"),
    VariableSpec("torque_drive", "output", (), "N.m"),
    VariableSpec("torque_acceleration", "output", (), "N.m"),
    VariableSpec("torque_active", "output", (), "N.m"),
    VariableSpec("torque", "output", (), "N.m"),
    VariableSpec("power", "output", (), "W"),
    VariableSpec("d50", "output", (), "m"),
)
"""What a mill asset needs (fmus/README.md, "Mill")."""


class FmuInterfaceError(ValidationError):
    """The FMU does not offer variables the asset needs (raised at load, all listed at once).

    ``problems`` holds one ``(variable, expected, found)`` per mismatch."""

    def __init__(self, fmu_name: str, problems: list[tuple[str, str, str]]):
        self.problems = problems
        first, expected, found = problems[0]
        super().__init__(f"{fmu_name}: variable {first!r}", expected, found)
        if len(problems) > 1:
            listed = "; ".join(f"variable {v!r}: must be {e} ({f})" for v, e, f in problems)
            self.args = (f"{fmu_name}: {len(problems)} variables do not match the "
                         f"interface: {listed}",)

    def __str__(self):
        return self.args[0]


class FmuCallError(RuntimeError):
    """An FMI call failed; the message names the FMU file, the call and the FMU's log."""


def fmu_path(name: str, fmi: int = 3) -> Path:
    """Built FMU of model ``name``: ``fmus/build/<name>.fmu`` (FMI 3.0) or ``-fmi2.fmu``."""
    if fmi not in (2, 3):
        raise ValidationError("fmi", "2 or 3", f"got {fmi!r}")
    path = BUILD_DIR / (f"{name}.fmu" if fmi == 3 else f"{name}-fmi2.fmu")
    if not path.is_file():
        raise ValidationError("fmu", "a built FMU file",
                              f"{path} does not exist; run `minetwin fmus build`")
    return path


def resolve_fmu(name: str) -> str:
    """The .fmu file a scenario means by ``name``: a path ending in .fmu, a built FMU
    (fmus/build/<name>.fmu), or an FMU a package registered (``cosim.fmu_registry``)."""
    from cosim.fmu_registry import registered_fmu_path, registered_fmus

    if name.endswith(".fmu"):
        if not Path(name).is_file():
            raise ValidationError("fmu", "a built FMU name or an existing .fmu file",
                                  f"{name!r} not found")
        return name
    built = BUILD_DIR / f"{name}.fmu"
    if built.is_file():
        return str(built)
    registered = registered_fmu_path(name)
    if registered is not None:
        return str(registered)
    names = sorted({p.name[:-len(".fmu")] for p in BUILD_DIR.glob("*.fmu")
                    if not p.name.endswith("-fmi2.fmu")} | set(registered_fmus()))
    raise ValidationError("fmu", f"an existing .fmu file or an FMU name: one of {names} "
                          "(built in fmus/build or registered by a package)",
                          f"got {name!r}; if it is one of MineTwin's own, run "
                          "`minetwin fmus build`")


def check_fmu_parameters(fmu: str, parameters: dict) -> None:
    """Refuse an FMU name that resolves to no file (``resolve_fmu``), parameters the FMU
    does not have, or values outside its declared min/max (field ``parameters.NAME``)."""
    file = resolve_fmu(fmu)
    if not parameters:
        return
    from fmpy import read_model_description

    try:
        description = read_model_description(file)
    except Exception:  # noqa: BLE001 - a broken FMU is reported, in full, when it is loaded
        return
    declared = {v.name: v for v in description.modelVariables
                if v.causality in ("parameter", "input") or v.variability == "tunable"}
    for key, value in parameters.items():
        name = f"parameters.{key}"
        variable = declared.get(key)
        if variable is None:
            raise ValidationError(name, f"a parameter of {Path(file).name}: "
                                  f"one of {sorted(declared)}", "unknown parameter")
        unit = f" {variable.unit}" if variable.unit else ""
        low, high = (None if v is None else float(v) for v in (variable.min, variable.max))
        if (low is not None and value < low) or (high is not None and value > high):
            bounds = " and ".join(part for part in (
                f">= {low:g}{unit}" if low is not None else "",
                f"<= {high:g}{unit}" if high is not None else "") if part)
            raise ValidationError(name, f"{bounds} (the FMU's declared range)",
                                  f"got {value!r}")


def fmi2_scalar_names(name: str, shape) -> list[str]:
    """FMI 2.0 scalar names of a variable, row-major: ``x``, ``x[1]``.., ``x[1,1]``.."""
    if len(shape) == 0:
        return [name]
    if len(shape) == 1:
        return [f"{name}[{i + 1}]" for i in range(shape[0])]
    if len(shape) == 2:
        return [f"{name}[{i + 1},{j + 1}]" for i in range(shape[0]) for j in range(shape[1])]
    raise ValidationError("shape", "at most 2 dimensions", f"{name} has shape {tuple(shape)}")


# ---- types ------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Access:
    """How values of one FMI type cross the C interface."""

    function: str        # suffix of fmi2Get*/fmi3Get*: "Float64", "Real", "Int64", ...
    ctype: object        # ctypes element type of the value buffer
    dtype: object        # numpy dtype of the values (object: String, Binary)


_INTEGER_RANGES = {name: (int(np.iinfo(dtype).min), int(np.iinfo(dtype).max)) for name, dtype in
                   (("Int8", np.int8), ("UInt8", np.uint8), ("Int16", np.int16),
                    ("UInt16", np.uint16), ("Int32", np.int32), ("UInt32", np.uint32),
                    ("Int64", np.int64), ("UInt64", np.uint64))}

_FMI3_ACCESS = {
    "Float32": _Access("Float32", ctypes.c_float, np.float32),
    "Float64": _Access("Float64", ctypes.c_double, np.float64),
    "Int8": _Access("Int8", ctypes.c_int8, np.int8),
    "UInt8": _Access("UInt8", ctypes.c_uint8, np.uint8),
    "Int16": _Access("Int16", ctypes.c_int16, np.int16),
    "UInt16": _Access("UInt16", ctypes.c_uint16, np.uint16),
    "Int32": _Access("Int32", ctypes.c_int32, np.int32),
    "UInt32": _Access("UInt32", ctypes.c_uint32, np.uint32),
    "Int64": _Access("Int64", ctypes.c_int64, np.int64),
    "UInt64": _Access("UInt64", ctypes.c_uint64, np.uint64),
    "Boolean": _Access("Boolean", ctypes.c_bool, np.bool_),
    "Enumeration": _Access("Int64", ctypes.c_int64, np.int64),
    "String": _Access("String", ctypes.c_char_p, object),
    "Binary": _Access("Binary", ctypes.c_void_p, object),
}
_FMI2_ACCESS = {
    "Float64": _Access("Real", ctypes.c_double, np.float64),
    "Int32": _Access("Integer", ctypes.c_int32, np.int32),
    "Enumeration": _Access("Integer", ctypes.c_int32, np.int32),
    "Boolean": _Access("Boolean", ctypes.c_int32, np.int32),  # fmi2Boolean is a C int
    "String": _Access("String", ctypes.c_char_p, object),
}
_FMI2_TYPE_NAMES = {"Real": "Float64", "Integer": "Int32", "Boolean": "Boolean",
                    "String": "String", "Enumeration": "Enumeration"}

RECORD_DTYPES = {"Float32": np.float32, "Float64": np.float64, "Boolean": np.bool_,
                 "Enumeration": np.int64, "String": object, "Binary": object,
                 **{name: getattr(np, name.lower()) for name in _INTEGER_RANGES}}
"""numpy dtype a recorded output of each FMI type gets in the master's time series."""


@dataclass
class _Variable:
    """A (possibly array) variable of the loaded FMU."""

    name: str
    causality: str
    type: str                    # FMI 3 type name (FMI 2 Real -> Float64, Integer -> Int32)
    shape: tuple
    value_references: list[int]  # FMI 3: one per variable; FMI 2: one per element
    native_type: str = ""        # the type as the FMU's own FMI version names it
    start: object = None         # declared start value(s), as text
    unit: str = ""
    description: str = ""
    variability: str = ""
    items: dict = field(default_factory=dict)  # Enumeration: value -> item name
    low: float = float("-inf")   # range an integer input takes (set for the fast path)
    high: float = float("inf")

    @property
    def size(self) -> int:
        return int(np.prod(self.shape)) if "incomplete" not in self.shape else 0


_FMI2_ELEMENT = re.compile(r"^(?P<base>.+)\[(?P<index>\d+(?:,\d+)*)\]$")


def _items(v) -> dict:
    declared = getattr(v, "declaredType", None)
    items = getattr(declared, "items", None) or []
    return {int(item.value): item.name for item in items}


def _describe(v, name, type_name, shape, refs, start) -> _Variable:
    return _Variable(name, v.causality, type_name, shape, refs, native_type=v.type, start=start,
                     unit=v.unit or (getattr(v.declaredType, "unit", None) or ""),
                     description=v.description or "", variability=v.variability or "",
                     items=_items(v))


def _fmi2_variables(description) -> dict[str, _Variable]:
    """Group FMI 2.0 scalars ``x[i]`` / ``x[i,j]`` into array variables (Modelica convention)."""
    scalars = {v.name: v for v in description.modelVariables}
    groups: dict[str, list[tuple[tuple[int, ...], object]]] = {}
    result: dict[str, _Variable] = {}
    for v in description.modelVariables:
        match = _FMI2_ELEMENT.match(v.name)
        if match:
            index = tuple(int(i) for i in match["index"].split(","))
            groups.setdefault(match["base"], []).append((index, v))
        else:
            result[v.name] = _describe(v, v.name, _FMI2_TYPE_NAMES[v.type], (),
                                       [v.valueReference], v.start)
    for base, elements in groups.items():
        types = {v.type for _, v in elements}
        if base in scalars or len(types) != 1:
            continue
        ranks = {len(index) for index, _ in elements}
        by_index = {index: v for index, v in elements}
        causalities = {v.causality for v in by_index.values()}
        first = elements[0][1]
        type_name = _FMI2_TYPE_NAMES[first.type]
        shape = tuple(max(index[d] for index, _ in elements) for d in range(max(ranks)))
        full = [tuple(i + 1 for i in idx) for idx in np.ndindex(*shape)]
        variable = _describe(first, base, type_name, shape, [], None)
        variable.causality = causalities.pop() if len(causalities) == 1 else "mixed"
        if len(ranks) != 1 or len(by_index) != len(full) or any(i not in by_index for i in full):
            # not a complete array name[1].. : keep what exists so validation can say so
            variable.shape = ("incomplete", len(by_index))
        else:
            variable.value_references = [by_index[i].valueReference for i in full]
            variable.start = [by_index[i].start for i in full]
        result[base] = variable
    return result


def _fmi3_variables(description) -> dict[str, _Variable]:
    return {v.name: _describe(v, v.name, v.type, tuple(v.shape or ()), [v.valueReference],
                              v.start)
            for v in description.modelVariables if v.type in _FMI3_ACCESS}


def _describe_shape(shape) -> str:
    if shape and shape[0] == "incomplete":
        return f"an incomplete array of {shape[1]} element(s)"
    return "a scalar" if shape == () else f"an array of shape {tuple(shape)}"


# ---- archive ----------------------------------------------------------------------------
def _binary_platform(fmi: int) -> tuple[str, str]:
    """(this platform's binaries/ folder name for ``fmi``, shared-library suffix)."""
    import fmpy

    suffix = {"windows": ".dll", "darwin": ".dylib"}.get(fmpy.system, ".so")
    return (fmpy.platform_tuple if fmi == 3 else fmpy.platform), suffix


def read_description(path: Path):
    """modelDescription.xml of ``path`` after checking the archive (every member's CRC).

    A file that is not a zip, a member failing its CRC or a corrupt deflate
    stream is a ``ValidationError`` naming ``path``."""
    from fmpy import read_model_description

    try:
        with zipfile.ZipFile(path) as archive:
            for info in archive.infolist():
                _check_member(path, archive, info)
            if "modelDescription.xml" not in archive.namelist():
                raise ValidationError("fmu", "an FMU archive with modelDescription.xml",
                                      f"{path} has none")
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError) as exc:
        raise ValidationError("fmu", "an FMU (a zip archive)", f"{path}: {exc}") from None
    try:
        return read_model_description(str(path), validate=False)
    except Exception as exc:  # fmpy raises plain Exceptions on malformed XML
        raise ValidationError("fmu", "an FMU with a readable modelDescription.xml",
                              f"{path}: {exc}") from None


def _check_member(path: Path, archive: zipfile.ZipFile, info: zipfile.ZipInfo) -> None:
    """Read one member through, so its CRC and its deflate stream are checked."""
    try:
        with archive.open(info) as member:
            while member.read(1 << 20):
                pass
    except zipfile.BadZipFile as exc:
        detail = "fails its CRC check" if "CRC" in str(exc) else str(exc)
        raise ValidationError("fmu", "an intact FMU archive",
                              f"{path}: member {info.filename} {detail}") from None
    except (zlib.error, EOFError) as exc:
        raise ValidationError("fmu", "an intact FMU archive",
                              f"{path}: member {info.filename}: corrupt deflate stream "
                              f"({exc})") from None


def check_binary(path: Path, description, fmi: int) -> None:
    """Refuse an FMU without a Co-Simulation binary for this platform, listing what it has."""
    needed, suffix = _binary_platform(fmi)
    member = f"binaries/{needed}/{description.coSimulation.modelIdentifier}{suffix}"
    with zipfile.ZipFile(path) as archive:
        names = archive.namelist()
    if member in names:
        return
    present = sorted({n.split("/")[1] for n in names
                      if n.startswith("binaries/") and n.count("/") >= 2 and n.split("/")[2]})
    sources = any(n.startswith("sources/") and n.endswith(".c") for n in names)
    raise ValidationError(
        "fmu", f"an FMU with a binary for this platform ({needed})",
        f"{path} lacks {member}; it has binaries for {present or 'no platform'}"
        + ("; it ships C sources: compile them with `fmpy compile`" if sources else ""))


def extract(path: Path) -> str:
    """Extract ``path`` into a new temporary folder; on any failure the folder is removed."""
    folder = tempfile.mkdtemp(prefix="minetwin-fmu-")
    try:
        with zipfile.ZipFile(path) as archive:
            for name in archive.namelist():
                if name.startswith("/") or ".." in Path(name).parts or "\\" in name:
                    raise ValidationError("fmu", "an FMU whose members stay inside it",
                                          f"{path}: member {name!r}")
            archive.extractall(folder)
    except BaseException as exc:
        shutil.rmtree(folder, ignore_errors=True)
        if isinstance(exc, (zipfile.BadZipFile, zlib.error, EOFError, OSError)):
            raise ValidationError("fmu", "an intact FMU archive", f"{path}: {exc}") from None
        raise
    return folder


# ---- the component ----------------------------------------------------------------------
class _Group:
    """Variables of one causality read or written with one FMI call (one access type)."""

    def __init__(self, access: _Access, variables: list[_Variable]):
        self.access = access
        self.variables = variables
        refs = [r for v in variables for r in v.value_references]
        self.refs = (ctypes.c_uint32 * len(refs))(*refs)
        self.n_refs = len(refs)
        self.n_values = sum(v.size for v in variables)
        self.buffer = (access.ctype * self.n_values)()
        self.sizes = (ctypes.c_size_t * self.n_values)()  # FMI 3 Binary only
        self.view = (np.frombuffer(self.buffer, dtype=access.dtype)
                     if access.dtype is not object else None)
        self.slices = {}
        offset = 0
        for v in variables:
            self.slices[v.name] = (slice(offset, offset + v.size), v.shape)
            offset += v.size
        self.binary_keep: dict = {}  # element -> its Binary buffer, alive while the FMU may read it
        self.calls = None  # {"get"|"set": (fmpy function, arguments)}, bound on first use
        self.has_scalars = any(v.shape == () for v in variables)
        self.bool_ints = access.function == "Boolean" and access.dtype is np.int32


class FmuComponent(Component):
    """Any FMI 2.0 / 3.0 Co-Simulation FMU as a master ``Component``.

    Parameters
    ----------
    path : str or Path
        The ``.fmu`` file.
    interface : tuple of VariableSpec, optional
        Variables the asset needs; checked at load (``FmuInterfaceError``).
    name : str, optional
        Component name in the master (default: the file's stem).
    parameters : dict, optional
        Parameter values set before initialisation (name -> value of the
        parameter's type, or an array of its shape).
    """

    def __init__(self, path, *, interface=(), name: str | None = None,
                 parameters: dict | None = None):
        super().__init__()
        self.path = Path(path)
        if not self.path.is_file():
            raise ValidationError("fmu", "an existing .fmu file", f"{self.path} does not exist")
        self.name = name or self.path.stem
        self.log: list[str] = []
        self.stop_request = None
        self.events_handled = 0
        description = read_description(self.path)
        if description.fmiVersion not in ("2.0", "3.0"):
            raise ValidationError("fmu", "FMI 2.0 or 3.0",
                                  f"{self.path.name} is FMI {description.fmiVersion}")
        if description.coSimulation is None:
            raise ValidationError("fmu", "a Co-Simulation FMU",
                                  f"{self.path.name} has no CoSimulation interface")
        self.description = description
        self.fmi = 3 if description.fmiVersion == "3.0" else 2
        self.variables = (_fmi3_variables if self.fmi == 3 else _fmi2_variables)(description)
        self.interface = tuple(interface)
        self.validate(self.interface)
        check_binary(self.path, description, self.fmi)
        self._access = _FMI3_ACCESS if self.fmi == 3 else _FMI2_ACCESS
        self.event_mode = self.fmi == 3 and bool(description.coSimulation.hasEventMode)

        usable = [v for v in self.variables.values() if v.type in self._access
                  and "incomplete" not in v.shape]
        # FMI 3 Clocks (Scheduled Execution and clocked Co-Simulation) are not exchanged
        self.skipped_variables = sorted(
            v.name for v in description.modelVariables
            if v.causality in ("input", "output") and self.fmi == 3 and v.type == "Clock")
        if self.skipped_variables:
            warnings.warn(f"{self.path.name}: Clock variables are not exchanged by the master: "
                          f"{self.skipped_variables}", stacklevel=2)
        self._inputs = self._groups([v for v in usable if v.causality == "input"])
        self._outputs = self._groups([v for v in usable if v.causality == "output"])
        self.input_names = tuple(v.name for g in self._inputs for v in g.variables)
        self._input_slot = {v.name: (g, *g.slices[v.name], v, self._fast_type(v))
                            for g in self._inputs for v in g.variables}
        for group, where, shape, v, _ in self._input_slot.values():
            # inputs not set by the user keep the FMU's start values
            self._store(group, where, self._convert(v, self._start_value(v), "start"))
        self._output_plan = [
            (g, [(v.name, g.slices[v.name][0], v.shape) for v in g.variables])
            for g in self._outputs]
        self.output_types = {v.name: v.type for g in self._outputs for v in g.variables}
        self.output_names = tuple(self.output_types)
        self._latest: dict[str, object] = {}

        self._unzipdir = extract(self.path)
        # the extracted files go even if finish() is never called
        self._cleanup = weakref.finalize(self, shutil.rmtree, self._unzipdir, True)
        try:
            self._instantiate(parameters or {})
        except BaseException:
            self.finish()
            raise

    # ---- validation -----------------------------------------------------------------
    def validate(self, interface) -> None:
        """Raise ``FmuInterfaceError`` listing every spec of ``interface`` not offered."""
        problems = []
        for spec in interface:
            kind = spec.type
            expected = f"{'an' if spec.causality[0] in 'aeiou' else 'a'} {spec.causality} " \
                       f"{kind} variable, {_describe_shape(spec.shape)}"
            if self.fmi == 2 and spec.shape:
                expected += f" ({fmi2_scalar_names(spec.name, spec.shape)[0]} .. " \
                            f"{fmi2_scalar_names(spec.name, spec.shape)[-1]} in FMI 2.0)"
            found = self.variables.get(spec.name)
            if found is None:
                problems.append((spec.name, expected, "missing"))
            elif found.type != spec.type:
                problems.append((spec.name, expected, f"its type is {found.native_type}"))
            elif found.causality != spec.causality:
                problems.append((spec.name, expected, f"its causality is {found.causality!r}"))
            elif tuple(found.shape) != tuple(spec.shape):
                problems.append((spec.name, expected, f"it is {_describe_shape(found.shape)}"))
        if problems:
            raise FmuInterfaceError(self.path.name, problems)

    # ---- set-up ---------------------------------------------------------------------
    def _groups(self, variables) -> list[_Group]:
        by_function: dict[str, list[_Variable]] = {}
        for v in variables:
            by_function.setdefault(self._access[v.type].function, []).append(v)
        return [_Group(self._access[members[0].type], members)
                for members in by_function.values()]

    @staticmethod
    def _fast_type(variable: _Variable):
        """The Python type ``set_input`` stores without conversion (None: always convert)."""
        if variable.type in ("Float32", "Float64"):
            return float if variable.shape == () else np.ndarray
        if variable.type in _INTEGER_RANGES and variable.shape == ():
            variable.low, variable.high = _INTEGER_RANGES[variable.type]
            return int
        return None

    def _start_value(self, variable: _Variable):
        """Start value(s) declared in modelDescription.xml, typed (defaults where none)."""
        default = {"String": "", "Binary": b"", "Boolean": False}.get(variable.type, 0)
        if variable.type == "Enumeration" and variable.items:
            default = min(variable.items)
        starts = variable.start if isinstance(variable.start, list) else [variable.start]
        if self.fmi == 3 and variable.start is not None and variable.type not in ("String",
                                                                                  "Binary"):
            starts = str(variable.start).split()
        values = [self._parse_start(variable.type, s, default) for s in starts]
        if variable.shape == ():
            return values[0]
        if variable.type in ("String", "Binary"):
            return (values * variable.size)[:variable.size] if len(values) == 1 else values
        return np.broadcast_to(np.array(values, dtype=RECORD_DTYPES[variable.type]),
                               (variable.size,)).reshape(variable.shape)

    @staticmethod
    def _parse_start(type_name, text, default):
        if text is None:
            return default
        if type_name in ("Float32", "Float64"):
            return float(text)
        if type_name == "Boolean":
            return str(text).lower() in ("true", "1")
        if type_name == "String":
            return str(text)
        if type_name == "Binary":
            return bytes.fromhex(str(text)) if not isinstance(text, bytes) else text
        return int(text)

    def _logger(self, *args):
        message = args[-1]
        self.log.append(message.decode("utf-8", "replace") if isinstance(message, bytes)
                        else str(message))

    def _instantiate(self, parameters: dict) -> None:
        md = self.description
        common = dict(guid=md.guid, unzipDirectory=self._unzipdir,
                      modelIdentifier=md.coSimulation.modelIdentifier, instanceName=self.name)
        try:
            if self.fmi == 3:
                from fmpy.fmi3 import FMU3Slave
                self.slave = FMU3Slave(**common)
            else:
                from fmpy.fmi2 import FMU2Slave
                self.slave = FMU2Slave(**common)
        except OSError as exc:  # the shared library does not load
            raise ValidationError("fmu", "an FMU whose binary loads on this machine",
                                  f"{self.path}: {exc}") from None
        if self.fmi == 3:
            from fmpy.fmi3 import fmi3Boolean, fmi3Float64

            self._call("instantiate", self.slave.instantiate, logMessage=self._logger,
                       eventModeUsed=self.event_mode, earlyReturnAllowed=self.event_mode)
            self._instantiated = True
            self._call("enterInitializationMode", self.slave.enterInitializationMode, startTime=0.0)
            self._flags = [fmi3Boolean() for _ in range(3)]
            self._last_time = fmi3Float64()
            self._flag_refs = ([ctypes.byref(f) for f in self._flags]
                               + [ctypes.byref(self._last_time)])
            self._do_step = self.slave.fmi3DoStep
        else:
            from fmpy.fmi2 import defaultCallbacks, fmi2CallbackFunctions, fmi2CallbackLoggerTYPE
            from fmpy.logging import addLoggerProxy

            self._callbacks = fmi2CallbackFunctions()
            self._callbacks.logger = fmi2CallbackLoggerTYPE(self._logger)
            self._callbacks.allocateMemory = defaultCallbacks.allocateMemory
            self._callbacks.freeMemory = defaultCallbacks.freeMemory
            addLoggerProxy(ctypes.byref(self._callbacks))
            self._call("instantiate", self.slave.instantiate, callbacks=self._callbacks)
            self._instantiated = True
            self._call("setupExperiment", self.slave.setupExperiment, startTime=0.0)
            self._call("enterInitializationMode", self.slave.enterInitializationMode)
            self._do_step = self.slave.fmi2DoStep
        self._component = self.slave.component
        self._input_calls = [self._bind("set", g) for g in self._inputs]
        self._output_calls = [(self._bind("get", g), g, plan) for g, plan in self._output_plan]
        self._set_parameters(parameters)
        self._write_inputs()
        self._call("exitInitializationMode", self.slave.exitInitializationMode)
        if self.event_mode:  # FMI 3: initialization ends in event mode
            self._event_iteration("initialization")
            self._call("enterStepMode", self.slave.enterStepMode)
        self._read_outputs()

    def _set_parameters(self, parameters: dict) -> None:
        names = sorted(v.name for v in self.variables.values() if v.causality == "parameter")
        for key, value in parameters.items():
            variable = self.variables.get(key)
            if variable is None or variable.causality != "parameter":
                raise ValidationError(f"{self.path.name}: parameter {key!r}",
                                      f"one of {names}", "no such parameter")
            group = _Group(self._access[variable.type], [variable])
            self._store(group, slice(0, variable.size), self._convert(variable, value, "parameter"))
            self._transfer("set", f"set parameter {key}", group)

    # ---- typed values ---------------------------------------------------------------
    def item_name(self, variable: str, value: int) -> str:
        """Name of Enumeration ``variable``'s item ``value``."""
        items = self.variables[variable].items
        if value not in items:
            raise ValidationError(f"{self.name}.{variable}", f"one of {sorted(items)}",
                                  f"got {value!r}")
        return items[value]

    def _convert(self, variable: _Variable, value, role: str):
        """``value`` checked against ``variable``'s type and shape: a flat list or numpy array."""
        where = f"{self.name}.{variable.name}"
        kind = variable.type
        if variable.shape == ():
            values = [value]
        elif kind in ("String", "Binary"):
            values = list(np.asarray(value, dtype=object).ravel()) \
                if np.shape(value) == tuple(variable.shape) else None
            if values is None:
                raise ValidationError(where, _describe_shape(variable.shape),
                                      f"got shape {np.shape(value)}")
        else:
            array = np.asarray(value)
            if array.shape != tuple(variable.shape):
                raise ValidationError(where, _describe_shape(variable.shape),
                                      f"got shape {array.shape}")
            values = array.ravel()
            if kind in ("Float32", "Float64"):
                if array.dtype.kind not in "iuf":
                    raise ValidationError(where, f"{kind} numbers", f"got dtype {array.dtype}")
                return values.astype(np.float64)
            if kind == "Boolean" and array.dtype.kind == "b":
                return values
        if kind == "Binary" and role == "parameter":  # a scenario file gives bytes as hex text
            values = [self._from_hex(where, item) if isinstance(item, str) else item
                      for item in values]
        return [self._check_scalar(where, variable, kind, item) for item in values]

    @staticmethod
    def _from_hex(where: str, text: str) -> bytes:
        try:
            return bytes.fromhex(text)
        except ValueError:
            raise ValidationError(where, "Binary: bytes or a hex string such as '0a0b'",
                                  f"got {text!r}") from None

    @staticmethod
    def _check_scalar(where, variable, kind, item):
        if kind in ("Float32", "Float64"):
            if isinstance(item, (bool, np.bool_)) or not isinstance(item, (int, float, np.integer,
                                                                           np.floating)):
                raise ValidationError(where, f"a {kind} number", f"got {item!r}")
            return float(item)
        if kind == "Boolean":
            if not isinstance(item, (bool, np.bool_)):
                raise ValidationError(where, "a Boolean (True or False)", f"got {item!r}")
            return bool(item)
        if kind == "String":
            if not isinstance(item, str):
                raise ValidationError(where, "a String", f"got {item!r}")
            return item
        if kind == "Binary":
            if not isinstance(item, (bytes, bytearray)):
                raise ValidationError(where, "Binary (bytes)", f"got {item!r}")
            return bytes(item)
        if kind == "Enumeration":
            items = variable.items
            if isinstance(item, str) and item in items.values():
                return next(k for k, n in items.items() if n == item)
            if isinstance(item, (int, np.integer)) and not isinstance(item, (bool, np.bool_)) \
                    and (not items or int(item) in items):
                return int(item)
            raise ValidationError(where, f"one of the items {items} (value or name)",
                                  f"got {item!r}")
        low, high = _INTEGER_RANGES[kind]
        if isinstance(item, (bool, np.bool_)) or not isinstance(item, (int, np.integer)):
            raise ValidationError(where, f"an {kind} integer in {low}..{high}", f"got {item!r}")
        if not low <= int(item) <= high:
            raise ValidationError(where, f"an {kind} integer in {low}..{high}", f"got {item}")
        return int(item)

    def _store(self, group: _Group, where: slice, values) -> None:
        if group.view is not None:
            group.view[where] = values
        elif group.access.function == "String":
            for i, item in zip(range(where.start, where.stop), values):
                group.buffer[i] = item.encode("utf-8")
        else:  # Binary: the FMU reads through pointers into buffers we keep alive
            for i, item in zip(range(where.start, where.stop), values):
                data = ctypes.create_string_buffer(item, max(len(item), 1))
                group.binary_keep[i] = data
                group.buffer[i] = ctypes.cast(data, ctypes.c_void_p)
                group.sizes[i] = len(item)

    # ---- FMI calls ------------------------------------------------------------------
    def _call(self, what: str, function, *args, **kwargs):
        first = len(self.log)
        try:
            return function(*args, **kwargs)
        except FMICallException as exc:
            self._fail(what, first, exc)
        except Exception as exc:  # fmpy raises a bare Exception when instantiation returns NULL
            if what != "instantiate":
                raise
            self._fail(what, first, exc)

    def _fail(self, what: str, first: int, exc: Exception):
        messages = "; ".join(self.log[first:]) or "no log message"
        raise FmuCallError(f"{self.path.name}: {what} failed: {messages} ({exc})") from None

    def _transfer(self, direction: str, what: str, group: _Group) -> None:
        calls = group.calls
        if calls is None:
            calls = group.calls = {d: self._bind(d, group) for d in ("get", "set")}
        function, args = calls[direction]
        self._call(what, function, *args)

    def _bind(self, direction: str, group: _Group):
        """The fmpy function and arguments moving ``group``'s values in ``direction``."""
        function = getattr(self.slave, f"fmi{self.fmi}{direction.title()}{group.access.function}")
        if group.access.function == "Binary":
            args = (self._component, group.refs, group.n_refs, group.sizes,
                    ctypes.cast(group.buffer, ctypes.POINTER(ctypes.POINTER(ctypes.c_uint8))),
                    group.n_values)
        elif self.fmi == 3:
            args = (self._component, group.refs, group.n_refs, group.buffer, group.n_values)
        else:
            args = (self._component, group.refs, group.n_refs, group.buffer)
        return function, args

    def _write_inputs(self) -> None:
        first = len(self.log)
        try:
            for function, args in self._input_calls:
                function(*args)
        except FMICallException as exc:
            self._fail("set inputs", first, exc)

    def _read_outputs(self) -> None:
        latest = {}
        first = len(self.log)
        for (function, args), group, plan in self._output_calls:
            try:
                function(*args)
            except FMICallException as exc:
                self._fail("get outputs", first, exc)
            view = group.view
            if view is not None:
                if group.bool_ints:  # FMI 2 Booleans are C ints
                    view = view != 0
                scalars = view.tolist() if group.has_scalars else None
                for key, where, shape in plan:
                    latest[key] = scalars[where.start] if not shape else \
                        view[where].reshape(shape).copy()
                continue
            if group.access.function == "String":
                items = [b.decode("utf-8", "replace") if b is not None else ""
                         for b in group.buffer]
            else:
                items = [ctypes.string_at(p, n) if p else b""
                         for p, n in zip(group.buffer, group.sizes)]
            for key, where, shape in plan:
                latest[key] = items[where.start] if not shape else \
                    np.array(items[where], dtype=object).reshape(shape)
        self._latest = latest

    def _event_iteration(self, when: str) -> None:
        """``fmi3UpdateDiscreteStates`` until no further update is needed (FMI 3 event mode)."""
        while True:
            (needs_update, terminate, _, _, _, _) = self._call(
                f"updateDiscreteStates ({when})", self.slave.updateDiscreteStates)
            if terminate and self.stop_request is None:
                self.stop_request = StopRequest(self._time, f"{self.path.name} requested to "
                                                "terminate in event mode")
            if not needs_update or terminate:
                return

    # ---- Component ------------------------------------------------------------------
    _time = 0.0

    def set_input(self, name: str, value) -> None:
        slot = self._input_slot.get(name)
        if slot is None:
            raise ValidationError("input", f"one of {list(self.input_names)} of {self.name}",
                                  f"got {name!r}")
        group, where, shape, variable, fast = slot
        kind = type(value)
        # the common cases, kept cheap: a float to a Float, an int to an Int, a float array
        if (fast is float and kind is float) or (
                fast is int and kind is int and variable.low <= value <= variable.high):
            group.view[where.start] = value
            self.inputs[name] = value
            return
        if fast is np.ndarray and kind is np.ndarray and value.shape == shape \
                and value.dtype.kind in "iuf":
            group.view[where] = value.ravel()
            self.inputs[name] = value
            return
        self._store(group, where, self._convert(variable, value, "input"))
        self.inputs[name] = value

    def step(self, t: float, dt: float) -> None:
        if not self._instantiated:
            raise FmuCallError(f"{self.path.name}: step after finish(); load the FMU again")
        self._write_inputs()
        first = len(self.log)
        if self.fmi == 3:
            try:
                self._do_step(self._component, t, dt, True, *self._flag_refs)
            except FMICallException as exc:
                self._fail(f"doStep at t = {t:g} s", first, exc)
            event, terminate, early = self._flags
            if event.value or terminate.value or early.value:
                self._step_rest(t, dt)
            else:
                self._time = t + dt
        else:
            try:
                self._do_step(self._component, t, dt, True)
            except FMICallException as exc:
                if exc.status != FMI2_DISCARD:
                    self._fail(f"doStep at t = {t:g} s", first, exc)
                self._discarded(t, first, exc)
            else:
                self._time = t + dt
        self._read_outputs()

    def _step_rest(self, t: float, dt: float) -> None:
        """FMI 3 doStep returned an event, a stop request or early: finish the step."""
        end = t + dt
        while True:
            event, terminate, early = (f.value for f in self._flags)
            reached = self._last_time.value if (early or terminate) else end
            self._time = reached
            if terminate:
                self.stop_request = StopRequest(
                    reached, f"{self.path.name} requested to terminate the simulation "
                             f"(fmi3DoStep terminateSimulation)")
                return
            if event:
                self._call(f"enterEventMode at t = {reached:g} s", self.slave.enterEventMode)
                self._event_iteration(f"t = {reached:g} s")
                self._call(f"enterStepMode at t = {reached:g} s", self.slave.enterStepMode)
                self.events_handled += 1
                if self.stop_request is not None:
                    return
            if reached >= end or np.isclose(reached, end, rtol=1e-12, atol=0.0):
                self._time = end
                return
            first = len(self.log)
            try:
                self._do_step(self._component, reached, end - reached, True, *self._flag_refs)
            except FMICallException as exc:
                self._fail(f"doStep at t = {reached:g} s", first, exc)

    def _discarded(self, t: float, first: int, exc) -> None:
        """FMI 2 fmi2Discard: a stop request if fmi2Terminated, else an error."""
        try:
            terminated = self.slave.getBooleanStatus(FMI2_TERMINATED)
        except FMICallException:
            terminated = False
        if not terminated:
            self._fail(f"doStep at t = {t:g} s (discarded, and fmi2Terminated is false: the "
                       "master does not retry with a smaller step)", first, exc)
        try:
            reached = self.slave.getRealStatus(FMI2_LAST_SUCCESSFUL_TIME)
        except FMICallException:
            reached = t
        self._time = reached
        self.stop_request = StopRequest(
            reached, f"{self.path.name} requested to terminate the simulation "
                     f"(fmi2DoStep returned fmi2Discard, fmi2Terminated = true)")

    def outputs(self) -> dict[str, object]:
        return self._latest

    def check_input_type(self, name: str, source_type: str, source: str) -> None:
        """Refuse connecting an output of FMI type ``source_type`` to input ``name`` if
        ``set_input`` would refuse its values (called by ``Master.connect``)."""
        variable = self._input_slot[name][3] if name in self._input_slot else None
        if variable is None:
            return
        numbers = set(_INTEGER_RANGES) | {"Enumeration"}
        target = variable.type
        fits = (source_type == target
                or (target in ("Float32", "Float64") and source_type in numbers | {"Float32",
                                                                                   "Float64"})
                or (target in _INTEGER_RANGES and source_type in numbers))
        if not fits:
            article = "an" if target[0] in "AEIO" else "a"
            raise ValidationError(f"connect {source} -> {self.name}.{name}",
                                  f"an output {article} {target} input takes",
                                  f"{source} is {source_type}")

    def record_dtypes(self) -> dict:
        """numpy dtype of each output in the master's time series (its FMI type)."""
        return {name: RECORD_DTYPES[kind] for name, kind in self.output_types.items()}

    def finish(self) -> None:
        """Terminate and free the FMU instance and delete its extracted files (idempotent)."""
        if getattr(self, "_instantiated", False):
            self._instantiated = False
            try:
                self.slave.terminate()
            except Exception:  # a failed FMU may refuse terminate; freeing still matters
                pass
            self.slave.freeInstance()
        if getattr(self, "_cleanup", None):
            self._cleanup()


def describe_fmu(path) -> dict:
    """What ``minetwin fmus info`` shows: model attributes, interfaces, platforms and every
    variable (name, causality, type, shape, unit, start, description, enumeration items)."""
    path = Path(path)
    if not path.is_file():
        raise ValidationError("fmu", "an existing .fmu file", f"{path} does not exist")
    description = read_description(path)
    fmi = 3 if description.fmiVersion == "3.0" else 2
    grouped = (_fmi3_variables if fmi == 3 else _fmi2_variables)(description)
    with zipfile.ZipFile(path) as archive:
        names = archive.namelist()
    platforms = sorted({n.split("/")[1] for n in names
                        if n.startswith("binaries/") and n.count("/") >= 2 and n.split("/")[2]})
    interfaces = [kind for kind, attr in (("Co-Simulation", "coSimulation"),
                                          ("Model Exchange", "modelExchange"),
                                          ("Scheduled Execution", "scheduledExecution"))
                  if getattr(description, attr, None) is not None]
    cs = description.coSimulation
    return {
        "file": str(path), "fmi_version": description.fmiVersion,
        "model_name": description.modelName, "description": description.description or "",
        "generation_tool": description.generationTool or "",
        "generation_date": description.generationDateAndTime or "",
        "interfaces": interfaces, "platforms": platforms,
        "this_platform": _binary_platform(fmi)[0],
        "event_mode": bool(cs is not None and fmi == 3 and cs.hasEventMode),
        "variables": [{"name": v.name, "causality": v.causality, "type": v.type,
                       "native_type": v.native_type,
                       "shape": list(v.shape) if "incomplete" not in v.shape else None,
                       "unit": v.unit, "start": _start_text(v), "description": v.description,
                       "items": {str(k): n for k, n in v.items.items()}}
                      for v in grouped.values()],
    }


def _start_text(variable: _Variable) -> str:
    start = variable.start
    if isinstance(start, str) and variable.shape and variable.type not in ("String", "Binary"):
        start = start.split()  # an FMI 3 array's start values
    if start is None or (isinstance(start, list) and all(s is None for s in start)):
        return ""
    if isinstance(start, list):
        distinct = {str(s) for s in start}
        return distinct.pop() + " (each element)" if len(distinct) == 1 else \
            " ".join(str(s) for s in start)
    return str(start)
