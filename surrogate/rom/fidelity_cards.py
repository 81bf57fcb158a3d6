"""Fidelity cards measured by a held-out evaluation (``cosim.fidelity``).

``surrogate.rom.evaluate.evaluate`` runs FIFO, perfect mixing and the ROM on
held-out scenarios of a DEM design, from the same initial pile with the same
inflow and feeder as a reference DEM run, and a second DEM run whose initial
positions differ by 1e-6 m (the noise floor). Each scenario is one operating
point (its discharge rate and initial held mass, with the range of held mass the
reference DEM pile went through when the summary records it, and the summary's window) and
gives one row of each model's card: the model's tracking error against the
reference DEM, the floor beside it, and the model's wall seconds per
simulated second. The DEM's own row has the floor as its error and the
reference run's wall time as its cost.
"""

from __future__ import annotations

from pathlib import Path

from cosim.errors import ValidationError
from cosim.fidelity import REFERENCE_MODEL, CardRow, FidelityCard

MODELS = ("fifo", "mixing", "rom")

SHIPPED_CARDS = Path(__file__).with_name("data") / "fidelity" / "quick_design_cards.json"
"""The cards measured on the quick design's three held-out scenarios (85-100 t piles,
200-1500 kg/s; ``data/fidelity/quick_design_evaluation.json``), registered as the
``minetwin.fidelity`` entry point ``quick_design``."""

PAPER_CARDS = Path(__file__).with_name("data") / "fidelity" / "paper_heldout_cards.json"
"""The cards measured on the paper-scale held-out design (a 1.47 kt DEM pile of 17,500
disks at 1.2-2 t/s, held mass over its scenes' range; ``data/fidelity/
paper_heldout_evaluation.json``), registered as the ``minetwin.fidelity`` entry point
``paper_heldout``: beside the quick design's, never merged with them
(``cosim.fidelity.cards_at``)."""


def cards_from_evaluation(summary: dict, *, provenance: dict) -> list[FidelityCard]:
    """One card per model (FIFO, mixing, ROM, DEM) from an evaluation summary."""
    try:
        window = float(summary["window_s"])
        scenarios = list(summary["scenarios"].values())
    except (KeyError, TypeError, AttributeError):
        raise ValidationError("summary", "the summary.json of `minetwin rom evaluate` "
                              "(window_s, scenarios)") from None
    rows = {name: [] for name in (*MODELS, REFERENCE_MODEL)}
    for result in scenarios:
        meta = result["scenario"]
        floor = float(result["tracking_error_dem_noise_floor"])
        wall = result["wall_s_per_simulated_s"]
        point = {"throughput_kg_s": float(meta["discharge_rate"]),
                 "held_mass_kg": float(meta["fill"]), "window_s": window,
                 "noise_floor": floor, "scenario": str(meta["name"])}
        if "held_mass_range_kg" in result:  # the mass the DEM pile went through
            low, high = (float(m) for m in result["held_mass_range_kg"])
            point.update(held_mass_min_kg=min(low, point["held_mass_kg"]),
                         held_mass_max_kg=max(high, point["held_mass_kg"]))
        for name in MODELS:
            rows[name].append(CardRow(tracking_error=float(result["tracking_error"][name]),
                                      wall_s_per_s=float(wall[name]), **point))
        rows[REFERENCE_MODEL].append(CardRow(tracking_error=floor,
                                             wall_s_per_s=float(wall[REFERENCE_MODEL]), **point))
    model = {k: v for k, v in summary.get("model", {}).items()
             if k in ("n_mass_modes", "n_velocity_modes", "ridge", "ranges", "n_samples")}
    return [FidelityCard(model=name, rows=tuple(r),
                         provenance={**provenance, **({"rom": model} if name == "rom" else {})})
            for name, r in rows.items()]
