"""Generate and build the test FMUs: variables of every FMI type (scalars, 1-D arrays).

The crusher and mill FMUs (fmus/build.py) are all float64; the master must
also take FMUs with integers, Booleans, Strings, Enumerations, Float32 and
FMI 3 Binary, stop requests and events inside a step. Those cases have test
models of our own in ``tests/fmus/<name>/``: ``model.json`` (identifier,
description, whether FMI 3 event mode is offered, enumeration types, every
variable: name, FMI 3 type, causality, start, unit, description, and
``"fmi": [3]`` for FMI 3-only types, ``"shape": [n]`` for a 1-D array of
numbers or Booleans) and ``model.c`` implementing
``tests/fmus/common/typed_model.h``. From these this module generates

* ``variables.h``: the struct ``ModelData`` (one field per variable), the
  table ``VARIABLES`` (value reference, type, causality, field offset) and
  ``set_start_values``,
* ``modelDescription.xml`` for FMI 3.0 and FMI 2.0 (value reference = index
  in model.json + 1, 0 = time; FMI 2 array elements ``name[i]`` get
  1000 * that + i - 1; generation tool and date),

and compiles them with ``tests/fmus/common/fmi3_typed.c`` / ``fmi2_typed.c``
through ``fmus.build.compile_fmu`` into ``fmus/build/test/<name>.fmu`` and
``<name>-fmi2.fmu``. Built by ``minetwin fmus build`` with the other FMUs.
"""

from __future__ import annotations

import hashlib
import json
import tempfile
import uuid
from pathlib import Path
from xml.sax.saxutils import quoteattr

TEST_SOURCE_DIR = Path(__file__).resolve().parent.parent / "tests" / "fmus"
TEST_COMMON_DIR = TEST_SOURCE_DIR / "common"
TEST_BUILD_DIR = Path(__file__).resolve().parent / "build" / "test"

FMI3_ONLY = {"Float32", "Int8", "UInt8", "Int16", "UInt16", "UInt32", "Int64", "UInt64", "Binary"}
_FMI2_ELEMENTS = {"Float64": "Real", "Int32": "Integer", "Boolean": "Boolean", "String": "String",
                  "Enumeration": "Enumeration"}
_C_TYPES = {"Float32": "float", "Float64": "double", "Int8": "int8_t", "UInt8": "uint8_t",
            "Int16": "int16_t", "UInt16": "uint16_t", "Int32": "int32_t", "UInt32": "uint32_t",
            "Int64": "int64_t", "UInt64": "uint64_t"}
_CAUSALITY = {"parameter": "C_PARAMETER", "input": "C_INPUT", "output": "C_OUTPUT"}


def typed_fmu_file(name: str, fmi: int = 3) -> Path:
    """Path of a built test FMU: ``fmus/build/test/<name>.fmu`` or ``<name>-fmi2.fmu``."""
    return TEST_BUILD_DIR / (f"{name}.fmu" if fmi == 3 else f"{name}-fmi2.fmu")


def load_model(name: str) -> dict:
    from fmus.build import TYPED_MODELS, BuildError

    path = TEST_SOURCE_DIR / name / "model.json"
    if not path.is_file():
        raise BuildError(f"{path}: no such test model (known: {', '.join(TYPED_MODELS)})")
    spec = json.loads(path.read_text())
    for vr, variable in enumerate(spec["variables"], start=1):
        variable["vr"] = vr
        variable.setdefault("fmi", [3] if variable["type"] in FMI3_ONLY else [2, 3])
    return spec


def _variables(spec: dict, fmi: int) -> list[dict]:
    return [v for v in spec["variables"] if fmi in v["fmi"]]


def _input_files(name: str) -> list[Path]:
    return [TEST_SOURCE_DIR / name / "model.json", TEST_SOURCE_DIR / name / "model.c",
            TEST_COMMON_DIR / "typed_model.h", TEST_COMMON_DIR / "fmi2_typed.c",
            TEST_COMMON_DIR / "fmi3_typed.c", Path(__file__).resolve()]


def instantiation_token(name: str) -> str:
    """Digest of every file the test FMU is generated from, as ``{uuid}``."""
    digest = hashlib.sha256()
    for path in _input_files(name):
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return "{" + str(uuid.UUID(digest.hexdigest()[:32])) + "}"


def _c_string(text: str) -> str:
    return json.dumps(text)  # a JSON string of ASCII text is a valid C string literal


def _size(v: dict) -> int:
    size = 1
    for extent in v.get("shape", []):
        size *= extent
    return size


def _fmi2_elements(v: dict) -> list[tuple[int, str]]:
    """(value reference, name) of each FMI 2 scalar of an array variable."""
    return [(1000 * v["vr"] + i, f"{v['name']}[{i + 1}]") for i in range(_size(v))]


def _starts(v: dict) -> list:
    start = v["start"]
    return list(start) if isinstance(start, list) else [start] * _size(v)


def _c_start(v: dict, fmi: int) -> str:
    if v.get("shape") and "start" in v:
        return "\n".join(_c_start({**v, "shape": [], "name": f"{v['name']}[{i}]", "start": x}, fmi)
                         for i, x in enumerate(_starts(v)))
    name, kind, start = v["name"], v["type"], v.get("start")
    if kind == "String":
        return f"    strcpy(m->{name}, {_c_string(start or '')});"
    if kind == "Binary":
        data = bytes.fromhex(start or "")
        literal = "".join(f"\\x{b:02x}" for b in data)
        return f'    memcpy(m->{name}, "{literal}", {len(data)}); m->{name}_size = {len(data)};'
    if start is None:
        return ""
    if kind == "Boolean":
        return f"    m->{name} = {1 if start else 0};"
    if kind == "Float32":
        return f"    m->{name} = {float(start)!r}f;"
    if kind == "Float64":
        return f"    m->{name} = {float(start)!r};"
    suffix = "ULL" if kind.startswith("UInt") else ("LL" if kind in ("Int64",
                                                                     "Enumeration") else "")
    return f"    m->{name} = {int(start)}{suffix};"


def variables_header(spec: dict, token: str, fmi: int) -> str:
    """C header: ModelData, the VARIABLES table and set_start_values (index 0 = time)."""
    variables = _variables(spec, fmi)
    boolean, enumeration = ("bool", "int64_t") if fmi == 3 else ("int", "int")
    lines = ["/* Generated by fmus/typed.py from model.json: do not edit. */",
             "#ifndef MINETWIN_TYPED_VARIABLES_H", "#define MINETWIN_TYPED_VARIABLES_H",
             "#include <stdbool.h>", "#include <stddef.h>", "#include <stdint.h>",
             "#include <string.h>",
             f'#define MODEL_IDENTIFIER "{spec["model_identifier"]}"',
             f'#define INSTANTIATION_TOKEN "{token}"', f"#define FMI_VERSION {fmi}",
             f"#define HAS_EVENT_MODE {1 if spec.get('has_event_mode') else 0}",
             "typedef struct {", "    double time;"]
    for v in variables:
        kind = v["type"]
        if kind == "String":
            lines.append(f"    char {v['name']}[STRING_CAPACITY];")
        elif kind == "Binary":
            lines += [f"    unsigned char {v['name']}[BINARY_CAPACITY];",
                      f"    size_t {v['name']}_size;"]
        else:
            ctype = {"Boolean": boolean, "Enumeration": enumeration}.get(kind, _C_TYPES.get(kind))
            size = f"[{_size(v)}]" if v.get("shape") else ""
            lines.append(f"    {ctype} {v['name']}{size};")
    lines += ["} ModelData;", "static const VariableInfo VARIABLES[] = {",
              '    {0, T_FLOAT64, C_INDEPENDENT, offsetof(ModelData, time), 0, 1, "time"},']
    for v in variables:
        size = f"offsetof(ModelData, {v['name']}_size)" if v["type"] == "Binary" else "0"
        head = f"    {{{{{{vr}}, T_{v['type'].upper()}, {_CAUSALITY[v['causality']]}, "
        if v.get("shape") and fmi == 2:  # one scalar per element, name[1]..name[n]
            for i, (vr, name) in enumerate(_fmi2_elements(v)):
                lines.append(head.format(vr=vr) + f"offsetof(ModelData, {v['name']}[{i}]), 0, 1, "
                             f"\"{name}\"}},")
        else:
            lines.append(head.format(vr=v["vr"]) + f"offsetof(ModelData, {v['name']}), {size}, "
                         f"{_size(v)}, \"{v['name']}\"}},")
    lines += ["};", "#define N_VARIABLES (sizeof VARIABLES / sizeof VARIABLES[0])",
              "static inline void set_start_values(ModelData *m) {",
              "    memset(m, 0, sizeof *m);"]
    lines += [line for line in (_c_start(v, fmi) for v in variables) if line]
    lines += ["}", "#endif", ""]
    return "\n".join(lines)


def _generation(spec: dict, token: str) -> str:
    from fmus.build import generation_date

    stamp = generation_date()
    return (f'modelName="{spec["model_identifier"]}" '
            f'description={quoteattr(spec["description"])} generationTool="MineTwin fmus/typed.py" '
            f'generationDateAndTime="{stamp}" variableNamingConvention="structured"')


def _variability(v: dict) -> str:
    if v["causality"] == "parameter":
        return "fixed"
    return "continuous" if v["type"] in ("Float32", "Float64") else "discrete"


def _start_attribute(v: dict) -> str:
    if v["causality"] == "output" or "start" not in v or v["type"] in ("String", "Binary"):
        return ""
    starts = _starts(v) if v.get("shape") else [v["start"]]
    if v["type"] == "Boolean":
        starts = ["true" if x else "false" for x in starts]
    return f' start="{" ".join(str(x) for x in starts)}"'


def _units(variables) -> list[str]:
    units = sorted({v["unit"] for v in variables if v.get("unit")})
    if not units:
        return []
    return (["  <UnitDefinitions>"] + [f'    <Unit name="{u}"/>' for u in units]
            + ["  </UnitDefinitions>"])


def model_description_fmi3(spec: dict, token: str) -> str:
    variables = _variables(spec, 3)
    ident = spec["model_identifier"]
    event = "true" if spec.get("has_event_mode") else "false"
    lines = ['<?xml version="1.0" encoding="UTF-8"?>',
             f'<fmiModelDescription fmiVersion="3.0" {_generation(spec, token)} '
             f'instantiationToken="{token}">',
             f'  <CoSimulation modelIdentifier="{ident}" '
             f'canHandleVariableCommunicationStepSize="true" hasEventMode="{event}"/>',
             *_units(variables)]
    if spec.get("enumerations"):
        lines.append("  <TypeDefinitions>")
        for type_name, items in spec["enumerations"].items():
            lines.append(f'    <EnumerationType name="{type_name}">')
            lines += [f'      <Item name="{item}" value="{k}"/>' for k, item in
                      enumerate(items, start=1)]
            lines.append("    </EnumerationType>")
        lines.append("  </TypeDefinitions>")
    lines += ["  <ModelVariables>",
              '    <Float64 name="time" valueReference="0" causality="independent" '
              'variability="continuous" description="simulation time"/>']
    for v in variables:
        attributes = (f'name="{v["name"]}" valueReference="{v["vr"]}" '
                      f'causality="{v["causality"]}" variability="{_variability(v)}" '
                      f'description={quoteattr(v.get("description", ""))}')
        if v["type"] == "Enumeration":
            attributes += f' declaredType="{v["declared_type"]}"'
        if v.get("unit"):
            attributes += f' unit="{v["unit"]}"'
        attributes += _start_attribute(v)
        if v["type"] in ("String", "Binary") and v["causality"] != "output":
            lines.append(f'    <{v["type"]} {attributes}><Start value="{v.get("start", "")}"/>'
                         f'</{v["type"]}>')
        elif v.get("shape"):
            dims = "".join(f'<Dimension start="{extent}"/>' for extent in v["shape"])
            lines.append(f'    <{v["type"]} {attributes}>{dims}</{v["type"]}>')
        else:
            lines.append(f'    <{v["type"]} {attributes}/>')
    outputs = [v["vr"] for v in variables if v["causality"] == "output"]
    lines += ["  </ModelVariables>", "  <ModelStructure>"]
    lines += [f'    <Output valueReference="{vr}"/>' for vr in outputs]
    lines += [f'    <InitialUnknown valueReference="{vr}"/>' for vr in outputs]
    lines += ["  </ModelStructure>", "</fmiModelDescription>", ""]
    return "\n".join(lines)


def model_description_fmi2(spec: dict, token: str) -> str:
    variables = _variables(spec, 2)
    ident = spec["model_identifier"]
    lines = ['<?xml version="1.0" encoding="UTF-8"?>',
             f'<fmiModelDescription fmiVersion="2.0" {_generation(spec, token)} guid="{token}">',
             f'  <CoSimulation modelIdentifier="{ident}" '
             'canHandleVariableCommunicationStepSize="true">',
             "    <SourceFiles>", '      <File name="model.c"/>',
             '      <File name="fmi2_typed.c"/>',
             "    </SourceFiles>", "  </CoSimulation>", *_units(variables)]
    if spec.get("enumerations"):
        lines.append("  <TypeDefinitions>")
        for type_name, items in spec["enumerations"].items():
            lines += [f'    <SimpleType name="{type_name}">', "      <Enumeration>"]
            lines += [f'        <Item name="{item}" value="{k}"/>' for k, item in
                      enumerate(items, start=1)]
            lines += ["      </Enumeration>", "    </SimpleType>"]
        lines.append("  </TypeDefinitions>")
    lines += ["  <ModelVariables>",
              '    <ScalarVariable name="time" valueReference="0" causality="independent" '
              'variability="continuous" description="simulation time"><Real/></ScalarVariable>']
    outputs = []
    scalars = []
    for v in variables:
        if v.get("shape"):
            scalars += [{**v, "shape": [], "vr": vr, "name": name, "start": x} if "start" in v
                        else {**v, "shape": [], "vr": vr, "name": name}
                        for (vr, name), x in zip(_fmi2_elements(v), _starts(v) if "start" in v
                                                 else [None] * _size(v))]
        else:
            scalars.append(v)
    for index, v in enumerate(scalars, start=2):
        element = _FMI2_ELEMENTS[v["type"]]
        initial = ' initial="exact"' if v["causality"] == "parameter" else ""
        if v["causality"] == "output":
            initial = ' initial="calculated"'
            outputs.append(index)
        typed = ""
        if v["type"] == "Enumeration":
            typed += f' declaredType="{v["declared_type"]}"'
        if v.get("unit"):
            typed += f' unit="{v["unit"]}"'
        if v["causality"] != "output" and "start" in v:
            start = v["start"]
            if v["type"] == "Boolean":
                start = "true" if start else "false"
            typed += f" start={quoteattr(str(start))}"
        lines.append(f'    <ScalarVariable name="{v["name"]}" valueReference="{v["vr"]}" '
                     f'causality="{v["causality"]}" variability="{_variability(v)}"{initial} '
                     f'description={quoteattr(v.get("description", ""))}>'
                     f"<{element}{typed}/></ScalarVariable>")
    lines += ["  </ModelVariables>", "  <ModelStructure>", "    <Outputs>"]
    lines += [f'      <Unknown index="{i}"/>' for i in outputs]
    lines += ["    </Outputs>", "    <InitialUnknowns>"]
    lines += [f'      <Unknown index="{i}"/>' for i in outputs]
    lines += ["    </InitialUnknowns>", "  </ModelStructure>", "</fmiModelDescription>", ""]
    return "\n".join(lines)


def build_description_fmi3(spec: dict) -> str:
    return ('<?xml version="1.0" encoding="UTF-8"?>\n<fmiBuildDescription fmiVersion="3.0">\n'
            f'  <BuildConfiguration modelIdentifier="{spec["model_identifier"]}">\n'
            '    <SourceFileSet language="C99">\n      <SourceFile name="model.c"/>\n'
            '      <SourceFile name="fmi3_typed.c"/>\n    </SourceFileSet>\n'
            "  </BuildConfiguration>\n</fmiBuildDescription>\n")


def build_typed_fmu(name: str, fmi: int = 3, *, force: bool = False) -> tuple[Path, bool]:
    """Build one test FMU; return its path and whether it was (re)built."""
    import shutil

    from fmus.build import compile_fmu, current_token

    spec = load_model(name)
    token = instantiation_token(name)
    target = typed_fmu_file(name, fmi)
    if not force and current_token(target) == token:
        return target, False
    with tempfile.TemporaryDirectory(prefix=f"fmu-{name}-") as tmp:
        root = Path(tmp) / "fmu"
        sources = root / "sources"
        sources.mkdir(parents=True)
        shutil.copy(TEST_SOURCE_DIR / name / "model.c", sources / "model.c")
        shutil.copy(TEST_COMMON_DIR / "typed_model.h", sources / "typed_model.h")
        shutil.copy(TEST_COMMON_DIR / f"fmi{fmi}_typed.c", sources / f"fmi{fmi}_typed.c")
        (sources / "variables.h").write_text(variables_header(spec, token, fmi))
        if fmi == 3:
            (root / "modelDescription.xml").write_text(model_description_fmi3(spec, token))
            (sources / "buildDescription.xml").write_text(build_description_fmi3(spec))
        else:
            (root / "modelDescription.xml").write_text(model_description_fmi2(spec, token))
        compile_fmu(root, target, Path(tmp))
    return target, True
