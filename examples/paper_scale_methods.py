"""Both DEM methods beside FIFO, mixing and the ROM, at the paper's scale.

On the held-out paper-scale scenes (a 17,500-disk, 1.47 kt pile, 180 s at
1.2 and 2 t/s in and out, and 1.5 t/s out with 0.7 t/s in), every model's
tracking error (mean total-variation distance of the 30 s outflow
compositions per 15 t lot, against each explicit DEM replica of the scene,
averaged) is drawn against its compute per simulated second:

- FIFO, perfect mixing and the shipped ROM: the shipped evaluation
  (``surrogate/rom/data/fidelity/paper_heldout_evaluation.json``, wall time of
  each model's run on one core);
- the explicit DEM at its design step (0.16 t_c): its error is its noise
  floor (its replicas against each other), its cost the CPU time of its runs
  (``surrogate/rom/data/paper_heldout/manifest.json``);
- the nonsmooth DEM (11 ms, 100 projected Gauss-Seidel sweeps, Servin et al.
  2014) where its runs of the same scenes finished
  (``surrogate.rom.method_score``; the design ``paper_heldout_nonsmooth``); a
  run the blow-up guard stopped is an X at error 1 at its cost until then, with
  the time it lasted.

DEM costs are CPU seconds: those runs shared a loaded machine, and their wall
time says more about the load than about the method.

Run the nonsmooth design first (about 16 CPU s per simulated second, 45-50 CPU
minutes a scene; resumable)::

    .venv/bin/minetwin rom design --design paper_heldout_nonsmooth --work WORK --workers 1
    .venv/bin/minetwin rom design --design paper_heldout_nonsmooth --work WORK --export --data NS
    .venv/bin/python examples/paper_scale_methods.py --method-data NS --out DIR

Writes ``paper_scale_methods.json`` and ``paper_scale_methods.png`` into
``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from cosim import jsonio
from cosim.errors import ValidationError

ROOT = Path(__file__).resolve().parents[1]
EVALUATION = ROOT / "surrogate" / "rom" / "data" / "fidelity" / "paper_heldout_evaluation.json"
REFERENCE = ROOT / "surrogate" / "rom" / "data" / "paper_heldout"


def points(evaluation: dict, methods: dict) -> dict:
    """Per scene: ``[{"model", "tracking_error", "cost_s_per_s", "cost_kind"}]``."""
    out = {}
    for scene, row in evaluation["scenarios"].items():
        rows = [{"model": name, "tracking_error": row["tracking_error"][name],
                 "cost_s_per_s": row["wall_s_per_simulated_s"][name], "cost_kind": "wall"}
                for name in ("fifo", "mixing", "rom")]
        scored = methods["scenes"].get(scene)
        explicit_cost = methods["explicit_costs"].get(scene)
        rows.append({"model": "dem_explicit", "tracking_error":
                     row["tracking_error_dem_noise_floor"],
                     "cost_s_per_s": (explicit_cost["cpu_s_per_simulated_s"]
                                      if explicit_cost else None), "cost_kind": "cpu"})
        failed = methods["failed"].get(scene)
        if scored is not None:
            rows.append({"model": f"dem_{methods['method']}",
                         "tracking_error": scored["tracking_error"],
                         "spread": scored["tracking_error_spread"],
                         "cost_s_per_s": scored["method_cost"]["cpu_s_per_simulated_s"],
                         "cost_kind": "cpu"})
        elif failed is not None:  # no outflow to score: where and when it blew up
            rows.append({"model": f"dem_{methods['method']}", "tracking_error": None,
                         "blew_up_after_s": failed["after_s"], "reason": failed["reason"],
                         "cost_s_per_s": failed["method_cost"]["cpu_s_per_simulated_s"],
                         "cost_kind": "cpu"})
        out[scene] = rows
    return out


BLOWN_UP_ROW = 1.0
"""Where a run that blew up is drawn (it has no tracking error): error 1, nothing
tracked."""


def plot(result: dict, path: Path) -> None:
    from cosim import plotstyle

    plt = plotstyle.pyplot()
    scenes = list(result["points"])
    fig, axes = plt.subplots(1, len(scenes), figsize=(5 * len(scenes), 4.6), sharey=True,
                             squeeze=False)
    style = {"fifo": ("tab:red", "o", "FIFO"), "mixing": ("tab:orange", "o", "perfect mixing"),
             "rom": ("tab:blue", "o", "ROM (shipped)"),
             "dem_explicit": ("tab:green", "s", "explicit DEM, 0.16 t_c (its noise floor)"),
             "dem_nonsmooth": ("tab:purple", "D", "nonsmooth DEM, 11 ms, 100 sweeps")}
    for ax, scene in zip(axes[0], scenes):
        for p in result["points"][scene]:
            if p["cost_s_per_s"] is None:
                continue
            colour, marker, label = style[p["model"]]
            if p["tracking_error"] is None:
                ax.scatter(p["cost_s_per_s"], BLOWN_UP_ROW, color=colour, marker="x", s=70,
                           zorder=3, label=f"{label}: blew up (cost until then)")
                ax.annotate(f"blew up after {p['blew_up_after_s']:.0f} s",
                            (p["cost_s_per_s"], BLOWN_UP_ROW), textcoords="offset points",
                            xytext=(-6, -12), ha="right", fontsize=7, color=colour)
                continue
            ax.scatter(p["cost_s_per_s"], p["tracking_error"], color=colour, marker=marker,
                       s=50, zorder=3, label=label)
            if "spread" in p:
                ax.vlines(p["cost_s_per_s"], p["spread"]["min"], p["spread"]["max"],
                          color=colour, lw=1,
                          label="range over the explicit replicas")
        ax.axhline(0.10, color="black", ls=":", lw=1, label="target 0.10")
        ax.axvline(1.0, color="grey", ls="-", lw=0.5, label="real time")
        ax.set_ylim(-0.03, BLOWN_UP_ROW + 0.08)
        ax.set_xscale("log")
        ax.set_xlabel("compute per simulated second, one core [s/s]")
        ax.set_title(scene, fontsize=9)
    axes[0, 0].set_ylabel("tracking error against the explicit DEM replicas [-]")
    shown = {}  # every model once, whichever panel drew it
    for ax in axes[0]:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            shown.setdefault(label, handle)
    axes[0, -1].legend(shown.values(), shown.keys(), fontsize=7, loc="center right")
    plotstyle.title(fig, "Paper-scale stockpile: tracking error against compute",
                    "held-out scenes, 30 s windows; DEM: CPU time, storage models: wall "
                    "time on one core")
    fig.tight_layout()
    plotstyle.save(fig, path, dpi=120)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--method-data", type=Path, required=True,
                        help="exported held-out design of another DEM method "
                             "(paper_heldout_nonsmooth)")
    parser.add_argument("--reference", type=Path, default=REFERENCE,
                        help="exported explicit held-out design (default: the shipped one)")
    parser.add_argument("--evaluation", type=Path, default=EVALUATION,
                        help="`minetwin rom evaluate` summary of the shipped ROM on it")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    from surrogate.rom.method_score import score_dem_method

    try:
        methods = score_dem_method(args.method_data, args.reference)
        evaluation = json.loads(args.evaluation.read_text())
    except (ValidationError, OSError) as error:
        print(f"paper_scale_methods: error: {error}", file=sys.stderr)
        return 2
    result = {"methods": methods, "points": points(evaluation, methods),
              "evaluation": str(args.evaluation)}
    args.out.mkdir(parents=True, exist_ok=True)
    jsonio.write(args.out / "paper_scale_methods.json", result, indent=1)
    plot(result, args.out / "paper_scale_methods.png")
    for scene, row in methods["scenes"].items():
        print(f"{scene}: {methods['method']} DEM tracking error {row['tracking_error']:.3f} "
              f"({row['tracking_error_spread']['min']:.3f}-"
              f"{row['tracking_error_spread']['max']:.3f} over "
              f"{row['tracking_error_spread']['n']} explicit replicas), explicit noise floor "
              f"{row['tracking_error_dem_noise_floor']:.3f}; CPU s per simulated s: "
              f"{row['method_cost']['cpu_s_per_simulated_s']:.1f} against the explicit "
              f"DEM's {methods['explicit_costs'][scene]['cpu_s_per_simulated_s']:.1f}; "
              f"discharged {row['discharged_kg'] / 1e3:.0f} t against the explicit "
              f"DEM's {row['explicit_discharged_kg'] / 1e3:.0f} t")
    for scene, row in methods["failed"].items():
        print(f"{scene}: {methods['method']} DEM blew up after {row['after_s']:.1f} s "
              f"({row['reason']}); picture at the failure: {row['picture']}")
    for scene, why in methods["skipped"].items():
        print(f"{scene}: not scored: {why}", file=sys.stderr)
    print(f"wrote {args.out / 'paper_scale_methods.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
