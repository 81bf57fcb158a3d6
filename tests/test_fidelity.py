"""The choice of the cheapest model that meets a stated accuracy (cosim.fidelity).

The cards here are built in the test to pin the rules (bracketing, conservative
error, noise-floor refusal, hysteresis); measured cards are checked where they are
made (tests of ``minetwin fidelity calibrate``).
"""

from pathlib import Path

import pytest

from cosim.errors import ValidationError
from cosim.fidelity import CardRow, FidelityCard, Ladder, OperatingPoint, choose

FLOOR = 0.04
POINTS = [(200.0, 100e3), (1200.0, 100e3), (1200.0, 2000e3)]


def card(model, errors, costs, window_s=30.0):
    rows = tuple(CardRow(throughput_kg_s=q, held_mass_kg=m, window_s=window_s,
                         tracking_error=FLOOR if model == "dem" else e, noise_floor=FLOOR,
                         wall_s_per_s=c, scenario=f"q{q:g}_m{m:g}")
                 for (q, m), e, c in zip(POINTS, errors, costs))
    return FidelityCard(model=model, rows=rows, provenance={"measured_by": "test"})


CARDS = [card("fifo", [0.45, 0.50, 0.55], [1e-4, 1e-4, 1e-4]),
         card("mixing", [0.30, 0.35, 0.40], [2e-4, 2e-4, 2e-4]),
         card("rom", [0.08, 0.12, 0.09], [5e-3, 5e-3, 2e-2]),
         card("dem", [0, 0, 0], [10.0, 12.0, 150.0])]
SCENE = OperatingPoint(throughput_kg_s=1200.0, held_mass_kg=1500e3)


@pytest.mark.parametrize("target, model", [(0.6, "fifo"), (0.45, "mixing"), (0.12, "rom"),
                                           (0.11, "dem"), (FLOOR, "dem")])
def test_the_cheapest_model_that_meets_the_target_runs(target, model):
    choice = choose(CARDS, SCENE, tracking_error=target)
    assert choice.model == model
    chosen = next(c for c in choice.compared if c["model"] == model)
    assert chosen["tracking_error"] <= target
    cheaper = [c for c in choice.compared if c["wall_s_per_s"] < chosen["wall_s_per_s"]]
    assert all(c["tracking_error"] > target for c in cheaper)


def test_the_error_at_a_point_is_the_worst_of_the_rows_around_it():
    rom = CARDS[2]
    assert rom.error_at(SCENE) == pytest.approx(0.12)  # rows at 1.2 t/s, 0.1 and 2 t held
    assert set(r.scenario for r in rom.rows_at(SCENE)) == {"q1200_m100000", "q1200_m2e+06"}
    assert rom.error_at(OperatingPoint(200.0, 100e3)) == pytest.approx(0.08)  # a measured row


def test_a_shorter_window_than_measured_is_not_certified():
    rom = CARDS[2]
    assert rom.error_at(OperatingPoint(1200.0, 1500e3, window_s=10.0)) == float("inf")
    choice = choose(CARDS, OperatingPoint(1200.0, 1500e3, window_s=10.0), tracking_error=0.2)
    assert choice.model == "dem"


def test_cost_grows_with_held_mass():
    dem = CARDS[3]
    assert dem.cost_at(OperatingPoint(1200.0, 2000e3)) > dem.cost_at(OperatingPoint(1200.0, 100e3))


def test_a_target_below_the_noise_floor_is_refused_naming_the_floor():
    with pytest.raises(ValidationError, match=r"accuracy.tracking_error.*0\.040.*noise floor"):
        choose(CARDS, SCENE, tracking_error=0.01)


def test_a_budget_gets_the_most_accurate_model_it_affords():
    assert choose(CARDS, SCENE, wall_s_per_s=1.0).model == "rom"
    assert choose(CARDS, SCENE, wall_s_per_s=1.5e-4).model == "fifo"
    with pytest.raises(ValidationError, match="budget.wall_s_per_s"):
        choose(CARDS, SCENE, wall_s_per_s=1e-6)


def test_one_kind_of_target_only():
    with pytest.raises(ValidationError, match="either"):
        choose(CARDS, SCENE)
    with pytest.raises(ValidationError, match="either"):
        choose(CARDS, SCENE, tracking_error=0.2, wall_s_per_s=1.0)


def test_outside_its_card_the_model_hands_over_and_returns_with_hysteresis():
    ladder = Ladder(CARDS, tracking_error=0.15, margin=0.1, dwell_s=30.0)
    assert ladder.start(SCENE).model == "rom"
    assert ladder.update(0.0, SCENE) is None
    empty = OperatingPoint(1200.0, 20e3)  # a pile nearly empty: below the ROM's range
    up = ladder.update(1.0, empty)
    assert (up.from_model, up.to_model) == ("rom", "dem") and "range of its card" in up.reason
    edge = OperatingPoint(1200.0, 105e3)  # back in range, but within the 10 % margin
    assert all(ladder.update(t, edge) is None for t in range(2, 100))
    inside = OperatingPoint(1000.0, 1500e3)
    assert ladder.update(100.0, inside) is None  # well inside: the dwell starts
    assert ladder.update(129.0, inside) is None
    down = ladder.update(130.0, inside)
    assert (down.from_model, down.to_model) == ("dem", "rom")
    assert [s.to_model for s in ladder.switches] == ["dem", "rom"]


def test_an_input_outside_the_training_range_hands_over_at_once():
    ladder = Ladder(CARDS, tracking_error=0.15)
    ladder.start(SCENE)
    switch = ladder.update(5.0, SCENE, out_of_range={"mass_distribution_residual"})
    assert switch.to_model == "dem" and "mass_distribution_residual" in switch.reason


def _big_pile_card(model, error, cost, floor=0.10):
    """A card measured on one 1.5 kt pile whose held mass went from 1.3 to 1.5 kt."""
    rows = tuple(CardRow(throughput_kg_s=q, held_mass_kg=1.5e6, window_s=30.0,
                         tracking_error=floor if model == "dem" else error, noise_floor=floor,
                         wall_s_per_s=cost, scenario=f"big_q{q:g}",
                         held_mass_min_kg=1.3e6, held_mass_max_kg=1.5e6)
                 for q in (1200.0, 2000.0))
    return FidelityCard(model=model, rows=rows, provenance={"measured_by": "test"})


BIG = [_big_pile_card("fifo", 0.85, 1e-4), _big_pile_card("mixing", 0.70, 3e-4),
       _big_pile_card("rom", 0.40, 7e-3), _big_pile_card("dem", 0.0, 80.0)]


def test_cards_of_one_model_from_two_designs_are_not_merged():
    """At a point one card per model speaks: the one whose range (held mass as the
    pile went through it) holds the point, the least favourable where two do; in
    the gap beside a design only the DEM does, whatever the target."""
    big_only = OperatingPoint(throughput_kg_s=1500.0, held_mass_kg=1.4e6)  # CARDS: <= 1.2 t/s
    assert choose(CARDS + BIG, big_only, tracking_error=0.75).model == "mixing"
    assert choose(CARDS + BIG, big_only, tracking_error=0.5).model == "rom"
    both = OperatingPoint(throughput_kg_s=1200.0, held_mass_kg=1.45e6)
    # fifo: 0.55 by the small-pile card, 0.85 by the big one; mixing 0.40 and 0.70
    assert choose(CARDS + BIG, both, tracking_error=0.86).model == "fifo"
    assert choose(CARDS + BIG, both, tracking_error=0.8).model == "mixing"
    gap = OperatingPoint(throughput_kg_s=1500.0, held_mass_kg=1.0e6)
    assert choose(BIG, gap, tracking_error=0.9).model == "dem"
    louder = _big_pile_card("dem", 0.0, 80.0, floor=0.2)
    with pytest.raises(ValidationError, match="0.200, the DEM's noise floor"):
        choose(BIG + [louder], big_only, tracking_error=0.15)
    with pytest.raises(ValidationError, match=r"held_mass_kg"):
        FidelityCard(model="rom", rows=(CardRow(1.0, 5.0, 30.0, 0.1, 0.0, 1.0,
                                                held_mass_min_kg=1.0, held_mass_max_kg=2.0),))


def test_cards_round_trip_through_strict_json():
    import json

    from cosim.jsonio import dumps

    for c in CARDS:
        assert FidelityCard.from_json(json.loads(dumps(c.to_json()))) == c
    with pytest.raises(ValidationError, match="format"):
        FidelityCard.from_json({"model": "rom", "rows": []})
    with pytest.raises(ValidationError, match=r"rows\[0\]\.tracking_error"):
        FidelityCard(model="rom", rows=(CardRow(1.0, 1.0, 30.0, float("nan"), 0.0, 1.0),))


SHIPPED = Path(__file__).resolve().parents[1] / "surrogate" / "rom" / "data" / "fidelity"


@pytest.mark.parametrize("design", ["quick_design", "paper_heldout"])
def test_the_shipped_cards_are_what_calibrate_makes_of_the_shipped_evaluation(tmp_path, design):
    """The cards are measured: `minetwin fidelity calibrate` on the committed
    evaluation summary gives the committed cards again, row for row."""
    import hashlib

    from cosim.fidelity import read_cards
    from minetwin.cli import main

    evaluation = SHIPPED / f"{design}_evaluation.json"
    out = tmp_path / "cards.json"
    assert main(["fidelity", "calibrate", "--summary", str(evaluation), "--out", str(out)]) == 0
    shipped = read_cards(SHIPPED / f"{design}_cards.json")
    assert [(c.model, c.rows) for c in read_cards(out)] == [(c.model, c.rows) for c in shipped]
    digest = hashlib.sha256(evaluation.read_bytes()).hexdigest()
    assert all(c.provenance["summary_sha256"] == digest for c in shipped)
    assert [c.model for c in shipped] == ["fifo", "mixing", "rom", "dem"]


def test_the_paper_scale_cards_choose_each_model_at_their_measured_scene(capsys):
    """The paper-scale cards (a 1.5 kt DEM pile at 2 t/s in and out, three DEM
    replicas): a target between two models' measured errors picks the cheaper of
    them that meets it, a target below the DEM's floor is refused naming it. (At
    1.2 t/s the ROM's error is below the DEM's floor, so the scene at 2 t/s, where
    every model is above it, is the one that tells them apart.)"""
    import json

    from minetwin.cli import main

    cards = str(SHIPPED / "paper_heldout_cards.json")
    scenes = json.loads((SHIPPED / "paper_heldout_evaluation.json").read_text())["heldout"]
    row = [s["name"] for s in scenes].index("heldout_q2000")
    scene = scenes[row]
    point = ["fidelity", "choose", "--cards", cards, "--throughput",
             repr(scene["discharge_rate"]), "--held-mass", repr(scene["fill"])]
    errors = {c["model"]: c["rows"][row]["tracking_error"]
              for c in json.loads(Path(cards).read_text())["cards"]}
    assert errors["dem"] < errors["rom"] < errors["mixing"] < errors["fifo"]
    for model, target in (("fifo", errors["fifo"]), ("mixing", errors["mixing"]),
                          ("rom", errors["rom"]), ("dem", 0.5 * (errors["dem"] + errors["rom"]))):
        assert main(point + ["--tracking-error", repr(target)]) == 0
        assert capsys.readouterr().out.startswith(f"{model}: ")
    assert main(point + ["--tracking-error", repr(0.9 * errors["dem"])]) == 2
    assert "noise floor" in capsys.readouterr().err


def test_the_registered_cards_speak_for_the_pile_they_were_measured_on(capsys):
    """Both shipped designs are registered: a 1.4 kt pile is judged by the paper-scale
    cards (its DEM pile went from 1.47 kt down to 1.32 kt), a 90 t pile by the quick
    design's, and a 0.8 kt pile, between them, by none but the DEM's."""
    from cosim.fidelity import cards_at, read_cards, registered_cards
    from minetwin.cli import main

    registered = registered_cards()
    for held_kg, design in ((1.4e6, "paper_heldout"), (90e3, "quick_design")):
        point = OperatingPoint(throughput_kg_s=1500.0, held_mass_kg=held_kg)
        assert cards_at(registered, point) == read_cards(SHIPPED / f"{design}_cards.json")
    assert main(["fidelity", "choose", "--throughput", "1500", "--held-mass", "8e5",
                 "--tracking-error", "0.95"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("dem: ")
    holds = {line.split()[0]: line.split()[1] for line in out[2:]}
    assert holds == {"fifo": "False", "mixing": "False", "rom": "False", "dem": "True"}


def test_choose_on_the_command_line(capsys):
    from minetwin.cli import main

    cards = str(SHIPPED / "quick_design_cards.json")
    scene = ["fidelity", "choose", "--cards", cards, "--throughput", "600", "--held-mass", "90e3"]
    assert main(scene + ["--tracking-error", "0.95"]) == 0
    assert capsys.readouterr().out.startswith("fifo: ")
    assert main(scene + ["--tracking-error", "0.6"]) == 0
    assert capsys.readouterr().out.startswith("mixing: ")
    assert main(scene + ["--tracking-error", "0.01"]) == 2
    assert "noise floor" in capsys.readouterr().err


PLANT = Path(__file__).resolve().parents[1] / "examples" / "cosim_tests" / "plant.toml"


def _auto_plant(tmp_path, stockpile: dict):
    from cosim.tomlfile import read_toml

    raw = read_toml(PLANT, "scenario")
    table = raw["assets"]["stockpile"]
    table.update({"model": "auto", **stockpile})
    table["initial_fill"] = {"mass_kg": 90e3, "trucks": "trucks", "crusher": "crusher"}
    return raw


@pytest.mark.parametrize("target, model", [(0.95, "fifo"), (0.6, "mixing"), (0.3, "dem")])
def test_an_auto_stockpile_runs_the_cheapest_model_its_cards_allow(tmp_path, target, model,
                                                                   capsys):
    """The plant's stockpile (90 t, 400 kg/s) with the registered cards: the quick
    design's ROM card needs the ROM file it was measured on, which this scene does not
    give; the paper-scale ROM card is the default ROM's but holds only at 1.3-1.5 kt;
    so a target between the mixing and the DEM errors gets the DEM."""
    from cosim.scenario import build, summarize

    simulation = build(_auto_plant(tmp_path, {"accuracy": {"tracking_error": target}}))
    try:
        choice = simulation.assets["stockpile"].fidelity
        assert choice["model"] == model
        assert simulation.assets["stockpile"].model.name == model
        assert f"model auto -> {model}" in capsys.readouterr().err
        summary = summarize(simulation)
        assert summary["storage_model"] == model
        assert summary["fidelity"]["stockpile"]["target"] == {"tracking_error": target,
                                                              "window_s": 30.0}
        rows = {c["model"]: c for c in choice["compared"]}
        assert rows[model]["tracking_error"] <= target
        assert rows["rom"]["holds"] is False
        assert set(rows["rom"]["rows"]) <= {"heldout_q1200", "heldout_q2000",
                                            "heldout_out1500_in700"}
    finally:
        simulation.close()


def test_a_rom_card_counts_for_a_stockpile_that_runs_the_default_rom(tmp_path):
    """The paper-scale cards' ROM card was measured on the shipped default ROM: a
    stockpile that names no ROM file runs that ROM, so the card is compared (it
    does not hold at this 90 t, 400 kg/s scene, so the DEM is chosen)."""
    from cosim.scenario import build

    cards = str(SHIPPED / "paper_heldout_cards.json")
    simulation = build(_auto_plant(tmp_path, {"accuracy": {"tracking_error": 0.5},
                                              "cards": cards}))
    try:
        rows = {c["model"]: c for c in simulation.assets["stockpile"].fidelity["compared"]}
        assert rows["rom"]["holds"] is False and rows["rom"]["rows"] == ["heldout_q1200"]
        assert simulation.assets["stockpile"].fidelity["model"] == "dem"
    finally:
        simulation.close()


def test_a_trained_rom_carries_its_own_card(tmp_path, capsys):
    """`fidelity calibrate --model M` writes M.cards.json beside the ROM file; an auto
    stockpile that runs that ROM reads it with no `cards` named, and its card (here
    measured, as a test stand-in, at this 90 t, 400 kg/s scene) is the one that
    speaks for the ROM."""
    import json
    import shutil

    from cosim.fidelity import own_cards_file, read_cards
    from cosim.scenario import build
    from minetwin.cli import main

    rom = tmp_path / "my_rom.npz"
    shutil.copyfile(SHIPPED.parent / "paper_rom.npz", rom)
    summary = json.loads((SHIPPED / "quick_design_evaluation.json").read_text())
    for scene in summary["scenarios"].values():  # rows that cover the plant's scene
        scene["scenario"].update(discharge_rate=400.0, fill=90e3)
        scene["tracking_error"]["rom"] = 0.05 + scene["tracking_error_dem_noise_floor"]
    evaluation = tmp_path / "summary.json"
    evaluation.write_text(json.dumps(summary))
    assert main(["fidelity", "calibrate", "--summary", str(evaluation),
                 "--model", str(rom)]) == 0
    assert f"wrote {own_cards_file(rom)}" in capsys.readouterr().err
    own_rom = next(c for c in read_cards(own_cards_file(rom)) if c.model == "rom")
    simulation = build(_auto_plant(tmp_path, {"accuracy": {"tracking_error": 0.5},
                                              "options": {"model": str(rom)}}))
    try:
        choice = simulation.assets["stockpile"].fidelity
        rows = {c["model"]: c for c in choice["compared"]}
        assert choice["model"] == "rom" and rows["rom"]["holds"] is True
        assert rows["rom"]["tracking_error"] == max(r.tracking_error for r in own_rom.rows)
    finally:
        simulation.close()
    assert main(["fidelity", "calibrate", "--summary", str(evaluation)]) == 2
    assert "--out" in capsys.readouterr().err


def test_an_auto_stockpile_below_the_noise_floor_is_refused_on_the_command_line(tmp_path,
                                                                               capsys):
    from minetwin.cli import main

    scenario = tmp_path / "plant.toml"
    text = PLANT.read_text().replace(
        'model = "fifo"', 'model = "auto"\naccuracy = { tracking_error = 0.05 }', 1)
    text += ('\n[assets.stockpile.initial_fill]\nmass_kg = 90e3\ntrucks = "trucks"\n'
             'crusher = "crusher"\n')
    scenario.write_text(text)
    assert main(["simulate", str(scenario), "--until", "5", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "assets.stockpile.accuracy.tracking_error" in err and "noise floor" in err


def test_accuracy_only_with_auto_and_auto_needs_one_target(tmp_path):
    from cosim.scenario import build

    with pytest.raises(ValidationError, match="accuracy"):
        build(_auto_plant(tmp_path, {"model": "fifo", "accuracy": {"tracking_error": 0.5}}))
    with pytest.raises(ValidationError, match="accuracy"):
        build(_auto_plant(tmp_path, {}))


def test_the_mill_integrator_auto_keeps_the_exponential_where_the_explicit_is_unsafe():
    """The plant's mill classifies fines at k_esc = 1000/s: the explicit update's
    limit is about 1 ms, far below the 0.5 s step, so ``integrator = "auto"`` runs
    the exponential integrator, bit for bit; a bad name is refused at load."""
    from cosim.comminution import explicit_step_limit
    from cosim.scenario import run_scenario
    from cosim.tomlfile import read_toml

    runs = {}
    for integrator in ("exponential", "auto"):
        raw = read_toml(PLANT, "scenario")
        raw["assets"]["mill"]["integrator"] = integrator
        simulation, _ = run_scenario(raw, until=200.0)
        runs[integrator] = simulation.timeseries["mill.mass_kg"].to_numpy()
        mill_fmu = simulation.master.components[[c.name for c in
                                                 simulation.master.components].index("mill_fmu")]
    assert runs["auto"].max() > 0 and (runs["auto"] == runs["exponential"]).all()
    outputs = mill_fmu.outputs()
    assert explicit_step_limit(1.0, outputs["breakage_rate"], outputs["escape_rate"]) < 0.01
    raw["assets"]["mill"]["integrator"] = "implicit"
    with pytest.raises(ValidationError, match="assets.mill.integrator"):
        run_scenario(raw, until=1.0)


def test_an_auto_stockpile_hands_over_up_the_ladder_when_its_card_stops_holding(tmp_path):
    """The plant's pile (90 t at the start, fed faster than the feeder draws) runs
    FIFO while FIFO's card holds (80-120 t here) and hands over to mixing when the
    pile grows past it: a "switch" event with the whole pile, the model's rung in
    the time series, the switch in summary.json, and the mass balance exact."""
    import sqlite3

    from cosim.fidelity import write_cards
    from cosim.scenario import run_scenario

    def rows(error, cost, masses):
        return tuple(CardRow(q, m, 30.0, error, FLOOR, cost, f"q{q:g}_m{m:g}")
                     for q in (100.0, 1000.0) for m in masses)

    cards = [FidelityCard("fifo", rows(0.3, 1e-4, (80e3, 120e3))),
             FidelityCard("mixing", rows(0.2, 2e-4, (1e3, 1e7))),
             FidelityCard("dem", rows(FLOOR, 10.0, (1e3, 1e7)))]
    path = write_cards(tmp_path / "cards.json", cards)
    raw = _auto_plant(tmp_path, {"accuracy": {"tracking_error": 0.35}, "cards": str(path)})
    simulation, summary = run_scenario(raw, tmp_path / "out", until=400.0)
    switches = summary["fidelity"]["stockpile"]["switches"]
    assert summary["fidelity"]["stockpile"]["model"] == "fifo"  # the choice at the start
    assert [(s["from_model"], s["to_model"]) for s in switches] == [("fifo", "mixing")]
    switch = switches[0]
    assert switch["held_mass_kg"] > 120e3 and "range of its card" in switch["reason"]
    rung = simulation.timeseries["stockpile.model_rung"]
    time = simulation.timeseries.index.to_numpy() if "time" not in simulation.timeseries \
        else simulation.timeseries["time"].to_numpy()
    assert set(rung.unique()) == {0.0, 1.0} and rung.is_monotonic_increasing
    assert summary["mass_balance_rel_error"] < 1e-12
    with sqlite3.connect(tmp_path / "out" / "events.sqlite") as db:
        (event_id, at, count), = db.execute(
            "SELECT event_id, time, n_particles FROM events WHERE type = 'switch'").fetchall()
        handed = db.execute("SELECT SUM(mass) FROM event_particles WHERE event_id = ?",
                            (event_id,)).fetchone()[0]
    assert at == pytest.approx(switch["time_s"]) and count == switch["particles"] > 0
    assert handed == pytest.approx(switch["held_mass_kg"], rel=1e-12)
    assert time.size == rung.size
    assert (tmp_path / "out" / "fidelity_stockpile.png").stat().st_size > 0
