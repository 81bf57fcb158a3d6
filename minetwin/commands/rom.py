"""``minetwin rom``: train and evaluate the reduced-order stockpile model."""

from __future__ import annotations

import hashlib
import sys

from cosim import jsonio
from minetwin import executors

PACKINGS = ("avalanche", "column", "loose", "none")
"""``surrogate.rom.storage.PACKINGS``, named here so ``--help`` needs no numba import."""

TRAIN_WORKERS = 2
"""Validation scenes ``rom train`` scores at once by default (the machine's two cores)."""


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "rom", help="train / evaluate the reduced-order stockpile model (ROM) on DEM data",
        description="Reduced-order stockpile model (POD + ridge regression, Wallin and Servin "
                    "2021): train it on a DEM design of experiments and score it against the "
                    "DEM, FIFO and perfect mixing on a held-out scenario.")
    sub = parser.add_subparsers(dest="rom_command", metavar="ACTION")
    train = sub.add_parser("train", help="fit a ROM on a DOE directory and save the model file")
    train.add_argument("--data", required=True, help="DOE directory (train/*.npz, doe.json)")
    train.add_argument("--out", required=True, help="model file to write (.npz)")
    _model_options(train)
    train.add_argument("--rest-fraction", type=float, default=None, metavar="SHARE",
                       help="share of the feeder's mean outlet speed below which a cell of "
                            "the ROM's field rests, kept in the model file (default: fitted "
                            "on the design by Youden's index, surrogate.rom.rest; 0: off)")
    train.add_argument("--dispersivity", type=float, default=None, metavar="M",
                       help="the bulk's random walk [m], kept in the model file (default: "
                            "the DEM's measured dispersivity less what the ROM's own scheme "
                            "shows under the storage options; 0: no walk)")
    train.add_argument("--validation", action="append", default=None, metavar="DIR",
                       help="choose the options left open by the tracking error on the "
                            "scenes of this exported held-out design (e.g. "
                            "surrogate/rom/data/paper_validation; repeat for several; "
                            "surrogate.rom.validation) instead of the leave-one-run-out "
                            "velocity error, among the candidates whose bulk rests on its "
                            "base (--hanging-limit)")
    train.add_argument("--hanging-limit", type=float, default=None, metavar="SHARE",
                       help="with --validation: the largest share [-] of the bulk a candidate "
                            "may leave hanging over emptied cells at a scene's end (default "
                            "0.005, surrogate.rom.hanging; 0-1)")
    train.add_argument("--select-by", choices=("mean", "floor-excess"), default=None,
                       help="with --validation: choose the candidate with the smallest mean "
                            "tracking error over the scenes (mean, the default) or the "
                            "smallest largest excess of a scene's over its DEM noise floor "
                            "(floor-excess; surrogate.rom.validation)")
    train.add_argument("--packing", choices=PACKINGS, default=None,
                       help="the storage's packing the model is chosen under and keeps as "
                            "its default (RomStorage's packing; default: avalanche)")
    train.add_argument("--void-gap", type=float, default=None, metavar="M",
                       help="with --packing loose: the largest void [m] a particle keeps over "
                            "the stack below it, kept as the model's default (default 0.3)")
    train.add_argument("--packing-density", type=float, default=None, metavar="KG_M2",
                       help="areal density [kg/m^2] the storage packs at, kept as the "
                            "model's default (default: its container's)")
    train.add_argument("--landing-spread", type=float, default=None, metavar="M",
                       help="the surface layer's landing spread [m], kept as the model's "
                            "default (default 0: none)")
    train.add_argument("--rom-seeds", type=int, default=None, metavar="N",
                       help="with --validation: ROM seeds 0 .. N-1 per scene (default 2; "
                            "1-100)")
    train.add_argument("--workers", type=int, default=None, metavar="N",
                       help="with --validation: scenes scored at once, in processes of this "
                            "machine (default 2; the model is the same for any N)")
    train.set_defaults(handler=run_train)
    evaluate = sub.add_parser(
        "evaluate", help="score a ROM on the held-out DEM scenario; writes summary.json",
        description="Score FIFO, mixing and the ROM against the DEM on every held-out scenario "
                    "of --data (surrogate/rom/data/paper_heldout: 1.2 and 2 t/s in and out, "
                    "1.5 t/s out with 0.7 t/s in, from a 1.47 kt pile) and print/write "
                    "summary.json: per scenario under 'scenarios', their means (wall times: "
                    "totals) at the top level; --mine and --integration-test add the "
                    "paper-scale mine and the integration test over OPC UA. With --quick: "
                    "build a small DEM design, train and evaluate end to end (a few minutes on "
                    "2 cores).")
    evaluate.add_argument("--model", help="model file (from `minetwin rom train`)")
    evaluate.add_argument("--data", help="DOE directory with held-out runs, or the data folder "
                                         "of an exported held-out design (e.g. "
                                         "surrogate/rom/data/paper_heldout; needs --out)")
    evaluate.add_argument("--quick", action="store_true",
                          help="build a small DOE in --out, train and evaluate")
    evaluate.add_argument("--out", help="output directory for summary.json (and the DOE "
                                        "with --quick); default: --data")
    evaluate.add_argument("--seed", type=int, default=0, help="seed of the design (0)")
    executors.add_options(evaluate, workers=2)
    evaluate.add_argument("--check", action="store_true",
                          help="exit 1 unless every target in summary.json 'targets' is met")
    evaluate.add_argument("--surface", choices=("dem", "rule"), default="dem",
                          help="the ROM's surface layer: resolved DEM impact (default) or the "
                               "sandpile rule alone")
    evaluate.add_argument("--transport", choices=("balanced", "projected", "repack"),
                          default=None,
                          help="the ROM's bulk transport (RomStorage's transport; default: "
                               "the storage's default)")
    evaluate.add_argument("--packing", choices=PACKINGS, default=None,
                          help="the ROM's packing after each move (RomStorage's packing; "
                               "default: the model file's, else avalanche)")
    evaluate.add_argument("--void-gap", type=float, default=None, metavar="M",
                          help="with the loose packing: the largest void [m] a particle "
                               "keeps over the stack below it (RomStorage's void_gap; "
                               "default: the model file's, else 0.3)")
    evaluate.add_argument("--velocity-model", choices=("regressed", "kinematic", "hybrid"),
                          default=None,
                          help="the field the ROM's bulk moves by (RomStorage's "
                               "velocity_model): the model's regression, the kinematic "
                               "funnel flow or the regression sped up to the kinematic "
                               "downward speed where that is faster (default: regressed)")
    evaluate.add_argument("--packing-density", type=float, default=None, metavar="KG_M2",
                          help="areal density [kg/m^2] the ROM packs its bulk at "
                               "(RomStorage's packing_density; default: the model "
                               "file's, else its container's; the DEM's mean settled "
                               "density of a design: python -m surrogate.rom.packing "
                               "--data DIR)")
    evaluate.add_argument("--rest-fraction", type=float, default=None, metavar="SHARE",
                          help="share of the feeder's mean outlet speed below which a cell "
                               "of the ROM's field rests (RomStorage's rest_fraction; default: "
                               "the model file's, fitted at rom train, 0.08 for the shipped "
                               "paper-scale ROM; 0: off)")
    evaluate.add_argument("--landing-spread", type=float, default=None, metavar="M",
                          help="standard deviation [m] of a normal offset to where the "
                               "ROM's surface DEM leaves each particle (RomStorage's "
                               "landing_spread; default: the model file's, else 0: none)")
    evaluate.add_argument("--rom-seeds", type=int, default=1, metavar="N",
                          help="run the ROM with seeds 0 .. N-1 on every scene and score "
                               "the mean over them and the DEM replicas (default 1: seed 0; "
                               "1-100; its surface layer and feeder draw random numbers)")
    evaluate.add_argument("--mine", nargs="?", type=float, const=7200.0, default=None,
                          metavar="S",
                          help="also time the paper-scale mine simulator (examples/"
                               "paper_scale.toml) with this ROM as its stockpile for S "
                               "simulated seconds (default 7200; target: 100x real time on "
                               "one core by CPU time); the result goes to summary.json 'mine'")
    evaluate.add_argument("--integration-test", type=float, default=None, metavar="S",
                          help="also run the paper's integration test (mock 800xA over OPC "
                               "UA, this ROM as the stockpile client, the monitor) at speed "
                               "1 for S seconds into OUT/integration_test (targets: step "
                               "and lag p99 below the exchange cycle, nothing lost or "
                               "duplicated); the result goes to summary.json "
                               "'integration_test'")
    _model_options(evaluate)
    evaluate.set_defaults(handler=run_evaluate)
    design = sub.add_parser(
        "design", help="run (or resume) a DEM design of experiments; stored by content",
        description="Run the DEM design of experiments DESIGN into the work directory --work: "
                    "base piles laid out and settled, then DEM runs under constant discharge "
                    "and inflow, each stored by the hash of its inputs (compact fields on the "
                    "ROM grid and outflow records, float32). A restarted design skips finished "
                    "runs (in --work or in --data) and resumes interrupted ones from their "
                    "latest checkpoint. --plan prints the planned cost; --export copies the "
                    "finished runs into --data (train/*.npz, manifest.json, doe.json).")
    design.add_argument("--design", default="paper",
                        help="paper (default), reduced, paper_heldout (the held-out "
                             "scenes), paper_heldout_nonsmooth (those scenes by the "
                             "nonsmooth DEM, one run each), paper_validation, "
                             "paper_validation_drain and paper_validation_q2000 (scenes "
                             "that hold a pile at 1.6 t/s, drain it and hold it at 2 t/s, "
                             "for choosing among fitted models, rom train "
                             "--validation), paper_validation_q2000_b (2 t/s on a pile "
                             "of its own, likewise), paper_rock and "
                             "paper_rock_inflow (a held-out pile at rock stiffness, "
                             "drained, or fed and drained), paper_rock_nonsmooth and "
                             "paper_rock_inflow_nonsmooth (those by the nonsmooth DEM) "
                             "or reduced_heldout")
    design.add_argument("--work", required=True,
                        help="work directory: checkpoints, states and results")
    design.add_argument("--data", default=None,
                        help="data folder of committed results: finished runs there are "
                             "skipped; --export writes there (default for the paper design: "
                             "the package's surrogate/rom/data/paper_design)")
    executors.add_options(design, workers=2)
    design.add_argument("--set", dest="changes", action="append", default=[],
                        metavar="FIELD=VALUE",
                        help="run the design with this DemConfig field changed, e.g. "
                             "solver_iterations=200 (repeatable; new keys, so its runs sit "
                             "beside the named design's; use its own --work and --data)")
    design.add_argument("--only", action="append", default=[], metavar="RUN",
                        help="run only this run of the design (repeatable; a name from "
                             "--status, e.g. heldout_q2000_r0); --plan, --status and "
                             "--export still cover the whole design")
    design.add_argument("--plan", action="store_true",
                        help="print the runs, their keys and planned particle-steps; run nothing")
    design.add_argument("--rate", type=float, default=None,
                        help="particle-steps per second per worker for --plan's time estimate")
    design.add_argument("--status", action="store_true",
                        help="print each run's state (done, partial: how far, pending); "
                             "run nothing")
    design.add_argument("--export", action="store_true",
                        help="copy the finished runs of --work into --data; run nothing")
    design.add_argument("--with-partial", action="store_true",
                        help="with --export: also copy the latest checkpoint of each "
                             "interrupted run (to resume it where --work is gone)")
    design.set_defaults(handler=run_design)
    parser.set_defaults(handler=lambda args: parser.print_help() or 2)


def _model_options(parser) -> None:
    parser.add_argument("--mass-modes", type=int, default=None,
                        help="POD modes of the mass field (default: chosen by "
                             "leave-one-run-out cross-validation)")
    parser.add_argument("--velocity-modes", type=int, default=None,
                        help="POD modes of the velocity field (default: cross-validated)")
    parser.add_argument("--ridge", type=float, default=None,
                        help="ridge penalty lambda (default: cross-validated)")
    parser.add_argument("--target", choices=("velocity", "flux"), default="velocity",
                        help="field the regression fits: the velocity (default) or the mass "
                             "flux per cell, divided by the cell's mass for the velocity "
                             "(surrogate.rom.model)")
    parser.add_argument("--flux-floor", type=float, default=None,
                        help="with --target flux: least fill of a full cell the flux is "
                             "divided by (default: cross-validated among 0.25, 0.5, 1)")
    parser.add_argument("--fill-law", choices=("dem",), default=None,
                        help="with --target flux: divide the flux by no more than the "
                             "training DEM's fitted fill of a cell carrying it (default: "
                             "off; surrogate.rom.model, 'Fitted fill')")
    parser.add_argument("--registration", choices=("height",), default=None,
                        help="fit the velocity on height-following levels, each column's "
                             "at heights in units of the column's own (default: off, the "
                             "fixed grid; surrogate.rom.model, 'Registered fit')")


def _progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def run_train(args) -> int:
    from cosim.errors import ValidationError
    from surrogate.rom.evaluate import VALIDATION_ROM_SEEDS, train
    from surrogate.rom.hanging import HANGING_LIMIT

    if args.rom_seeds is not None and args.validation is None:
        raise ValidationError("--rom-seeds", "only with --validation")
    if args.hanging_limit is not None and args.validation is None:
        raise ValidationError("--hanging-limit", "only with --validation")
    if args.select_by is not None and args.validation is None:
        raise ValidationError("--select-by", "only with --validation")
    if args.workers is not None and args.validation is None:
        raise ValidationError("--workers", "only with --validation")
    if args.workers is not None and args.workers < 1:
        raise ValidationError("--workers", ">= 1", f"got {args.workers}")
    model = train(args.data, args.out, args.mass_modes, args.velocity_modes, args.ridge,
                  progress=_progress, target=args.target, flux_floor=args.flux_floor,
                  fill_law=args.fill_law, rest_fraction=args.rest_fraction,
                  registration=args.registration, validation=args.validation,
                  storage_options={"packing": args.packing,
                                   "packing_density": args.packing_density,
                                   "landing_spread": args.landing_spread,
                                   "void_gap": args.void_gap},
                  rom_seeds=VALIDATION_ROM_SEEDS if args.rom_seeds is None else args.rom_seeds,
                  dispersivity=args.dispersivity,
                  hanging_limit=(HANGING_LIMIT if args.hanging_limit is None
                                 else args.hanging_limit),
                  select_by=args.select_by or "mean",
                  workers=TRAIN_WORKERS if args.workers is None else args.workers)
    print(f"trained on {model.n_samples} samples, grid {model.grid.nx}x{model.grid.ny}, "
          f"modes {model.n_mass_modes}/{model.n_velocity_modes}, ridge {model.ridge:g}, "
          f"resting share {model.rest_fraction:g}; wrote {args.out}")
    return 0


def run_evaluate(args) -> int:
    from pathlib import Path

    from cosim.errors import ValidationError
    from minetwin import acceptance
    from surrogate.rom import heldout_layout
    from surrogate.rom.evaluate import (build_data, check_rom_seeds, evaluate, train,
                                        write_summary)
    from surrogate.rom.model import RomModel
    from surrogate.rom.storage import RomStorage

    check_rom_seeds(args.rom_seeds)  # before a design is built or laid out
    if args.quick and (args.mine is not None or args.integration_test is not None):
        raise ValidationError("--mine/--integration-test", "with --model and --data (a "
                              "paper-scale ROM), not --quick")
    if args.mine is not None:
        acceptance.check_duration("--mine", args.mine, acceptance.MINE_UNTIL_MAX_S)
    if args.integration_test is not None:
        acceptance.check_duration("--integration-test", args.integration_test,
                                  acceptance.INTEGRATION_TEST_MAX_S)
    rom_options = {"surface": args.surface,
                   **{k: getattr(args, k)
                      for k in ("transport", "packing", "velocity_model", "packing_density",
                                "rest_fraction", "landing_spread", "void_gap")
                      if getattr(args, k) is not None}}
    RomStorage(**rom_options)  # the storage checks its options, here rather than in a worker
    if args.mine is not None and args.model:  # a mine that cannot run here: before the scoring
        acceptance.mine_config(args.model, rom_options)
    if args.quick:
        if not args.out:
            raise ValidationError("--out", "a directory when --quick is given")
        data = Path(args.out)
        with executors.make(args) as executor:
            build_data(data, quick=True, seed=args.seed, progress=_progress, executor=executor)
        model = train(data, data / "rom_model.npz", args.mass_modes, args.velocity_modes,
                      args.ridge, progress=_progress, target=args.target,
                      flux_floor=args.flux_floor, fill_law=args.fill_law,
                      registration=args.registration)
        _progress(f"trained on {model.n_samples} samples; model {data / 'rom_model.npz'}")
    else:
        if not (args.model and args.data):
            raise ValidationError("--model/--data", "both given (or use --quick --out DIR)")
        data = Path(args.data)
        model = RomModel.load(args.model)
        if heldout_layout.is_heldout_data(data):  # a paper-scale held-out design
            if not args.out:
                raise ValidationError("--out", "a directory when --data is a held-out design "
                                      "(its scenes are laid out there for scoring)")
            layout = heldout_layout.write_layout(data, Path(args.out) / "scenes", _progress)
            for scene, reason in layout["skipped"].items():
                _progress(f"held-out scene {scene} left out: {reason}")
            data = Path(args.out) / "scenes"
    with executors.make(args) as executor:  # the held-out scenes are scored in parallel
        summary = evaluate(model, data, progress=_progress,
                           rom_options=rom_options,
                           executor=executor, rom_seeds=args.rom_seeds)
    # the file scored, so that `fidelity calibrate` ties the ROM card to it
    model_file = Path(args.model) if args.model else data / "rom_model.npz"
    summary["model_sha256"] = hashlib.sha256(model_file.read_bytes()).hexdigest()
    check_errors = acceptance.run_from_command_line(
        summary, model_file, args.out or data, mine_until=args.mine,
        integration_duration=args.integration_test, rom_options=rom_options,
        progress=_progress)
    path = write_summary(summary, args.out or data)
    shown = {k: summary[k] for k in ("tracking_error", "tracking_error_dem_noise_floor",
                                     "velocity_field_rel_error",
                                     "velocity_field_rel_error_dem_noise_floor",
                                     "wall_s_per_simulated_s",
                                     "speedup_vs_dem", "grade_error", "hardness_error",
                                     "feed_prediction_error", "targets")}
    shown.update({k: summary[k] for k in ("mine", "integration_test") if k in summary})
    shown["rom_seeds"] = summary["rom_seeds"]
    shown["scenarios"] = {name: {k: s[k] for k in ("tracking_error",
                                                    "tracking_error_spread", "dem_replicas",
                                                    "rom_tracking_error_by_seed",
                                                    "tracking_error_dem_noise_floor",
                                                    "velocity_field_rel_error",
                                                    "velocity_field_rel_error_dem_noise_floor",
                                                    "speedup_vs_dem", "targets")}
                          for name, s in summary["scenarios"].items()}
    print(jsonio.dumps(shown, indent=1))
    print(f"wrote {path}", file=sys.stderr)
    for error in check_errors:
        print(f"minetwin rom evaluate: {error}", file=sys.stderr)
    if check_errors:
        return 1
    rom = summary["tracking_error"]["rom"]
    if rom != rom:
        print("minetwin rom evaluate: the ROM run gave no outflow to score", file=sys.stderr)
        return 1
    if args.check and not all(summary["targets"].values()):
        failed = [name for name, ok in summary["targets"].items() if not ok]
        print(f"minetwin rom evaluate: targets not met: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


def run_design(args) -> int:
    import json
    from pathlib import Path

    from cosim.errors import ValidationError
    from surrogate.rom import paper_design

    from minetwin.commands.dem import setting_changes

    design = paper_design.with_settings(paper_design.get_design(args.design),
                                        setting_changes(args.changes))
    if args.changes and not args.data and design.name == "paper":
        raise ValidationError("--data", "a folder of its own with --set (the package's "
                              "paper_design data holds the named design's runs)")
    if args.workers is not None and args.workers < 1:
        raise ValidationError("--workers", ">= 1", f"got {args.workers}")
    workers = args.default_workers if args.workers is None else args.workers
    data = Path(args.data) if args.data else (paper_design.DATA_DIR if design.name == "paper"
                                              else None)
    if args.plan:
        cost = paper_design.estimate(design)
        plan = paper_design.design_description(design)
        total = sum(cost.values())
        plan["planned_particle_steps_total"] = total
        if args.rate:
            if not args.rate > 0:
                raise ValidationError("--rate", "> 0 particle-steps/s", f"got {args.rate}")
            plan["planned_hours_on_workers"] = total / args.rate / workers / 3600.0
        print(json.dumps(plan, indent=1, allow_nan=False))
        return 0
    if args.status:
        for row in paper_design.status(design, args.work, data):
            detail = {"done": lambda r: f"{(r['result_bytes'] or 0) / 1e6:.2f} MB, wall "
                                        f"{(r['wall_s'] or 0) / 60:.0f} min",
                      "partial": lambda r: f"{r['simulated_s']:.0f}/{r['duration_s']:.0f} s"
                      }.get(row["state"], lambda r: "")(row)
            print(f"{row['name']:<28} {row['key']} {row['state']:<8} {detail}")
        return 0
    if args.export:
        if data is None:
            raise ValidationError("--data", "a folder to export into")
        manifest = paper_design.export(design, args.work, data, with_partial=args.with_partial)
        print(f"exported {manifest['runs_done']} of {manifest['runs_total']} runs "
              f"({manifest['bytes'] / 1e6:.1f} MB) to {data}", file=sys.stderr)
        return 0
    if args.only:
        design = paper_design.only_runs(design, args.only)
    with executors.make(args) as executor:
        manifest = paper_design.run_design(design, args.work, data, executor=executor)
    done = sum(r["status"] == "done" for r in manifest["runs_finished"])
    print(f"design {design.name}: {done} of {len(design.runs)} runs finished in {args.work}",
          file=sys.stderr)
    return 0
