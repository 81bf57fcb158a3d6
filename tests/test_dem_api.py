"""DEM interfaces: checkpoint/restart, input validation, snapshots, the
``dem`` storage model and the ``minetwin dem`` commands (issue 5)."""

import json
import re

import numpy as np
import pytest

from cosim import sizes
from minetwin.cli import main
from cosim.errors import ValidationError
from cosim.particles import ParticleStore
from cosim.storage import make_storage
from surrogate.dem import Dem, DemConfig
from surrogate.dem.builders import config_for_particles
from surrogate.dem.snapshots import SnapshotWriter, read_snapshots

F16 = np.eye(16)[12]


def _small_pile(seed=0, lots=6):
    dem = Dem(config_for_particles(60), seed=seed)
    for k in range(lots):
        dem.emit(700.0, 0.1 * k, 1.0, F16, k, inlet=k % 2)
        dem.advance(0.3)
    return dem


def _state(dem):
    snap = dem.snapshot()
    snap.update(ht=dem.ht, hr=dem.hr, wall_ht=dem.wall_ht, credits=dem.credits)
    return snap


def test_checkpoint_restart_continues_bit_for_bit(tmp_path):
    dem = _small_pile()
    dem.set_discharge_rate(800.0)
    dem.advance(0.4)
    path = tmp_path / "dem.npz"
    dem.save_checkpoint(path)
    dem.emit(300.0, 0.9, 2.0, F16, 99, inlet=1)  # rng state must be restored too
    dem.advance(1.5)
    straight = _state(dem)
    straight_out = dem.discharged()

    again = Dem.load_checkpoint(path)
    again.emit(300.0, 0.9, 2.0, F16, 99, inlet=1)
    again.advance(1.5)
    restarted = _state(again)
    restarted_out = again.discharged()
    assert straight_out["id"].size > 0  # the feeder worked across the restart
    for key, value in straight.items():
        assert np.array_equal(value, restarted[key]), key
    for key, value in straight_out.items():
        assert np.array_equal(value, restarted_out[key]), key


def test_same_seed_same_run_and_ids_are_uint64():
    a, b = _small_pile(seed=5, lots=3), _small_pile(seed=5, lots=3)
    assert a.id.dtype == np.uint64
    assert np.array_equal(a.pos, b.pos) and np.array_equal(a.id, b.id)


def test_bad_input_is_refused_by_field_and_nothing_is_added():
    dem = _small_pile(lots=1)
    n, mass = dem.n, dem.held_mass()
    with pytest.raises(ValidationError, match="grade"):
        dem.emit(100.0, 1.5, 1.0, F16, 1)
    with pytest.raises(ValidationError, match="mass_kg"):
        dem.emit(-5.0, 0.5, 1.0, F16, 1)
    with pytest.raises(ValidationError, match="inlet"):
        dem.emit(100.0, 0.5, 1.0, F16, 1, inlet=7)
    with pytest.raises(ValidationError, match="ids"):
        dem.emit([50.0], 0.5, 1.0, F16, 1, ids=dem.id[:1])
    with pytest.raises(ValidationError, match="discharge_rate"):
        dem.set_discharge_rate(2500.0)
    with pytest.raises(ValidationError, match="discharge_rate"):
        dem.set_discharge_rate(float("nan"))
    with pytest.raises(ValidationError, match="restitution"):
        DemConfig(restitution=0.1)
    with pytest.raises(ValidationError, match="unknown key"):
        DemConfig.from_dict({"stiffness": 1.0})
    assert dem.n == n and dem.held_mass() == mass


def test_config_round_trips_through_toml(tmp_path):
    path = tmp_path / "dem.toml"
    path.write_text("[dem]\nfriction = 0.7\nfloor_width = 50.0\noutlets = [-5.0, 5.0]\n")
    cfg = DemConfig.from_toml(path)
    assert cfg.friction == 0.7 and cfg.outlets == [-5.0, 5.0]
    assert DemConfig.from_dict(cfg.to_dict()) == cfg
    assert cfg.stable_dt == pytest.approx(cfg.contact_time / cfg.dt_safety_factor)


def test_snapshots_written_at_interval_and_read_back(tmp_path):
    dem = _small_pile(lots=2)
    writer = SnapshotWriter(tmp_path / "snaps", interval=0.2)
    for _ in range(5):
        dem.advance(0.1)
        writer.maybe_write(dem)
    snaps = list(read_snapshots(tmp_path / "snaps"))
    assert len(snaps) == 3
    assert snaps[-1]["position"].shape == (dem.n, 2)
    assert np.array_equal(snaps[-1]["id"], dem.id)
    assert np.diff([s["time"] for s in snaps]).min() >= 0.2 - 1e-9


def test_dem_storage_model_keeps_ids_and_mass_and_syncs_positions():
    store = ParticleStore()
    owner = 3
    rng = np.random.default_rng(1)
    ids = store.add(mass=rng.uniform(60, 140, 40), f=sizes.swebrec(), grade=0.3,
                    hardness=1.0, owner=owner)
    model = make_storage("dem", config=config_for_particles(40).to_dict(),
                         rng=np.random.default_rng(0))
    model.bind(store, owner)
    model.receive(ids, 0.0)
    total = store.total_mass(owner)
    assert model.held_mass() == pytest.approx(total, rel=1e-14)
    left = []
    for k in range(20):
        leaving = model.step(0.25 * k, 0.25, 400.0)
        store.set_owner(store.slots(leaving), 9, 0.25 * (k + 1))
        left.extend(leaving.tolist())
    assert left, "the feeder took nothing"
    assert len(set(left)) == len(left)
    assert sorted(left + model.held_ids().tolist()) == sorted(ids.tolist())
    assert store.total_mass(9) + model.held_mass() == pytest.approx(total, rel=1e-12)
    held = store.slots(model.dem.id)
    assert np.array_equal(store.position[held, :2], model.dem.pos)
    assert (store.position[held, 2] == 0).all()
    predicted_ids, predicted_mass = model.predict(2.0, 400.0)
    assert predicted_mass.sum() == pytest.approx(min(800.0 + model.dem.credits[0],
                                                     model.held_mass()), rel=1e-9)
    assert set(predicted_ids.tolist()) <= set(model.held_ids().tolist())
    with pytest.raises(ValidationError, match="discharge_rate"):
        model.step(10.0, 0.1, -1.0)


def test_cli_pile_then_discharge_writes_summary_and_pictures(tmp_path, capsys):
    pile, out = tmp_path / "pile", tmp_path / "out"
    assert main(["dem", "pile", "--particles", "60", "--out", str(pile),
                 "--settle-time", "2"]) == 0
    # progress in a log: plain lines, the compile notice first, and a last line at the
    # run's end (100 %, with its wall time), also when the pile settled before 2 s. The
    # remaining-time field is not checked: tqdm prints "?" there when the run took under
    # its first rate sample (kernels already cached, a fast CPU), "00:00" otherwise.
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("dem pile: ")]
    assert "\r" not in err and "compile the DEM kernels" in lines[0]
    assert "100%|##########|" in lines[-1]
    assert re.search(r"\[\d\d:\d\d<", lines[-1]), lines[-1]
    summary = json.loads((pile / "summary.json").read_text())
    assert summary["particles"] == 60
    for key in ("dt_s", "steps", "wall_s", "particle_steps_per_s", "angle_of_repose_deg",
                "discharged_kg", "mass_balance_rel_error"):
        assert key in summary
    assert summary["mass_balance_rel_error"] < 1e-12
    for stem in ("grade", "residence_time", "speed"):
        assert (pile / f"pile_{stem}.png").stat().st_size > 1000
    assert main(["dem", "discharge", "--from", str(pile), "--rate", "500", "--duration", "2",
                 "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["discharged_kg"] > 0
    assert summary["mass_balance_rel_error"] < 1e-12
    assert summary["particles"] < 60
    assert (out / "discharged.csv").read_text().count("\n") == 1 + 60 - summary["particles"]
    err = capsys.readouterr().err
    # progress counts the command's own seconds, not the pile's clock
    lines = [line for line in err.splitlines() if line.startswith("dem discharge: ")]
    assert "| 2.0/2.0 [" in lines[-2] and "100%|##########|" in lines[-2], lines
    assert main(["dem", "discharge", "--from", str(pile), "--rate", "5000", "--duration", "2",
                 "--out", str(out)]) == 2
    assert "discharge_rate" in capsys.readouterr().err
    # the same state continued under changed settings, from the checkpoint file
    changed = tmp_path / "changed"
    assert main(["dem", "discharge", "--from", str(out / "checkpoint.npz"), "--rate", "300",
                 "--duration", "1", "--out", str(changed), "--set", "method=nonsmooth",
                 "--set", "solver_iterations=50"]) == 0
    summary = json.loads((changed / "summary.json").read_text())
    assert summary["dt_s"] == 0.011 and summary["mass_balance_rel_error"] < 1e-12
    capsys.readouterr()
    for bad, named in (("solver_iterations=2.5", "solver_iterations: must be an integer"),
                       ("rolling_resistance=NaN", "rolling_resistance: must be in [0, 10]"),
                       ("nonsense=1", "unknown key(s) ['nonsense']")):
        assert main(["dem", "discharge", "--from", str(out), "--rate", "300", "--duration",
                     "1", "--out", str(changed), "--set", bad]) == 2
        assert named in capsys.readouterr().err


@pytest.mark.parametrize("angle", [30.0, 38.0])
def test_angle_of_repose_estimator_reads_a_laid_out_triangle(angle):
    from surrogate.dem.analysis import angle_of_repose
    from surrogate.dem.builders import packed_pile

    dem = packed_pile(DemConfig(floor_width=80.0), 1500, seed=0, angle_deg=angle)
    assert angle_of_repose(dem.pos, dem.radius) == pytest.approx(angle, abs=1.5)


def test_neighbour_lists_grow_past_their_first_capacity():
    """Lists start with room for ~8 pairs and ~1 wall per disk; denser scenes double it."""
    from surrogate.dem import kernels

    # 2 disks each within reach of 30 short segments: 60 wall entries > 2 + 16
    pos = np.array([[0.0, 0.0], [5.0, 0.0]])
    radius = np.full(2, 0.5)
    angles = np.linspace(0, 2 * np.pi, 30, endpoint=False)
    walls = np.array([[x + 0.4 * np.cos(a), 0.4 * np.sin(a), x + 0.45 * np.cos(a),
                       0.45 * np.sin(a)] for x in (0.0, 5.0) for a in angles])
    empty = np.zeros(1, np.int64)
    start, wall, ht, hr, hn = kernels.build_wall_list(pos, radius, 0.05, walls, empty,
                                                      np.zeros(0, np.int64), np.zeros(0),
                                                      np.zeros(0), np.zeros(0), np.full(2, -1))
    assert start.tolist() == [0, 30, 60]
    assert sorted(wall[:30]) == list(range(30)) and sorted(wall[30:]) == list(range(30, 60))
    # 40 disks piled into one spot: 780 pairs > 8 * 40 + 16
    pos = np.random.default_rng(0).uniform(0, 0.1, (40, 2))
    start, nbr, ht, hr, hn = kernels.build_pair_list(pos, np.full(40, 0.5), 0.05, empty,
                                                     np.zeros(0, np.int64), np.zeros(0),
                                                     np.zeros(0), np.zeros(0), np.full(40, -1))
    assert start[-1] == 40 * 39 // 2
    assert all(list(nbr[start[i]:start[i + 1]]) == list(range(i + 1, 40)) for i in range(40))


def test_explicit_dem_gives_the_same_bits_on_one_and_two_threads(monkeypatch):
    """The force kernel and the integration run on all threads (prange) with
    each disk's sums gathered in a fixed order, so the thread count cannot
    change a bit: a pile discharging for 0.25 s at 1 and at 2 threads, and at
    one thread by the rule for scenes below ``PARALLEL_MIN_DISKS``."""
    import numba

    from surrogate.dem import kernels
    from surrogate.dem.builders import packed_pile

    runs = []
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("needs NUMBA_NUM_THREADS >= 2")
    for threads, smallest in ((1, 0), (2, 0), (2, 10 ** 9)):
        monkeypatch.setattr(kernels, "PARALLEL_MIN_DISKS", smallest)
        dem = packed_pile(config_for_particles(300), 300, seed=4)
        dem.threads = threads
        assert dem.kernel_threads() == (1 if smallest else threads)
        dem.set_discharge_rate(800.0)
        dem.advance(0.25)
        runs.append((dem.pos, dem.vel, dem.omega, dem.ht, dem.hr, dem.wall_ht,
                     dem.discharged()["id"]))
    assert runs[0][-1].size > 0
    for one, two, serial in zip(*runs):
        assert np.array_equal(one, two) and np.array_equal(one, serial)


def test_dem_command_reports_a_blow_up_without_a_traceback(tmp_path, capsys):
    dem = Dem(config_for_particles(60))
    r = 0.2
    # two disks placed 90 % into each other: the guard stops the first step
    dem.place(np.array([[0.0, 1.0], [0.1 * r, 1.0]]), dem.cfg.sphere_mass(2 * r), 0.5, 1.0,
              F16, 1)
    source = tmp_path / "bad"
    source.mkdir()
    dem.save_checkpoint(source / "checkpoint.npz")
    code = main(["dem", "discharge", "--from", str(source), "--rate", "100",
                 "--duration", "1", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 1
    assert "minetwin dem discharge: error: DEM blew up at t = " in err
    assert "Traceback" not in err
