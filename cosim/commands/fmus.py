"""``minetwin fmus``: build the crusher and mill FMUs and validate FMUs."""

from __future__ import annotations

import sys


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "fmus", help="build and validate the crusher and mill FMUs",
        description="Build the C source FMUs in fmus/ (FMI 3.0 and FMI 2.0 Co-Simulation, "
                    "compiled with fmpy's build tooling) and validate FMUs.")
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    build = actions.add_parser(
        "build", help="build fmus/build/<name>.fmu and <name>-fmi2.fmu (skips up-to-date ones)",
        description="Generate modelDescription.xml and compile every model in fmus/ into "
                    "fmus/build/<name>.fmu (FMI 3.0) and fmus/build/<name>-fmi2.fmu (FMI 2.0). "
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
    validate.add_argument("--interface", choices=("auto", "crusher", "mill", "none"),
                          default="auto",
                          help="interface to check (auto: mill if the file name starts with "
                               "'mill', else crusher)")
    validate.set_defaults(handler=run_validate)


def run_build(args) -> int:
    from fmus.build import MODELS, BuildError, build_all

    names = args.model or list(MODELS)
    unknown = [n for n in names if n not in MODELS]
    if unknown:
        print(f"minetwin fmus build: error: --model: must be one of {list(MODELS)} "
              f"(got {unknown})", file=sys.stderr)
        return 2
    try:
        build_all(names, force=args.force, progress=lambda m: print(m, file=sys.stderr))
    except BuildError as exc:
        print(f"minetwin fmus build: error: {exc}", file=sys.stderr)
        return 1
    return 0


def run_validate(args) -> int:
    from pathlib import Path

    from fmpy.validation import validate_fmu

    from cosim.errors import ValidationError
    from cosim.fmu import BUILD_DIR, CRUSHER_INTERFACE, MILL_INTERFACE, FmuCallError, FmuComponent

    paths = [Path(p) for p in args.fmu] or sorted(BUILD_DIR.glob("*.fmu"))
    if not paths:
        print(f"minetwin fmus validate: error: no FMUs in {BUILD_DIR}; run `minetwin fmus build`",
              file=sys.stderr)
        return 2
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        print(f"minetwin fmus validate: error: fmu: no such file {missing}", file=sys.stderr)
        return 2
    failed = 0
    for path in paths:
        choice = args.interface
        if choice == "auto":
            choice = "mill" if path.name.startswith("mill") else "crusher"
        interface = {"crusher": CRUSHER_INTERFACE, "mill": MILL_INTERFACE, "none": ()}[choice]
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
