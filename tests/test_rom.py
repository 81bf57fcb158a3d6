"""ROM stockpile: model file, range warnings, exact mass/id bookkeeping.

The training data here is synthetic but physical: heaps of random height and
shape with the 2-D point-sink funnel flow towards the outlet,
|v| = q / (rho_A pi r) (mass flux q through every half circle around the
outlet), inside the pile.
"""

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from cosim import sizes
from cosim.particles import ParticleStore
from cosim.storage import make_storage
from surrogate.rom import metrics
from surrogate.rom.container import Container
from surrogate.rom.grid import Grid, mass_field
from surrogate.rom.model import OutOfTrainingRange, RomModel
from surrogate.rom.storage import RomStorage

OWNER = 3
CONTAINER = Container(x_min=-10.0, x_max=10.0, floor=0.0, outlet_x=0.0, inlet_x=0.0,
                      areal_density=1600.0, repose_angle=0.6)
GRID = Grid.covering(-10.0, 10.0, 0.0, 8.0, 1.0)


def heap(rng, height, centre):
    """Positions of a triangular heap (slope 0.6) sampled uniformly, 0.4 m spacing."""
    x, y = np.meshgrid(np.arange(-9.8, 10, 0.4), np.arange(0.2, 8, 0.4))
    x, y = x.ravel(), y.ravel()
    inside = y < height - 0.6 * np.abs(x - centre)
    return np.column_stack((x[inside], y[inside])) + rng.normal(0, 0.02, (inside.sum(), 2))


def sink_flow(position, rate):
    offset = position - [CONTAINER.outlet_x, CONTAINER.floor]
    r = np.maximum(np.linalg.norm(offset, axis=1), 0.5)
    return -rate / (CONTAINER.areal_density * np.pi * r)[:, None] * offset / r[:, None]


def synthetic_training(samples=40, seed=1):
    rng = np.random.default_rng(seed)
    masses, velocities, q_out, q_in = [], [], [], []
    x, y = GRID.centres()
    centres = np.column_stack([g.ravel() for g in np.meshgrid(x, y)])
    for _ in range(samples):
        position = heap(rng, rng.uniform(4, 7.5), rng.uniform(-2, 2))
        mass = np.full(len(position), 0.16 * CONTAINER.areal_density)
        field = mass_field(GRID, position, mass)
        rate = rng.uniform(0, 400)
        velocity = sink_flow(centres, rate).reshape(GRID.ny, GRID.nx, 2) * (field > 0)[..., None]
        masses.append(field), velocities.append(velocity)
        q_out.append(rate), q_in.append(rng.uniform(0, 300))
    return np.array(masses), np.array(q_out), np.array(q_in), np.array(velocities)


def write_design(folder: Path, samples=12, runs=2, container=CONTAINER) -> Path:
    """``synthetic_training`` as a design folder (``doe.json``, ``train/<run>.npz``),
    the samples split evenly into ``runs`` runs, as ``minetwin rom train`` reads it."""
    mass, q_out, q_in, velocity = synthetic_training(samples=samples)
    (folder / "train").mkdir(parents=True)
    per = samples // runs
    for k in range(runs):
        rows = slice(k * per, (k + 1) * per)
        np.savez(folder / "train" / f"run{k}.npz", time=np.arange(float(per)), mass=mass[rows],
                 velocity=velocity[rows], discharge_rate=q_out[rows], inflow_rate=q_in[rows])
    (folder / "doe.json").write_text(json.dumps({"grid": GRID.to_dict(),
                                                 "container": container.to_dict()}))
    return folder


@pytest.fixture(scope="module")
def trained():
    mass, q_out, q_in, velocity = synthetic_training()
    return RomModel(GRID, n_mass_modes=6, n_velocity_modes=6, ridge=1e-3,
                    container=CONTAINER).fit(mass, q_out, q_in, velocity), (mass, q_out, velocity)


def test_model_learns_the_funnel_and_round_trips(trained, tmp_path):
    model, (mass, q_out, velocity) = trained
    predicted = np.array([model.predict(m, q, 100.0) for m, q in zip(mass, q_out)])
    assert metrics.velocity_field_rel_error(predicted, velocity, mass) < 0.3
    path = model.save(tmp_path / "pile.rom.npz")
    loaded = RomModel.load(path)
    assert loaded.header() == model.header()
    assert loaded.container == CONTAINER and loaded.grid == GRID
    np.testing.assert_array_equal(loaded.predict(mass[0], 200.0, 50.0),
                                  model.predict(mass[0], 200.0, 50.0))


def test_out_of_range_input_warns_naming_the_input(trained):
    model, (mass, q_out, _) = trained
    with pytest.warns(OutOfTrainingRange, match=r"discharge_rate = 1900 kg/s .*training range"):
        model.predict(mass[0], 1900.0, 10.0)
    with pytest.warns(OutOfTrainingRange, match="held_mass"):
        model.predict(mass[0] * 3.0, 100.0, 10.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model.predict(mass[0], float(q_out[0]), 100.0)


def filled_storage(model, rng, seed=0):
    position = heap(rng, 6.0, 0.0)
    store = ParticleStore(first_id=10)
    store.add_attribute("tracking_id", np.uint64, 0)
    ids = store.add(mass=rng.uniform(200, 300, len(position)), f=sizes.swebrec(),
                    grade=rng.uniform(0, 1, len(position)), hardness=1.0, owner=OWNER,
                    tracking_id=1)
    storage = make_storage("rom", model=model, rng=np.random.default_rng(seed))
    storage.bind(store, OWNER)
    storage.place(ids, position)
    return store, storage, ids


@pytest.mark.filterwarnings("ignore::surrogate.rom.model.OutOfTrainingRange")
def test_the_storage_says_which_inputs_are_out_of_range_now(trained):
    """The warning comes once; ``out_of_range_now`` follows the latest check."""
    model, _ = trained
    store, storage, _ = filled_storage(model, np.random.default_rng(2))
    storage.step(0.0, 1.0, 1900.0)
    assert "discharge_rate" in storage.out_of_range_now
    assert "discharge_rate" in storage.out_of_range
    storage.step(1.0, 1.0, 100.0)  # a new rate is checked at once
    assert "discharge_rate" not in storage.out_of_range_now
    assert "discharge_rate" in storage.out_of_range  # the record of the first warning stays


# the synthetic heaps are reshaped by the repose rule, so the mass-distribution
# range warning fires; it is tested on its own above
@pytest.mark.filterwarnings("ignore::surrogate.rom.model.OutOfTrainingRange")
def test_rom_storage_conserves_mass_and_ids_and_follows_the_rate(trained):
    model, _ = trained
    rng = np.random.default_rng(4)
    store, storage, ids = filled_storage(model, rng)
    total = store.total_mass()
    held0 = storage.held_mass()
    received, left, rate, dt = [ids], [], 150.0, 1.0
    for k in range(40):
        new = store.add(mass=np.full(3, 50.0), f=sizes.swebrec(), grade=0.5, hardness=2.0,
                        owner=OWNER, tracking_id=100 + k)
        storage.receive(new, k * dt)
        received.append(new)
        total += 150.0
        leaving = storage.step(k * dt, dt, rate)
        store.set_owner(store.slots(leaving), OWNER + 1, (k + 1) * dt)
        left.append(leaving)
        # feeding and discharging at the same rate keeps the held mass constant
        assert abs(storage.held_mass() - held0) <= 300.0
    left, received = np.concatenate(left), np.concatenate(received)
    assert np.unique(left).size == left.size
    held = storage.held_ids()
    assert np.array_equal(np.sort(np.concatenate((left, held))), np.sort(received))
    assert store.total_mass(OWNER + 1) == pytest.approx(rate * 40 * dt, abs=300.0)
    assert store.total_mass(OWNER) + store.total_mass(OWNER + 1) == pytest.approx(total,
                                                                                 rel=1e-12)
    # particles leave from the outlet region, not from anywhere
    assert np.abs(store.position[store.slots(left), 0]).mean() < 3.0
    fields = storage.fields()
    assert fields["mass"].sum() == pytest.approx(storage.held_mass(), rel=1e-12)


@pytest.mark.filterwarnings("ignore::surrogate.rom.model.OutOfTrainingRange")
def test_feed_prediction_covers_the_horizon_from_the_funnel(trained):
    model, _ = trained
    store, storage, _ = filled_storage(model, np.random.default_rng(2))
    storage.step(0.0, 1.0, 200.0)
    ids, share = storage.predict(30.0, 200.0)
    assert share.sum() == pytest.approx(storage._credit_kg + 200.0 * 30.0)
    assert np.abs(store.position[store.slots(ids), 0]).max() < 6.0


@pytest.mark.filterwarnings("ignore::surrogate.rom.model.OutOfTrainingRange")
def test_feed_profile_is_read_from_one_forecast(trained):
    """``predict_each``: every horizon's feed is a prefix of the longest one's (one
    forecast, so the profile's intervals never go negative), each covers the
    feeder's budget, the longest is ``predict``'s to the last bit, and the
    forecast leaves the pile as it was."""
    model, _ = trained
    store, storage, _ = filled_storage(model, np.random.default_rng(2))
    storage.step(0.0, 1.0, 200.0)
    before = storage.bulk_snapshot(1.0)
    horizons = [5.0, 10.0, 20.0, 30.0]
    profile = storage.predict_each(horizons, 200.0)
    longest_ids, longest_share = storage.predict(30.0, 200.0)
    np.testing.assert_array_equal(profile[-1][0], longest_ids)
    np.testing.assert_array_equal(profile[-1][1], longest_share)
    for horizon, (ids, share) in zip(horizons, profile):
        assert share.sum() == pytest.approx(storage._credit_kg + 200.0 * horizon, rel=1e-12)
        np.testing.assert_array_equal(ids, longest_ids[:ids.size])
        np.testing.assert_array_equal(share[:-1], longest_share[:ids.size - 1])
    after = storage.bulk_snapshot(1.0)
    for key in ("id", "position", "mass"):
        np.testing.assert_array_equal(after[key], before[key])


def test_tracking_error_bounds():
    out = {"time": np.array([1.0, 2.0, 40.0]), "tracking_id": np.array([1, 2, 3]),
           "mass": np.array([10.0, 10.0, 5.0])}
    other = {**out, "tracking_id": np.array([4, 5, 6])}
    assert metrics.tracking_error(out, out, 0.0, 60.0) == 0.0
    assert metrics.tracking_error(out, other, 0.0, 60.0) == 1.0
    half = {**out, "tracking_id": np.array([1, 5, 3])}
    assert metrics.tracking_error(half, out, 0.0, 60.0) == pytest.approx(0.25)


def test_cli_trains_from_a_doe_directory(tmp_path, capsys):
    import json

    from minetwin.cli import main

    mass, q_out, q_in, velocity = synthetic_training(samples=12)
    (tmp_path / "train").mkdir()
    np.savez(tmp_path / "train" / "a.npz", time=np.arange(12.0), mass=mass, velocity=velocity,
             discharge_rate=q_out, inflow_rate=q_in)
    (tmp_path / "doe.json").write_text(json.dumps({"grid": GRID.to_dict(),
                                                   "container": CONTAINER.to_dict()}))
    out = tmp_path / "model.npz"
    assert main(["rom", "train", "--data", str(tmp_path), "--out", str(out),
                 "--mass-modes", "4", "--velocity-modes", "4"]) == 0
    loaded = RomModel.load(out)
    low, high = loaded.ranges["discharge_rate"]  # rates are smoothed over 5 s
    assert loaded.n_samples == 12 and q_out.min() <= low < high <= q_out.max()
    assert main(["rom", "evaluate", "--model", str(out)]) == 2
    assert "--model/--data" in capsys.readouterr().err


def test_bad_model_file_is_refused_by_name(tmp_path):
    from cosim.errors import ValidationError

    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a model")
    with pytest.raises(ValidationError, match="^model: "):
        RomModel.load(bad)
    with pytest.raises(ValidationError, match="^model: "):
        RomStorage(bad)


@pytest.mark.filterwarnings("ignore::surrogate.rom.model.OutOfTrainingRange")
def test_stockpile_asset_runs_on_the_rom_by_name(trained, tmp_path):
    from surrogate.stockpile import StockpileAsset

    model, _ = trained
    path = model.save(tmp_path / "pile.rom.npz")
    asset = StockpileAsset("rom", storage_options={"model": str(path)})
    for k in range(30):
        asset.receive_bin(100 + k // 10, 500.0, 0.5, 1.0 + k % 2)
        asset.set_discharge_rate(0.0 if k < 10 else 400.0)
        asset.step(1.0)
    assert asset.mass_out_kg > 0
    assert asset.mass_in_kg == pytest.approx(asset.mass_out_kg + asset.particles.total_mass(),
                                             rel=1e-12)
    assert np.isfinite(asset.fields()["mass"]).any()
    held = asset.particles.total_mass()
    assert asset.predicted_feed(30.0)["mass_kg"] == pytest.approx(
        min(asset.storage._credit_kg + 400.0 * 30.0, held))


def test_out_of_range_input_hands_the_pile_over_to_the_dem(trained):
    """fallback="dem": the ROM pile continues as DEM with every id, its mass,
    attributes and tracking id, disks not overlapping, mass conserved exactly."""
    model, _ = trained
    rng = np.random.default_rng(5)
    position = heap(rng, 6.0, 0.0)
    store = ParticleStore(first_id=10)
    store.add_attribute("tracking_id", np.uint64, 0)
    ids = store.add(mass=rng.uniform(200, 300, len(position)), f=sizes.swebrec(),
                    grade=rng.uniform(0, 1, len(position)), hardness=1.0, owner=OWNER,
                    tracking_id=np.arange(len(position)) % 7)
    config = {"floor_width": 20.0, "inlets": [[0.0, 9.0]], "outlets": [0.0],
              "outlet_width": 3.0, "side_wall_height": 8.0, "diameter_min": 0.4,
              "diameter_max": 0.6, "normal_stiffness": 8.0e6, "rolling_resistance": 0.2}
    storage = make_storage("rom", model=model, rng=np.random.default_rng(0), fallback="dem",
                           fallback_config=config)
    storage.bind(store, OWNER)
    storage.place(ids, position)
    total = store.total_mass()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the synthetic heap's shape is out of range too
        left = [storage.step(0.0, 1.0, 300.0)]
    assert storage.dem_storage is None  # in range so far: still the ROM
    with pytest.warns(OutOfTrainingRange, match="continues as DEM"):
        left.append(storage.step(1.0, 1.0, 1900.0))
    dem = storage.dem_storage.dem
    assert storage.fallen_back_at == 1.0
    gone = np.concatenate(left)
    assert np.array_equal(np.sort(dem.id), np.sort(ids[~np.isin(ids, gone)]))
    slots = store.slots(dem.id)
    np.testing.assert_array_equal(dem.mass, store.mass[slots])
    np.testing.assert_array_equal(dem.grade, store.grade[slots])
    np.testing.assert_array_equal(dem.tracking_id, store.attribute("tracking_id")[slots])
    assert dem.held_mass() == pytest.approx(total - store.mass[store.slots(gone)].sum(),
                                            rel=1e-12)
    store.set_owner(store.slots(gone), OWNER + 1, 2.0)
    for k in range(2, 6):
        new = store.add(mass=np.full(4, 250.0), f=sizes.swebrec(), grade=0.5, hardness=2.0,
                        owner=OWNER, tracking_id=100 + k)
        storage.receive(new, float(k))
        total += 1000.0
        leaving = storage.step(float(k), 1.0, 1900.0)
        store.set_owner(store.slots(leaving), OWNER + 1, k + 1.0)
        left.append(leaving)
    left = np.concatenate(left)
    assert left.size and np.unique(left).size == left.size
    assert np.intersect1d(left, storage.held_ids()).size == 0
    assert storage.held_mass() == pytest.approx(dem.held_mass(), rel=1e-12)
    assert store.total_mass(OWNER) + store.mass[store.slots(left)].sum() == pytest.approx(
        total, rel=1e-12)
    # disks were handed over without deep overlaps: none is thrown off the pile
    assert dem.max_overlap_ratio() < 0.05
    assert (np.abs(dem.pos[:, 0]) <= 10.0).all() and (dem.pos[:, 1] > 0).all()
    assert np.isfinite(storage.fields()["mass"]).all()
    assert storage.fields()["mass"].sum() == pytest.approx(dem.held_mass(), rel=1e-12)


def test_a_ladder_hands_the_pile_from_the_rom_to_the_dem_and_back_exactly(trained):
    """Switching along the ladder (cosim.handover): a ROM whose card holds up to
    400 kg/s runs until the feeder asks 1,900 kg/s, hands the pile to the DEM (ids,
    masses, attributes, positions, the feeder's credit), takes it back once the rate
    has been inside its card, with 10 % to spare, for the dwell time, and hands it up
    again when it finds the pile outside its training range. Mass and ids are exact
    across the three hand-overs; every id leaves once."""
    from cosim.fidelity import CardRow, FidelityCard, Ladder, OperatingPoint
    from cosim.handover import Switcher

    model, _ = trained
    rng = np.random.default_rng(5)
    position = heap(rng, 6.0, 0.0)
    store = ParticleStore(first_id=10)
    store.add_attribute("tracking_id", np.uint64, 0)
    ids = store.add(mass=rng.uniform(200, 300, len(position)), f=sizes.swebrec(),
                    grade=rng.uniform(0, 1, len(position)), hardness=1.0, owner=OWNER,
                    tracking_id=np.arange(len(position)) % 7)
    config = {"floor_width": 20.0, "inlets": [[0.0, 9.0]], "outlets": [0.0],
              "outlet_width": 3.0, "side_wall_height": 8.0, "diameter_min": 0.4,
              "diameter_max": 0.6, "normal_stiffness": 8.0e6, "rolling_resistance": 0.2}

    def card(name, error, cost):
        return FidelityCard(model=name, rows=tuple(
            CardRow(q, m, 30.0, error, 0.05, cost, f"q{q}") for q in (100.0, 400.0)
            for m in (1e3, 1e6)))

    ladder = Ladder([card("rom", 0.1, 1e-3), card("dem", 0.05, 1.0)], tracking_error=0.15,
                    margin=0.1, dwell_s=3.0)

    def build(name):
        if name == "rom":
            return make_storage("rom", model=model, rng=np.random.default_rng(1))
        return make_storage("dem", config=config, rng=np.random.default_rng(2))

    total = store.total_mass()
    assert ladder.start(OperatingPoint(300.0, total)).model == "rom"
    storage = build("rom").bind(store, OWNER)
    storage.place(ids, position)
    switcher = Switcher(ladder, build)
    rates = [300.0] * 2 + [1900.0] * 3 + [300.0] * 6
    left = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the synthetic heap's shape is out of range too
        for k, rate in enumerate(rates):
            storage = switcher.update(float(k), storage, rate)
            leaving = storage.step(float(k), 1.0, rate)
            store.set_owner(store.slots(leaving), OWNER + 1, k + 1.0)
            left.append(leaving)
            held = np.sort(storage.held_ids())
            assert np.array_equal(held, np.sort(store.id[store.owner == OWNER]))
            assert storage.held_mass() == pytest.approx(store.total_mass(OWNER), rel=1e-12)
    switches = switcher.switches
    assert [(s["from_model"], s["to_model"], s["time_s"]) for s in switches] == [
        ("rom", "dem", 2.0), ("dem", "rom", 8.0), ("rom", "dem", 9.0)]
    assert "outside the range of its card" in switches[0]["reason"]
    assert "for 3 s" in switches[1]["reason"]  # back in range from 5 s, dwell 3 s
    # the pile the DEM left is not a shape the synthetic ROM was trained on: the ROM
    # says so at its first step, and the ladder goes up again at once
    assert "training range" in switches[2]["reason"]
    assert all(s["particles"] > 0 for s in switches)
    left = np.concatenate(left)
    assert left.size and np.unique(left).size == left.size
    assert np.intersect1d(left, storage.held_ids()).size == 0
    assert store.total_mass(OWNER) + store.mass[store.slots(left)].sum() == pytest.approx(
        total, rel=1e-12)
    # the DEM drew no more than commanded: credit carried over, never doubled
    assert store.mass[store.slots(left)].sum() <= sum(rates) + 300.0
