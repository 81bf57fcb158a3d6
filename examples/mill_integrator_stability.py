"""Mill integrator stability: size-distribution error against the communication step.

The mill FMU gives the breakage rates, daughter fractions and classifier
escape rates for a mill just filled with 1.8 t of crushed ore (the calibrated
steady hold-up, fmus/README.md). With these operators held, particles of
hardness 1, 1.5 and 2 (100 kg of crushed ore each) are advanced over
``--horizon`` seconds with communication steps from 0.1 ms to 1 s, by the
paper's explicit update and by the default sequential exponential
integrator (cosim/comminution.py). The error is the L1 distance of the class
masses (remaining in the particle, plus escaped) from a fine-step reference
(explicit update with 10 us steps, far inside its stability limit), relative
to the initial mass, the worst over the particles (the floor near 4e-7 at
the smallest steps is the reference's own error). The explicit update
diverges above 2 / max(P/h + Q) = 2 ms (k_esc = 1000/s); the default stays
bounded by the total mass for any step.

Writes ``mill_integrator_stability.png`` and ``mill_integrator_stability.json``
to ``--out``:

    .venv/bin/python examples/mill_integrator_stability.py --out out/mill
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from cosim import jsonio, sizes
from cosim.comminution import apply_fragmentation, mill_step_mass
from cosim.fmu import CRUSHER_INTERFACE, MILL_INTERFACE, FmuComponent, fmu_path

HARDNESS = np.array([1.0, 1.5, 2.0])
PARTICLE_MASS = 100.0  # kg
CHARGE_MASS = 1800.0  # kg, the calibrated steady hold-up at 15 kg/s
ERROR_CAP = 1e6  # errors above this (and inf/nan) are drawn as "diverged"


def mill_operators() -> tuple[np.ndarray, dict]:
    """Crushed-ore size fractions and the mill FMU's operators for a charge of that ore."""
    crusher = FmuComponent(fmu_path("crusher"), interface=CRUSHER_INTERFACE)
    try:
        feed = apply_fragmentation(sizes.swebrec(0.1, 1.0, 2.0),
                                   crusher.outputs()["fragmentation_map"])
    finally:
        crusher.finish()
    mill = FmuComponent(fmu_path("mill"), interface=MILL_INTERFACE)
    try:
        mill.set_input("charge_mass", CHARGE_MASS * feed)
        mill.step(0.0, 1.0)
        return feed, dict(mill.outputs())
    finally:
        mill.finish()


def study(steps, horizon: float = 4.0, fine_step: float = 1e-5, progress=None) -> dict:
    """Error of each method at each communication step [s] against the fine-step reference."""
    feed, ops = mill_operators()
    start = PARTICLE_MASS * np.tile(feed, (HARDNESS.size, 1))
    args = (HARDNESS, ops["breakage_rate"], ops["daughter_fraction"], ops["escape_rate"], horizon)

    def final_state(method, substeps):
        with np.errstate(over="ignore", invalid="ignore"):
            remaining, escaped = mill_step_mass(start, *args, method=method, substeps=substeps)
            # escaped mass keeps its class: the error covers where every kilogram went
            return np.concatenate([remaining, escaped], axis=1)

    reference = final_state("explicit", int(round(horizon / fine_step)))
    result = {"horizon_s": horizon, "fine_step_s": fine_step,
              "stability_limit_s": float(2.0 / np.max(ops["breakage_rate"][None, :] / HARDNESS[:, None]
                                                      + ops["escape_rate"][None, :])),
              "steps_s": [], "exponential": [], "explicit": []}
    for dt in steps:
        n = max(1, int(round(horizon / dt)))
        result["steps_s"].append(horizon / n)
        for method in ("exponential", "explicit"):
            state = final_state(method, n)
            with np.errstate(over="ignore", invalid="ignore"):
                error = np.max(np.abs(state - reference).sum(axis=1)) / PARTICLE_MASS
            result[method].append(float(error) if np.isfinite(error) else None)  # None: overflow
        if progress:
            progress(f"dt = {horizon / n:.2e} s: exponential {result['exponential'][-1]:.2e}, "
                     f"explicit {result['explicit'][-1]:.2e}")
    return result


def plot(result: dict, path: Path) -> None:
    from cosim import plotstyle

    plt = plotstyle.pyplot()
    steps = np.array(result["steps_s"])
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for method, style, label in (("explicit", "o-", "explicit (paper)"),
                                 ("exponential", "s-", "exponential (default)")):
        error = np.array([np.inf if e is None else e for e in result[method]])
        diverged = ~(error <= ERROR_CAP)
        shown = np.where(diverged, ERROR_CAP, error)
        line, = ax.plot(steps, shown, style, label=label)
        if diverged.any():
            ax.plot(steps[diverged], shown[diverged], "x", color=line.get_color(), markersize=10,
                    label=f"{label}: diverged (> {ERROR_CAP:.0e})")
    ax.axvline(result["stability_limit_s"], color="grey", ls="--", lw=1,
               label=f"explicit stability limit {result['stability_limit_s'] * 1e3:.1f} ms")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("communication step dt [s]")
    ax.set_ylabel("size-distribution error, L1 of class masses / mass [-]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    plotstyle.title(fig, f"Mill population balance after {result['horizon_s']:g} s vs "
                    f"fine-step reference ({result['fine_step_s'] * 1e6:.0f} us)",
                    "mill FMU alone (no scenario, no seed: deterministic)")
    fig.tight_layout()
    plotstyle.save(fig, path, dpi=120)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/mill"), help="output directory")
    parser.add_argument("--horizon", type=float, default=4.0, help="simulated time [s] (4)")
    args = parser.parse_args(argv)
    if not args.horizon > 0:
        print("mill_integrator_stability: error: --horizon: must be > 0 s", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    steps = np.logspace(-4, 0, 17)
    result = study(steps, horizon=args.horizon, progress=lambda m: print(m, file=sys.stderr))
    plot(result, args.out / "mill_integrator_stability.png")
    jsonio.write(args.out / "mill_integrator_stability.json", result, indent=1)
    print(jsonio.dumps({"png": str(args.out / "mill_integrator_stability.png"),
                      "stability_limit_s": result["stability_limit_s"],
                      "exponential_max_error": max(result["exponential"]),
                      "explicit_diverged_above_s": min(
                          (dt for dt, e in zip(result["steps_s"], result["explicit"])
                           if e is None or e > 1.0), default=None)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
