"""FMUs as co-simulation components: load, validate, parameterise and step any
FMI 2.0 or FMI 3.0 Co-Simulation FMU through fmpy's low-level API.

Source: DESIGN.md sections 4-5 (crusher and mill physics are FMUs the master
steps with fmpy; an FMU missing or mistyping a variable is a clear error at
load) and fmus/README.md (the interface convention).

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
* Arrays: FMI 3.0 array variables, or FMI 2.0 scalars ``x[1]``..``x[16]`` and
  ``x[1,1]``..``x[16,16]`` (1-based, row-major: the Modelica convention). Either
  way ``set_input`` takes and ``outputs`` returns numpy arrays of the declared
  shape (0-based).
* Validation at load against an interface (a tuple of ``VariableSpec``): a
  missing variable, a wrong causality, a non-float type or a wrong array size
  raises ``FmuInterfaceError`` naming the FMU file, the variable and what was
  expected. A failing FMI call (e.g. ``doStep``) raises ``FmuCallError`` with
  the FMU's own log message; inside ``Master.run`` this stops the run and the
  recorded data stays readable.
* Values are float64 only (FMI 2 Real, FMI 3 Float64), which is what the
  crusher/mill convention uses.
"""

from __future__ import annotations

import ctypes
import re
import shutil
import weakref
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cosim.errors import ValidationError
from cosim.master import Component

BUILD_DIR = Path(__file__).resolve().parent.parent / "fmus" / "build"
"""Where ``minetwin fmus build`` writes the FMUs."""


@dataclass(frozen=True)
class VariableSpec:
    """One variable an asset needs from an FMU."""

    name: str
    causality: str  # "parameter", "input" or "output"
    shape: tuple[int, ...] = ()
    unit: str = ""


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
    """The FMU does not offer a variable the asset needs (raised at load)."""


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


def fmi2_scalar_names(name: str, shape) -> list[str]:
    """FMI 2.0 scalar names of a variable, row-major: ``x``, ``x[1]``.., ``x[1,1]``.."""
    if len(shape) == 0:
        return [name]
    if len(shape) == 1:
        return [f"{name}[{i + 1}]" for i in range(shape[0])]
    if len(shape) == 2:
        return [f"{name}[{i + 1},{j + 1}]" for i in range(shape[0]) for j in range(shape[1])]
    raise ValidationError("shape", "at most 2 dimensions", f"{name} has shape {tuple(shape)}")


@dataclass
class _Variable:
    """A (possibly array) float variable of the loaded FMU."""

    name: str
    causality: str
    shape: tuple[int, ...]
    value_references: list[int]  # FMI 3: one per variable; FMI 2: one per element


_FMI2_ELEMENT = re.compile(r"^(?P<base>.+)\[(?P<index>\d+(?:,\d+)*)\]$")


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
        elif v.type == "Real":
            result[v.name] = _Variable(v.name, v.causality, (), [v.valueReference])
    for base, elements in groups.items():
        if base in scalars or any(v.type != "Real" for _, v in elements):
            continue
        ranks = {len(index) for index, _ in elements}
        by_index = {index: v for index, v in elements}
        causalities = {v.causality for v in by_index.values()}
        causality = causalities.pop() if len(causalities) == 1 else "mixed"
        shape = tuple(max(index[d] for index, _ in elements) for d in range(max(ranks)))
        full = [tuple(i + 1 for i in idx) for idx in np.ndindex(*shape)]
        if len(ranks) != 1 or len(by_index) != len(full) or any(i not in by_index for i in full):
            # not a complete array name[1].. : keep what exists so validation can say so
            result[base] = _Variable(base, causality, ("incomplete", len(by_index)), [])
            continue
        result[base] = _Variable(base, causality, shape, [by_index[i].valueReference for i in full])
    return result


def _fmi3_variables(description) -> dict[str, _Variable]:
    return {v.name: _Variable(v.name, v.causality, tuple(v.shape or ()), [v.valueReference])
            for v in description.modelVariables if v.type == "Float64"}


def _describe_shape(shape) -> str:
    if shape and shape[0] == "incomplete":
        return f"an incomplete array of {shape[1]} element(s)"
    return "a scalar" if shape == () else f"an array of shape {tuple(shape)}"


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
        Parameter values set before initialisation (name -> float or array).
    """

    def __init__(self, path, *, interface=(), name: str | None = None,
                 parameters: dict | None = None):
        super().__init__()
        from fmpy import extract, read_model_description

        self.path = Path(path)
        if not self.path.is_file():
            raise ValidationError("fmu", "an existing .fmu file", f"{self.path} does not exist")
        self.name = name or self.path.stem
        self.log: list[str] = []
        try:
            description = read_model_description(str(self.path), validate=False)
        except Exception as exc:
            raise ValidationError("fmu", "a readable FMU (zip with modelDescription.xml)",
                                  f"{self.path}: {exc}") from exc
        if description.coSimulation is None:
            raise ValidationError("fmu", "a Co-Simulation FMU",
                                  f"{self.path.name} has no CoSimulation interface")
        if description.fmiVersion not in ("2.0", "3.0"):
            raise ValidationError("fmu", "FMI 2.0 or 3.0",
                                  f"{self.path.name} is FMI {description.fmiVersion}")
        self.description = description
        self.fmi = 3 if description.fmiVersion == "3.0" else 2
        self.variables = (_fmi3_variables if self.fmi == 3 else _fmi2_variables)(description)
        self._other_types = {_FMI2_ELEMENT.sub(r"\g<base>", v.name): v.type
                             for v in description.modelVariables
                             if v.type not in ("Real", "Float64")}
        self.interface = tuple(interface)
        self.validate(self.interface)

        self._inputs = [v for v in self.variables.values() if v.causality == "input"
                        and "incomplete" not in v.shape]
        self._outputs = [v for v in self.variables.values() if v.causality == "output"
                         and "incomplete" not in v.shape]
        self.input_names = tuple(v.name for v in self._inputs)
        self._input_buffer, self._input_refs, self._input_slices = self._buffers(self._inputs)
        for v in self._inputs:  # inputs not set by the user keep the FMU's start values
            where, shape = self._input_slices[v.name]
            np.frombuffer(self._input_buffer, dtype=np.float64)[where] = self._start_values(v)
        self._output_buffer, self._output_refs, self._output_slices = self._buffers(self._outputs)
        self._scalar_output_names = [k for k, (_, shape) in self._output_slices.items() if not shape]
        self._scalar_output_index = np.array(
            [self._output_slices[k][0].start for k in self._scalar_output_names], dtype=np.intp)
        self._array_outputs = [(k, where, shape) for k, (where, shape) in self._output_slices.items()
                               if shape]
        self._latest: dict[str, object] = {}

        self._unzipdir = extract(str(self.path))
        # the extracted files go even if finish() is never called
        self._cleanup = weakref.finalize(self, shutil.rmtree, self._unzipdir, True)
        try:
            self._instantiate(parameters or {})
        except BaseException:
            self._cleanup()
            raise

    # ---- validation -----------------------------------------------------------------
    def validate(self, interface) -> None:
        """Raise ``FmuInterfaceError`` unless every spec of ``interface`` is offered."""
        for spec in interface:
            expected = f"{'an' if spec.causality[0] in 'aeiou' else 'a'} {spec.causality} " \
                       f"Float64 variable, {_describe_shape(spec.shape)}"
            if self.fmi == 2 and spec.shape:
                expected += f" ({fmi2_scalar_names(spec.name, spec.shape)[0]} .. " \
                            f"{fmi2_scalar_names(spec.name, spec.shape)[-1]} in FMI 2.0)"
            field = f"{self.path.name}: variable {spec.name!r}"
            found = self.variables.get(spec.name)
            if found is None:
                other = self._other_types.get(spec.name)
                raise FmuInterfaceError(field, expected,
                                        f"its type is {other}" if other else "missing")
            if found.causality != spec.causality:
                raise FmuInterfaceError(field, expected, f"its causality is {found.causality!r}")
            if tuple(found.shape) != tuple(spec.shape):
                raise FmuInterfaceError(field, expected, f"it is {_describe_shape(found.shape)}")

    # ---- set-up ---------------------------------------------------------------------
    def _buffers(self, variables):
        size = sum(int(np.prod(v.shape)) for v in variables)
        buffer = (ctypes.c_double * size)()
        refs = []
        slices = {}
        offset = 0
        for v in variables:
            n = int(np.prod(v.shape))
            slices[v.name] = (slice(offset, offset + n), v.shape)
            refs += v.value_references
            offset += n
        ref_array = (ctypes.c_uint32 * len(refs))(*refs)
        return buffer, ref_array, slices

    def _start_values(self, variable: _Variable) -> np.ndarray:
        """Start value(s) declared in modelDescription.xml (0 where none is declared)."""
        if self.fmi == 3:
            declared = {v.name: v for v in self.description.modelVariables}[variable.name]
            text = declared.start if declared.start is not None else "0"
            values = np.array(str(text).split(), dtype=np.float64)
            return np.broadcast_to(values, (int(np.prod(variable.shape)),))
        by_ref = {v.valueReference: v for v in self.description.modelVariables
                  if v.type == "Real"}
        return np.array([float(by_ref[r].start) if by_ref[r].start is not None else 0.0
                         for r in variable.value_references])

    def _logger(self, *args):
        message = args[-1]
        self.log.append(message.decode("utf-8", "replace") if isinstance(message, bytes)
                        else str(message))

    def _instantiate(self, parameters: dict) -> None:
        md = self.description
        common = dict(guid=md.guid, unzipDirectory=self._unzipdir,
                      modelIdentifier=md.coSimulation.modelIdentifier, instanceName=self.name)
        if self.fmi == 3:
            from fmpy.fmi3 import FMU3Slave, fmi3Boolean, fmi3Float64

            self.slave = FMU3Slave(**common)
            self._call("instantiate", self.slave.instantiate, logMessage=self._logger)
            self._call("enterInitializationMode", self.slave.enterInitializationMode, startTime=0.0)
            self._flags = [fmi3Boolean() for _ in range(3)]
            self._last_time = fmi3Float64()
            self._flag_refs = [ctypes.byref(f) for f in self._flags] + [ctypes.byref(self._last_time)]
            self._set_raw = self.slave.fmi3SetFloat64
            self._get_raw = self.slave.fmi3GetFloat64
        else:
            from fmpy.fmi2 import FMU2Slave, defaultCallbacks, fmi2CallbackFunctions, \
                fmi2CallbackLoggerTYPE
            from fmpy.logging import addLoggerProxy

            self.slave = FMU2Slave(**common)
            self._callbacks = fmi2CallbackFunctions()
            self._callbacks.logger = fmi2CallbackLoggerTYPE(self._logger)
            self._callbacks.allocateMemory = defaultCallbacks.allocateMemory
            self._callbacks.freeMemory = defaultCallbacks.freeMemory
            addLoggerProxy(ctypes.byref(self._callbacks))
            self._call("instantiate", self.slave.instantiate, callbacks=self._callbacks)
            self._call("setupExperiment", self.slave.setupExperiment, startTime=0.0)
            self._call("enterInitializationMode", self.slave.enterInitializationMode)
            self._set_raw = self.slave.fmi2SetReal
            self._get_raw = self.slave.fmi2GetReal
        self._instantiated = True
        self._set_parameters(parameters)
        self._write_inputs()
        self._call("exitInitializationMode", self.slave.exitInitializationMode)
        self._read_outputs()

    def _set_parameters(self, parameters: dict) -> None:
        for key, value in parameters.items():
            variable = self.variables.get(key)
            if variable is None or variable.causality != "parameter":
                names = sorted(v.name for v in self.variables.values()
                               if v.causality == "parameter")
                raise ValidationError(f"{self.path.name}: parameter {key!r}",
                                      f"one of {names}", "no such parameter")
            values = self._as_values(key, value, variable.shape)
            refs = (ctypes.c_uint32 * len(variable.value_references))(*variable.value_references)
            array = (ctypes.c_double * values.size)(*values)
            self._call(f"set parameter {key}", self._raw_set, refs, len(variable.value_references),
                       array, values.size)

    def _as_values(self, key: str, value, shape) -> np.ndarray:
        values = np.asarray(value, dtype=np.float64)
        if values.shape != tuple(shape):
            raise ValidationError(f"{self.name}.{key}", _describe_shape(shape),
                                  f"got shape {values.shape}")
        return values.ravel()

    # ---- FMI calls ------------------------------------------------------------------
    def _call(self, what: str, function, *args, **kwargs):
        from fmpy.fmi1 import FMICallException

        first = len(self.log)
        try:
            return function(*args, **kwargs)
        except FMICallException as exc:
            messages = "; ".join(self.log[first:]) or "no log message"
            if what == "doStep":
                what = f"doStep at t = {args[1]:g} s"
            raise FmuCallError(f"{self.path.name}: {what} failed: {messages} ({exc})") from None
        except Exception as exc:  # fmpy raises a bare Exception when instantiation returns NULL
            if what != "instantiate":
                raise
            messages = "; ".join(self.log[first:]) or "no log message"
            raise FmuCallError(f"{self.path.name}: instantiate failed: {messages} ({exc})") from None

    def _raw_set(self, refs, n_refs, values, n_values):
        if self.fmi == 3:
            return self._set_raw(self.slave.component, refs, n_refs, values, n_values)
        return self._set_raw(self.slave.component, refs, n_refs, values)

    def _raw_get(self, refs, n_refs, values, n_values):
        if self.fmi == 3:
            return self._get_raw(self.slave.component, refs, n_refs, values, n_values)
        return self._get_raw(self.slave.component, refs, n_refs, values)

    def _write_inputs(self) -> None:
        if self._inputs:
            self._call("set inputs", self._raw_set, self._input_refs, len(self._input_refs),
                       self._input_buffer, len(self._input_buffer))

    def _read_outputs(self) -> None:
        if self._outputs:
            self._call("get outputs", self._raw_get, self._output_refs, len(self._output_refs),
                       self._output_buffer, len(self._output_buffer))
        values = np.frombuffer(self._output_buffer, dtype=np.float64).copy()
        latest = dict(zip(self._scalar_output_names, values[self._scalar_output_index].tolist()))
        for key, where, shape in self._array_outputs:
            latest[key] = values[where].reshape(shape)
        self._latest = latest

    # ---- Component ------------------------------------------------------------------
    def set_input(self, name: str, value) -> None:
        entry = self._input_slices.get(name)
        if entry is None:
            raise ValidationError("input", f"one of {list(self.input_names)} of {self.name}",
                                  f"got {name!r}")
        where, shape = entry
        values = self._as_values(name, value, shape)
        np.frombuffer(self._input_buffer, dtype=np.float64)[where] = values
        self.inputs[name] = value

    def step(self, t: float, dt: float) -> None:
        if not self._instantiated:
            raise FmuCallError(f"{self.path.name}: step after finish(); load the FMU again")
        self._write_inputs()
        if self.fmi == 3:
            self._call("doStep", self.slave.fmi3DoStep, self.slave.component,
                       t, dt, True, *self._flag_refs)
        else:
            self._call("doStep", self.slave.fmi2DoStep, self.slave.component, t, dt, True)
        self._read_outputs()

    def outputs(self) -> dict[str, object]:
        return self._latest

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
