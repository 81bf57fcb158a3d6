"""``minetwin fidelity``: measure storage models' fidelity cards, and choose by them."""

from __future__ import annotations

import sys


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "fidelity", help="fidelity cards: measure them, and pick the cheapest model that "
                         "meets an accuracy",
        description="Each storage model carries a fidelity card: its tracking error against "
                    "the DEM (with the DEM's noise floor) and its cost, measured over operating "
                    "points. `calibrate` measures the cards from a held-out evaluation; "
                    "`choose` picks the cheapest model that meets a tracking-error target (or "
                    "the most accurate within a cost budget) at an operating point.")
    sub = parser.add_subparsers(dest="fidelity_command", metavar="ACTION")
    calibrate = sub.add_parser(
        "calibrate", help="write the cards measured by a `minetwin rom evaluate` summary",
        description="Build the fidelity cards of FIFO, mixing, the ROM and the DEM from the "
                    "summary.json of `minetwin rom evaluate` (one row per held-out scenario) "
                    "and write them, with their provenance, as strict JSON.")
    calibrate.add_argument("--summary", required=True,
                           help="summary.json written by `minetwin rom evaluate`")
    calibrate.add_argument("--model", help="the ROM file that evaluation scored (its SHA-256 "
                                           "goes into the ROM card's provenance; default: "
                                           "the one the summary records)")
    calibrate.add_argument("--out", help="cards file to write (.json; default with --model: "
                                         "the ROM's own, MODEL.cards.json beside it, which a "
                                         "stockpile running that ROM reads)")
    calibrate.set_defaults(handler=run_calibrate)
    choose = sub.add_parser(
        "choose", help="the cheapest model whose card meets a target at an operating point",
        description="Print the model the cards pick at the operating point, why, and the card "
                    "rows compared. Exit 2 if the target cannot be met (below the DEM's noise "
                    "floor, or a budget no model fits).")
    choose.add_argument("--cards", help="cards file (from `calibrate`; default: the "
                        "registered cards, those a model = \"auto\" stockpile uses)")
    choose.add_argument("--throughput", type=float, required=True,
                        help="discharge rate of the scene [kg/s]")
    choose.add_argument("--held-mass", type=float, required=True,
                        help="mass held in the stockpile [kg]")
    choose.add_argument("--window", type=float, default=30.0,
                        help="window of the tracking error [s] (30)")
    target = choose.add_mutually_exclusive_group(required=True)
    target.add_argument("--tracking-error", type=float,
                        help="largest tracking error the scene accepts (fraction, 0..1)")
    target.add_argument("--budget", type=float,
                        help="largest cost the scene affords [wall s per simulated s]")
    choose.add_argument("--plot", metavar="PNG",
                        help="also write the speed-against-accuracy chart of the choice")
    choose.set_defaults(handler=run_choose)
    parser.set_defaults(handler=lambda args: parser.print_help() or 2)


def _provenance(args, summary) -> dict:
    """Where the cards came from; the ROM file is ``--model``, else the one the
    evaluation ``summary`` (already read) records."""
    import datetime
    import hashlib
    import subprocess
    from pathlib import Path

    provenance = {"measured_by": "minetwin fidelity calibrate", "summary": str(args.summary),
                  "summary_sha256": hashlib.sha256(Path(args.summary).read_bytes()).hexdigest(),
                  "date": datetime.datetime.now(datetime.timezone.utc).isoformat(
                      timespec="seconds")}
    if args.model:
        provenance["model_sha256"] = hashlib.sha256(Path(args.model).read_bytes()).hexdigest()
    elif isinstance(summary, dict) and summary.get("model_sha256"):
        provenance["model_sha256"] = summary["model_sha256"]
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                                cwd=Path(__file__).resolve().parent, timeout=10)
        if commit.returncode == 0:
            provenance["commit"] = commit.stdout.strip()
    except OSError:
        pass
    return provenance


def run_calibrate(args) -> int:
    import json
    from pathlib import Path

    from cosim.errors import ValidationError
    from cosim.fidelity import own_cards_file, write_cards
    from surrogate.rom.fidelity_cards import cards_from_evaluation

    if not (args.out or args.model):
        raise ValidationError("--out", "a cards file to write (or --model, whose own cards "
                              "file MODEL.cards.json is then written)", "neither given")
    try:
        summary = json.loads(Path(args.summary).read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise ValidationError("--summary", "a readable summary.json of `minetwin rom evaluate`",
                              str(exc)) from None
    provenance = _provenance(args, summary)
    cards = cards_from_evaluation(summary, provenance=provenance)
    path = write_cards(args.out or own_cards_file(args.model), cards, provenance=provenance)
    for card in cards:
        print(f"{card.model:>7}: " + ", ".join(
            f"{r.scenario} error {r.tracking_error:.3f} (floor {r.noise_floor:.3f}), "
            f"{r.wall_s_per_s:.3g} s/s" for r in card.rows))
    print(f"wrote {path}", file=sys.stderr)
    return 0


def run_choose(args) -> int:
    from cosim.fidelity import OperatingPoint, choose, read_cards, registered_cards

    point = OperatingPoint(throughput_kg_s=args.throughput, held_mass_kg=args.held_mass,
                           window_s=args.window)
    cards = read_cards(args.cards) if args.cards else registered_cards()
    choice = choose(cards, point, tracking_error=args.tracking_error,
                    wall_s_per_s=args.budget, field_name="")
    print(f"{choice.model}: {choice.reason}")
    print(f"{'model':>7} {'holds':>5} {'error':>7} {'floor':>7} {'wall s/s':>10}  rows")
    for c in choice.compared:
        print(f"{c['model']:>7} {str(c['holds']):>5} {c['tracking_error']:7.3f} "
              f"{c['noise_floor']:7.3f} {c['wall_s_per_s']:10.3g}  {', '.join(c['rows'])}")
    if args.plot:
        from cosim.fidelity_plot import plot_fidelity

        print(f"wrote {plot_fidelity(choice.to_json(), args.plot)}", file=sys.stderr)
    return 0
