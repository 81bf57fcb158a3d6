"""``minetwin fmus``: build the crusher, mill and test FMUs; validate and describe FMUs."""

from __future__ import annotations

import sys


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "fmus", help="build, validate and describe FMUs",
        description="Build the C source FMUs in fmus/ and the test FMUs in tests/fmus/ "
                    "(FMI 3.0 and FMI 2.0 Co-Simulation, compiled with fmpy's build "
                    "tooling), validate FMUs and list an FMU's variables.")
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    build = actions.add_parser(
        "build", help="build fmus/build/<name>.fmu and <name>-fmi2.fmu (skips up-to-date ones)",
        description="Generate modelDescription.xml and compile every model in fmus/ into "
                    "fmus/build/<name>.fmu (FMI 3.0) and fmus/build/<name>-fmi2.fmu (FMI 2.0), "
                    "and the test models in tests/fmus/ into fmus/build/test/. "
                    "An FMU whose sources did not change is skipped.")
    build.add_argument("--force", action="store_true", help="rebuild even if up to date")
    build.add_argument("--model", action="append", metavar="NAME",
                       help="build only this model (repeatable; default: all)")
    build.set_defaults(handler=run_build)
    validate = actions.add_parser(
        "validate", help="check FMUs with fmpy's validator and against the asset interface",
        description="Run fmpy's validation (modelDescription schema, variables, model "
                    "structure, units) on each FMU and load it through the master's "
                    "FmuComponent, checking the crusher or mill interface. Default: every "
                    "FMU in fmus/build/.")
    validate.add_argument("fmu", nargs="*", help="FMU files (default: fmus/build/*.fmu)")
    validate.add_argument("--interface", metavar="ROLE", default="auto",
                          help="the FMU role whose interface to check (`minetwin fmus roles` "
                               "lists them), 'none', or 'auto' (default: mill if the file "
                               "name starts with 'mill', else crusher)")
    validate.set_defaults(handler=run_validate)
    info = actions.add_parser(
        "info", help="list an FMU's variables (causality, type, unit, start, description)",
        description="Show an FMU's model attributes (FMI version, generation tool and date, "
                    "interfaces, platforms with a binary) and every variable with its "
                    "causality, type, shape, unit, start value and description; an "
                    "Enumeration's items. Reads the archive only (nothing is instantiated).")
    info.add_argument("fmu", help="FMU file")
    info.add_argument("--json", action="store_true", help="print one JSON object instead")
    info.set_defaults(handler=run_info)
    roles = actions.add_parser(
        "roles", help="list the FMU roles and the variables an FMU in each must offer",
        description="List every registered FMU role (MineTwin's crusher and mill, and any "
                    "a package registers under the 'minetwin.fmu_roles' entry points) with "
                    "the variables, causalities, shapes and units its interface requires, "
                    "and the FMU files packages register under 'minetwin.fmus'.")
    roles.add_argument("--json", action="store_true", help="print one JSON object instead")
    roles.set_defaults(handler=run_roles)


def run_build(args) -> int:
    from fmus.build import MODELS, TYPED_MODELS, BuildError, build_all

    names = args.model or list(MODELS + TYPED_MODELS)
    known = list(MODELS + TYPED_MODELS)
    unknown = [n for n in names if n not in known]
    if unknown:
        print(f"minetwin fmus build: error: --model: must be one of {known} "
              f"(got {unknown})", file=sys.stderr)
        return 2
    try:
        build_all([n for n in names if n in MODELS], force=args.force,
                  typed=[n for n in names if n in TYPED_MODELS],
                  progress=lambda m: print(m, file=sys.stderr))
    except BuildError as exc:
        print(f"minetwin fmus build: error: {exc}", file=sys.stderr)
        return 1
    return 0


def run_validate(args) -> int:
    from pathlib import Path

    from fmpy.validation import validate_fmu

    from cosim.errors import ValidationError
    from cosim.fmu import BUILD_DIR, FmuCallError, FmuComponent, check_binary, read_description
    from cosim.fmu_registry import registered_roles, role_interface

    allowed = ["auto", *registered_roles(), "none"]
    if args.interface not in allowed:
        print(f"minetwin fmus validate: error: --interface: must be one of {allowed} "
              f"(got {args.interface!r})", file=sys.stderr)
        return 2

    paths = [Path(p) for p in args.fmu] or sorted(BUILD_DIR.glob("*.fmu"))
    if not paths:
        print(f"minetwin fmus validate: error: no FMUs in {BUILD_DIR}; run `minetwin fmus build`",
              file=sys.stderr)
        return 2
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        print(f"minetwin fmus validate: error: fmu: no such file {missing}", file=sys.stderr)
        return 2
    unreadable = []
    for path in paths:  # broken archives and missing binaries are bad input, one line each
        try:
            description = read_description(path)
            if description.coSimulation is not None:
                check_binary(path, description, 3 if description.fmiVersion == "3.0" else 2)
        except ValidationError as exc:
            unreadable.append(str(exc))
    if unreadable:
        for message in unreadable:
            print(f"minetwin fmus validate: error: {message}", file=sys.stderr)
        return 2
    failed = 0
    for path in paths:
        choice = args.interface
        if choice == "auto":
            choice = "mill" if path.name.startswith("mill") else "crusher"
        try:
            interface = () if choice == "none" else role_interface(choice, "--interface")
        except ValidationError as exc:
            print(f"minetwin fmus validate: error: {exc}", file=sys.stderr)
            return 2
        problems = list(validate_fmu(str(path)))
        if not problems:
            try:
                FmuComponent(path, interface=interface).finish()
            except (ValidationError, FmuCallError) as exc:
                problems.append(str(exc))
        if problems:
            failed += 1
            print(f"FAIL {path}", file=sys.stderr)
            for problem in problems:
                print(f"  {problem}", file=sys.stderr)
        else:
            print(f"ok   {path} ({choice} interface)")
    return 1 if failed else 0


def run_info(args) -> int:
    import json

    from cosim.fmu import describe_fmu

    info = describe_fmu(args.fmu)
    if args.json:
        print(json.dumps(info, indent=1, allow_nan=False))
        return 0
    lines = [f"{info['file']}", f"  FMI version      {info['fmi_version']}",
             f"  model name       {info['model_name']}",
             f"  description      {info['description']}",
             f"  generation tool  {info['generation_tool'] or '-'}",
             f"  generated        {info['generation_date'] or '-'}",
             f"  interfaces       {', '.join(info['interfaces']) or '-'}"
             + ("  (event mode)" if info["event_mode"] else ""),
             f"  platforms        {', '.join(info['platforms']) or '-'}  "
             f"(this machine: {info['this_platform']})", "",
             f"  {'name':<28} {'causality':<11} {'type':<12} {'unit':<8} {'start':<18} "
             "description"]
    for v in info["variables"]:
        shape = "x".join(str(n) for n in v["shape"]) if v["shape"] else ""
        kind = v["type"] + (f"[{shape}]" if shape else "") if v["shape"] is not None \
            else v["type"] + "[incomplete]"
        start = v["start"] if len(v["start"]) <= 18 else v["start"][:15] + "..."
        text = v["description"]
        if v["items"]:
            text += " (" + ", ".join(f"{k} = {n}" for k, n in v["items"].items()) + ")"
        lines.append(f"  {v['name']:<28} {v['causality']:<11} {kind:<12} {v['unit']:<8} "
                     f"{start:<18} {text}")
    print("\n".join(lines))
    return 0


def run_roles(args) -> int:
    import json

    from cosim.errors import ValidationError
    from cosim.fmu_registry import (registered_fmu_path, registered_fmus, registered_roles,
                                    role_interface)

    try:
        roles = {role: [{"name": v.name, "causality": v.causality, "type": v.type,
                         "shape": list(v.shape), "unit": v.unit}
                        for v in role_interface(role)] for role in registered_roles()}
        files = {name: str(registered_fmu_path(name)) for name in registered_fmus()}
    except ValidationError as exc:
        print(f"minetwin fmus roles: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps({"roles": roles, "fmus": files}, indent=1, allow_nan=False))
        return 0
    lines = []
    for role, variables in roles.items():
        lines.append(f"{role}")
        for v in variables:
            shape = "[" + "x".join(str(n) for n in v["shape"]) + "]" if v["shape"] else ""
            lines.append(f"  {v['name']:<24} {v['causality']:<10} {v['type'] + shape:<14} "
                         f"{v['unit']}")
    lines.append("registered FMU files" + ("" if files else ": none"))
    lines.extend(f"  {name:<24} {path}" for name, path in files.items())
    print("\n".join(lines))
    return 0
