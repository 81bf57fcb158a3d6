"""Fidelity cards, and the cheapest model that meets a stated accuracy.

"Model no more than a scene needs." Each storage model that can stand in for
another (FIFO, perfect mixing, the ROM, the DEM) carries a *fidelity card*: a
measured table of its error and its cost over operating points. A scenario
states the accuracy it needs (or the cost it can afford), and ``choose``
picks the cheapest model whose card meets it at the scenario's operating
point; ``Ladder`` moves up or down the models during a run when the running
one leaves the range where its card holds.

The error is the stockpile tracking error (``surrogate.rom.metrics``: the
mass-weighted outflow mismatch per tracking id over a moving window, against
the DEM of the same scene), beside the DEM's own noise floor: the same error
between two DEM runs whose initial positions differ by 1e-6 m, which no
model can beat (Wallin and Servin 2021, the ROM's reference, section 4; the
paper's integration test asks for 10 % accuracy). The cost is wall seconds
per simulated second of the model's own calls.

Cards are measured, never typed by hand: ``cards_from_evaluation`` builds
them from the summary of a held-out evaluation (``minetwin rom evaluate``
and ``minetwin fidelity calibrate``), which records where the numbers came
from in each card's ``provenance``.

Rules (all conservative, so that a choice is never better than measured):

- A card *holds* at an operating point when its throughput and held mass lie
  within the range of its rows (a row's held mass is the range the scene's pile
  went through, ``held_mass_min_kg`` to ``held_mass_max_kg``, or its one value).
  The DEM is the reference and holds everywhere.
- Several cards of one model (measured on different designs, say a 100 t and a
  1.5 kt pile) are never merged: the gap between them is unmeasured. At a point
  the model is represented by the card that holds there (by the least favourable
  of them, the largest error, when several do); when none holds, by one that
  does not, so the model is not chosen. Of several reference cards the one whose
  range holds the point gives the noise floor (else the one with the largest).
- The error at a point is the largest error of the rows that bracket it
  (nearest measured value at or below and at or above, in throughput and in
  held mass), at the largest measured window not longer than the asked one
  (a shorter window is the stricter test). With no row in the bracket, the
  largest error of the whole card.
- The cost at a point grows linearly with held mass: ``a + b M`` with
  ``a, b >= 0`` fitted to the card's rows (the DEM and the ROM step every
  held particle).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from cosim.errors import ValidationError, check_finite_range

CARD_FORMAT = "minetwin-fidelity-card/1"
REFERENCE_MODEL = "dem"
"""The model every error is measured against; its card's error is its noise floor."""


@dataclass(frozen=True)
class OperatingPoint:
    """Where a stockpile runs.

    Parameters
    ----------
    throughput_kg_s : float
        Discharge rate [kg/s].
    held_mass_kg : float
        Mass held [kg].
    window_s : float
        Window of the tracking error [s], default 30 (the paper's feed horizon).
    """

    throughput_kg_s: float
    held_mass_kg: float
    window_s: float = 30.0

    def __post_init__(self):
        check_finite_range("operating_point.throughput_kg_s", self.throughput_kg_s, 0.0,
                           unit="kg/s")
        check_finite_range("operating_point.held_mass_kg", self.held_mass_kg, 0.0, unit="kg")
        check_finite_range("operating_point.window_s", self.window_s, 0.0, low_open=True,
                           unit="s")


@dataclass(frozen=True)
class CardRow:
    """One measured operating point of one model.

    ``tracking_error`` and ``noise_floor`` are fractions of the outflow mass
    (0..1); ``wall_s_per_s`` is wall seconds per simulated second;
    ``scenario`` names the run it was measured on.
    """

    throughput_kg_s: float
    held_mass_kg: float
    window_s: float
    tracking_error: float
    noise_floor: float
    wall_s_per_s: float
    scenario: str = ""
    held_mass_min_kg: float | None = None
    held_mass_max_kg: float | None = None

    @property
    def held_mass_range(self) -> tuple[float, float]:
        """The held mass [kg] the row was measured over (its scene's pile)."""
        low = self.held_mass_kg if self.held_mass_min_kg is None else self.held_mass_min_kg
        high = self.held_mass_kg if self.held_mass_max_kg is None else self.held_mass_max_kg
        return low, high


@dataclass(frozen=True)
class FidelityCard:
    """The measured error and cost of ``model`` over operating points."""

    model: str
    rows: tuple[CardRow, ...]
    provenance: dict = field(default_factory=dict)

    def __post_init__(self):
        if not self.rows:
            raise ValidationError(f"card[{self.model}].rows", "at least one measured row")
        for k, row in enumerate(self.rows):
            for name in ("throughput_kg_s", "held_mass_kg", "tracking_error", "noise_floor",
                         "wall_s_per_s"):
                check_finite_range(f"card[{self.model}].rows[{k}].{name}",
                                   getattr(row, name), 0.0)
            check_finite_range(f"card[{self.model}].rows[{k}].window_s", row.window_s, 0.0,
                               low_open=True, unit="s")
            for name in ("held_mass_min_kg", "held_mass_max_kg"):
                if getattr(row, name) is not None:
                    check_finite_range(f"card[{self.model}].rows[{k}].{name}",
                                       getattr(row, name), 0.0, unit="kg")
            low, high = row.held_mass_range
            if not low <= row.held_mass_kg <= high:
                raise ValidationError(f"card[{self.model}].rows[{k}].held_mass_kg",
                                      f"within held_mass_min_kg {low:g} and held_mass_max_kg "
                                      f"{high:g}", f"got {row.held_mass_kg:g}")

    @property
    def is_reference(self) -> bool:
        return self.model == REFERENCE_MODEL

    def holds_at(self, point: OperatingPoint, margin: float = 0.0) -> bool:
        """Whether ``point`` lies in the card's measured range, shrunk by
        ``margin`` (a fraction of each bound) for the hysteresis of a return."""
        return self.is_reference or self.covers(point, margin)

    def covers(self, point: OperatingPoint, margin: float = 0.0) -> bool:
        """Whether ``point`` lies in the range of the card's rows (the reference's
        too), shrunk by ``margin``."""
        throughput = [r.throughput_kg_s for r in self.rows]
        low = min(r.held_mass_range[0] for r in self.rows)
        high = max(r.held_mass_range[1] for r in self.rows)
        return (min(throughput) * (1 + margin) <= point.throughput_kg_s
                <= max(throughput) * (1 - margin)
                and low * (1 + margin) <= point.held_mass_kg <= high * (1 - margin))

    def rows_at(self, point: OperatingPoint) -> list[CardRow]:
        """The rows that bracket ``point`` (module docstring)."""
        windows = sorted({r.window_s for r in self.rows if r.window_s <= point.window_s + 1e-9})
        if not windows:  # the reference stays the best there is, at its largest floor
            return list(self.rows) if self.is_reference else []
        rows = [r for r in self.rows if r.window_s == windows[-1]]
        low_t, high_t = _bracket([r.throughput_kg_s for r in rows], point.throughput_kg_s)
        low_m, high_m = _bracket([r.held_mass_kg for r in rows], point.held_mass_kg)
        inside = [r for r in rows if low_t <= r.throughput_kg_s <= high_t
                  and low_m <= r.held_mass_kg <= high_m]
        return inside or rows

    def error_at(self, point: OperatingPoint) -> float:
        """The tracking error the card certifies at ``point`` (inf: none)."""
        rows = self.rows_at(point)
        if not rows:
            return math.inf
        if self.is_reference:
            return max(r.noise_floor for r in rows)
        return max(r.tracking_error for r in rows)

    def noise_floor_at(self, point: OperatingPoint) -> float:
        rows = self.rows_at(point) or list(self.rows)
        return max(r.noise_floor for r in rows)

    def cost_at(self, point: OperatingPoint) -> float:
        """Wall seconds per simulated second at ``point``'s held mass."""
        from scipy.optimize import nnls

        held = np.array([r.held_mass_kg for r in self.rows])
        cost = np.array([r.wall_s_per_s for r in self.rows])
        design = np.column_stack([np.ones_like(held), held])
        (base, per_kg), _ = nnls(design, cost)
        return float(base + per_kg * point.held_mass_kg)

    def to_json(self) -> dict:
        return {"format": CARD_FORMAT, "model": self.model,
                "rows": [asdict(r) for r in self.rows], "provenance": self.provenance}

    @classmethod
    def from_json(cls, data: dict, field_name: str = "card") -> "FidelityCard":
        if not isinstance(data, dict) or data.get("format") != CARD_FORMAT:
            raise ValidationError(f"{field_name}.format", repr(CARD_FORMAT),
                                  f"got {data.get('format') if isinstance(data, dict) else data!r}")
        try:
            rows = tuple(CardRow(**row) for row in data["rows"])
            return cls(model=str(data["model"]), rows=rows,
                       provenance=dict(data.get("provenance", {})))
        except (KeyError, TypeError) as exc:
            raise ValidationError(field_name, "a fidelity card (model, rows, provenance)",
                                  str(exc)) from None


def _bracket(values: list[float], x: float) -> tuple[float, float]:
    values = sorted(set(values))
    below = [v for v in values if v <= x]
    above = [v for v in values if v >= x]
    low = below[-1] if below else values[0]
    high = above[0] if above else values[-1]
    return low, high


def cards_at(cards: list[FidelityCard], point: OperatingPoint,
             margin: float = 0.0) -> list[FidelityCard]:
    """One card per model at ``point``, in the order the models first appear
    (module docstring: several cards of one model)."""
    by_model: dict[str, list[FidelityCard]] = {}
    for card in cards:
        by_model.setdefault(card.model, []).append(card)
    chosen = []
    for model, group in by_model.items():
        if len(group) == 1:
            chosen.append(group[0])
            continue
        inside = [c for c in group if c.covers(point, margin)]
        if model == REFERENCE_MODEL:
            chosen.append(max(inside or group, key=lambda c: c.noise_floor_at(point)))
        else:
            chosen.append(max(inside, key=lambda c: c.error_at(point)) if inside else group[0])
    return chosen


@dataclass
class Choice:
    """The model ``choose`` picked, why, and the card rows it compared."""

    model: str
    reason: str
    target: dict
    point: OperatingPoint
    compared: list[dict]

    def to_json(self) -> dict:
        return {"model": self.model, "reason": self.reason, "target": self.target,
                "operating_point": asdict(self.point), "compared": self.compared}


def choose(cards: list[FidelityCard], point: OperatingPoint, *,
           tracking_error: float | None = None, wall_s_per_s: float | None = None,
           field_name: str = "stockpile") -> Choice:
    """The cheapest model whose card meets ``tracking_error`` at ``point`` or,
    with a cost budget ``wall_s_per_s`` instead, the most accurate model
    within it. A target below the DEM's noise floor is refused. ``field_name``
    prefixes the fields named in errors (the scenario's table)."""
    field_name = f"{field_name}." if field_name else ""
    cards = cards_at(cards, point)
    if (tracking_error is None) == (wall_s_per_s is None):
        raise ValidationError(f"{field_name}accuracy",
                              "either accuracy.tracking_error or budget.wall_s_per_s",
                              "got both" if tracking_error is not None else "got neither")
    reference = [c for c in cards if c.is_reference]
    if not reference:
        raise ValidationError(f"{field_name}cards", f"a card of the reference model "
                              f"{REFERENCE_MODEL!r}", f"got {[c.model for c in cards]}")
    floor = reference[0].noise_floor_at(point)
    compared = []
    for card in cards:
        error, cost = card.error_at(point), card.cost_at(point)
        compared.append({"model": card.model, "holds": card.holds_at(point),
                         "tracking_error": error, "noise_floor": card.noise_floor_at(point),
                         "wall_s_per_s": cost,
                         "rows": [r.scenario for r in card.rows_at(point)]})
    compared.sort(key=lambda c: c["wall_s_per_s"])
    usable = [c for c in compared if c["holds"] and math.isfinite(c["tracking_error"])]
    if tracking_error is not None:
        target = {"tracking_error": float(tracking_error), "window_s": point.window_s}
        check_finite_range(f"{field_name}accuracy.tracking_error", tracking_error, 0.0, 1.0)
        if tracking_error < floor:
            raise ValidationError(
                f"{field_name}accuracy.tracking_error",
                f">= {floor:.3f}, the DEM's noise floor at {point.throughput_kg_s:g} kg/s and "
                f"{point.held_mass_kg / 1e3:g} t (no model is more accurate than the DEM "
                f"against itself)", f"got {tracking_error:g}")
        meets = [c for c in usable if c["tracking_error"] <= tracking_error]
        best = meets[0]  # the reference always meets a target at or above its floor
        reason = (f"the cheapest model whose measured tracking error "
                  f"({best['tracking_error']:.3f}) is within {tracking_error:g} at "
                  f"{point.window_s:g} s")
    else:
        target = {"wall_s_per_s": float(wall_s_per_s)}
        check_finite_range(f"{field_name}budget.wall_s_per_s", wall_s_per_s, 0.0,
                           low_open=True, unit="s/s")
        within = [c for c in usable if c["wall_s_per_s"] <= wall_s_per_s]
        if not within:
            raise ValidationError(f"{field_name}budget.wall_s_per_s",
                                  f">= {usable[0]['wall_s_per_s']:.3g} s/s, the cost of the "
                                  f"cheapest model ({usable[0]['model']}) here",
                                  f"got {wall_s_per_s:g}")
        best = min(within, key=lambda c: c["tracking_error"])
        reason = (f"the most accurate model (tracking error {best['tracking_error']:.3f}) "
                  f"within {wall_s_per_s:g} wall s per simulated s")
    return Choice(model=best["model"], reason=reason, target=target, point=point,
                  compared=compared)


@dataclass
class Switch:
    """A change of model during a run (a macro-tracking event)."""

    time_s: float
    from_model: str
    to_model: str
    reason: str


class Ladder:
    """Which model runs as the operating point moves during a run.

    The running model hands over *up* (to the cheapest costlier model that
    meets the target) as soon as its card stops holding or it reports an
    input outside its training range; it hands back *down* to a cheaper
    model only when that model's card holds with ``margin`` to spare (a
    fraction of each bound of its range, default 0.1) for ``dwell_s``
    seconds without a break (default 30), so that it does not flap.

    ``target`` is the ``choose`` keyword (``tracking_error=`` or
    ``wall_s_per_s=``).
    """

    def __init__(self, cards: list[FidelityCard], *, margin: float = 0.1, dwell_s: float = 30.0,
                 **target):
        self.cards = list(cards)
        self.margin = float(check_finite_range("ladder.margin", margin, 0.0, 0.5))
        self.dwell_s = float(check_finite_range("ladder.dwell_s", dwell_s, 0.0, unit="s"))
        self.target = target
        self.model: str | None = None
        self.switches: list[Switch] = []
        self._cheaper_since: float | None = None

    def start(self, point: OperatingPoint) -> Choice:
        choice = choose(self.cards, point, **self.target)
        self.model = choice.model
        return choice

    def _choice(self, point, margin, excluded=()) -> str:
        """The model ``choose`` picks among the cards that hold at ``point``; the
        reference when none within a cost budget does (a run goes on)."""
        cards = [c for c in self.cards if c.model not in excluded
                 and (c.is_reference or c.holds_at(point, margin))]
        try:
            return choose(cards, point, **self.target).model
        except ValidationError:
            return REFERENCE_MODEL

    def update(self, t: float, point: OperatingPoint, out_of_range=()) -> Switch | None:
        """The switch due at time ``t`` [s], or None. ``out_of_range``: inputs
        the running model reports outside its training range."""
        here = cards_at(self.cards, point)
        card = next(c for c in here if c.model == self.model)
        if out_of_range or not card.holds_at(point):
            why = (f"inputs outside the training range: {sorted(out_of_range)}" if out_of_range
                   else f"outside the range of its card at {point.throughput_kg_s:g} kg/s, "
                        f"{point.held_mass_kg / 1e3:g} t")
            return self._switch(t, self._choice(point, 0.0, excluded=(self.model,)), why)
        down = self._choice(point, self.margin)
        cost = {c.model: c.cost_at(point) for c in here}
        if cost[down] >= cost[self.model]:
            self._cheaper_since = None
            return None
        if self._cheaper_since is None:
            self._cheaper_since = t
        if t - self._cheaper_since < self.dwell_s:
            return None
        return self._switch(t, down, f"back within the range of its card (by "
                                     f"{self.margin:.0%}) for {self.dwell_s:g} s")

    def _switch(self, t, to_model, reason) -> Switch:
        switch = Switch(float(t), self.model, to_model, reason)
        self.switches.append(switch)
        self.model = to_model
        self._cheaper_since = None
        return switch


CARDS_FORMAT = "minetwin-fidelity-cards/1"


def write_cards(path, cards: list[FidelityCard], *, provenance: dict | None = None):
    """Write ``cards`` to the strict-JSON file ``path`` (with the provenance of
    the calibration that measured them)."""
    from cosim.jsonio import write

    return write(path, {"format": CARDS_FORMAT, "provenance": provenance or {},
                        "cards": [c.to_json() for c in cards]})


def read_cards(path) -> list[FidelityCard]:
    """The cards of a file written by ``write_cards``; a bad file is a
    ``ValidationError`` naming it."""
    import json

    field_name = f"cards file {path}"
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"),
                          parse_constant=lambda c: _refuse_constant(field_name, c))
    except OSError as exc:
        raise ValidationError(field_name, "a readable file", exc.strerror or str(exc)) from None
    except json.JSONDecodeError as exc:
        raise ValidationError(field_name, "strict JSON", str(exc)) from None
    if not isinstance(data, dict) or data.get("format") != CARDS_FORMAT:
        raise ValidationError(f"{field_name}: format", repr(CARDS_FORMAT))
    return [FidelityCard.from_json(c, f"{field_name}: cards[{k}]")
            for k, c in enumerate(data.get("cards", []))]


def own_cards_file(model_file) -> Path:
    """Where a trained model file keeps its own cards: beside it, with the suffix
    ``.cards.json`` (``rom_model.npz`` -> ``rom_model.cards.json``). A stockpile
    that runs that model reads them too; ``minetwin fidelity calibrate --model``
    writes there by default."""

    return Path(model_file).with_suffix(".cards.json")


CARDS_ENTRY_POINT_GROUP = "minetwin.fidelity"
"""Entry points naming a cards file (a ``pathlib.Path`` attribute of a module): the
cards a ``model = "auto"`` stockpile chooses by when its scenario names none."""


def registered_cards() -> list[FidelityCard]:
    """The cards of every registered cards file, in entry-point name order."""
    from cosim.plugins import registered

    cards = []
    for ep in registered(CARDS_ENTRY_POINT_GROUP).values():
        cards += read_cards(ep.load())
    return cards


def _refuse_constant(field_name, constant):
    raise ValidationError(field_name, "strict JSON (no NaN or Infinity)", f"found {constant}")
