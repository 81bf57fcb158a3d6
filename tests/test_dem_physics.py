"""Physics of the 2D DEM: restitution, friction law, angle of repose, feeder
discharge, conservation and time-step stability (issue 5)."""

import dataclasses
import math

import numpy as np
import pytest

from surrogate.dem import Dem, DemBlowUp, DemConfig, FeederCapped
from surrogate.dem.analysis import side_angles
from surrogate.dem.builders import config_for_particles, packed_pile, pour_pile, settle
from surrogate.dem.config import GRAVITY

F16 = np.eye(16)[12]


def _drop(restitution, height=5.0, diameter=0.4):
    """Drop one disk on the floor; return (impact speed, rebound speed).

    The rebound speed is corrected for the impulse of gravity during the
    contact (g times the contact duration), which is not part of the
    contact law the restitution describes (~1.5 % at e = 0.3).
    """
    cfg = DemConfig(floor_width=10.0, restitution=restitution, inlets=[[0.0, 8.0]])
    dem = Dem(cfg)
    dem.place([[1.0, height]], cfg.sphere_mass(diameter), 0.5, 1.0, F16, 1)
    r = diameter / 2
    v_in = None
    while True:
        y_before, v_before = dem.pos[0, 1], dem.vel[0, 1]
        dem.step(1)
        if v_in is None and dem.pos[0, 1] < r:
            v_in = -v_before  # last free-flight velocity before touching
            touched = dem.time - dem.dt
        if v_in is not None and dem.pos[0, 1] > r and dem.vel[0, 1] > 0:
            return v_in, dem.vel[0, 1] + GRAVITY * (dem.time - touched)
        assert dem.time < 5.0, "no rebound"
        assert y_before > -1.0


@pytest.mark.parametrize("restitution", [0.3, 0.6, 0.9])
def test_dropped_disk_rebounds_with_configured_restitution(restitution):
    v_in, v_out = _drop(restitution)
    assert v_in == pytest.approx(math.sqrt(2 * GRAVITY * (5.0 - 0.2)), rel=0.01)
    assert v_out / v_in == pytest.approx(restitution, rel=0.02)


def _on_incline(angle_deg, friction=0.5, seconds=1.0):
    """Disk at rest on an incline; return its displacement along the slope after ``seconds``."""
    theta = math.radians(angle_deg)
    length = 20.0
    a = np.array([0.0, 1.0])
    b = a + length * np.array([math.cos(theta), math.sin(theta)])
    # rolling resistance mu_r = 1 > tan(theta) locks rolling, so the friction law alone decides
    cfg = DemConfig(floor_width=60.0, friction=friction, rolling_resistance=1.0,
                    extra_walls=[[*a, *b]], inlets=[[0.0, 20.0]])
    dem = Dem(cfg)
    r = 0.2
    along = np.array([math.cos(theta), math.sin(theta)])
    normal = np.array([-math.sin(theta), math.cos(theta)])
    start = a + 15.0 * along + r * normal
    dem.place([start], cfg.sphere_mass(2 * r), 0.5, 1.0, F16, 1)
    dem.advance(seconds)
    return float((start - dem.pos[0]) @ along), dem.time


def test_disk_sticks_on_incline_below_friction_angle():
    moved, _ = _on_incline(20.0)  # tan 20 deg = 0.36 < mu = 0.5
    assert abs(moved) < 1e-3


def test_disk_slides_on_incline_above_friction_angle_with_coulomb_deceleration():
    angle = 35.0  # tan 35 deg = 0.70 > mu = 0.5
    moved, t = _on_incline(angle)
    theta = math.radians(angle)
    expected = 0.5 * GRAVITY * (math.sin(theta) - 0.5 * math.cos(theta)) * t * t
    assert moved == pytest.approx(expected, rel=0.03)


def _poured_repose_angle(seed: int, particles: int = 600) -> float:
    """Mean flank angle [deg] of a pile of ``particles`` disks poured and settled 10 s."""
    cfg = config_for_particles(particles)
    dem = Dem(cfg, seed=seed)
    pour_pile(dem, particles)
    settle(dem, max_time=10.0)
    left, right = side_angles(dem.pos, dem.radius)
    return 0.5 * (left + right)


REPOSE_SEEDS = (0, 1, 2, 3)
REPOSE_MEAN_DEG, REPOSE_SD_DEG = 38.6, 2.66
"""Measured over 16 poured piles (seeds 0-7, each compiled for this AMD EPYC and with
``NUMBA_CPU_NAME=generic``): per-pile mean flank angle 38.6 deg, standard deviation
2.66 deg (``python tests/test_dem_physics.py 0 1 2 3 4 5 6 7``, once per target)."""


@pytest.mark.slow
def test_poured_piles_angle_of_repose_over_seeds():
    """A poured pile's angle is chaotic (one pile ranged 34.4-44.5 deg over seeds, and a
    pile changes with the CPU's instruction set), so the test is on the mean over four
    seeds: within three standard errors of the measured ensemble mean, and inside the
    30-45 deg of dry rock piles."""
    angles = [_poured_repose_angle(seed) for seed in REPOSE_SEEDS]
    band = 3.0 * REPOSE_SD_DEG / math.sqrt(len(angles))
    mean = float(np.mean(angles))
    assert abs(mean - REPOSE_MEAN_DEG) <= band, angles
    assert 30.0 <= mean <= 45.0, angles


@pytest.fixture(scope="module")
def settled_pile():
    cfg = config_for_particles(600)
    dem = packed_pile(cfg, 600, seed=1)
    settle(dem, max_time=3.0)
    return dem


@pytest.mark.parametrize("rate", [500.0, 2000.0])
def test_discharge_follows_setpoint_and_conserves_mass_and_ids(settled_pile, tmp_path, rate):
    path = tmp_path / "pile.npz"
    settled_pile.save_checkpoint(path)
    dem = Dem.load_checkpoint(path)
    ids_in = set(dem.id.tolist())
    mass_in = dem.held_mass()
    dem.set_discharge_rate(rate)
    dem.advance(1.0)  # the feeder's first draw empties the zone it starts with
    first = dem.discharged()
    duration = 4.0
    dem.advance(duration)
    out = dem.discharged()
    assert out["mass"].sum() / duration == pytest.approx(rate, rel=0.05)
    assert dem.held_mass() > 0.5 * mass_in  # still "full"
    # funnel flow: the column above the outlet moves, the flanks rest
    speed = np.hypot(dem.vel[:, 0], dem.vel[:, 1])
    x = np.abs(dem.pos[:, 0] - dem.cfg.outlets[0])
    width = dem.cfg.outlet_width
    assert speed[x < width / 2].mean() > 10 * speed[x > width].mean()
    left = np.concatenate((first["id"], out["id"]))
    assert len(set(left.tolist())) == left.size
    assert set(left.tolist()) | set(dem.id.tolist()) == ids_in
    assert not set(left.tolist()) & set(dem.id.tolist())
    total = dem.held_mass() + first["mass"].sum() + out["mass"].sum()
    assert total == pytest.approx(mass_in, rel=1e-12)
    assert dem.mass_balance_error() < 1e-12


def test_feeder_setpoint_above_the_opening_is_capped_and_reported():
    cfg = DemConfig(outlet_width=1.8)
    dem = Dem(cfg)
    capacity = cfg.orifice_capacity()
    # 2D Beverloo with the defaults: C = 0.66, rho_2D = 595 kg/m^2, d = 0.376 m, k = 1.5
    assert capacity == pytest.approx(0.66 * 594.78 * math.sqrt(GRAVITY)
                                     * (1.8 - 1.5 * 0.37638) ** 1.5, rel=1e-4)
    assert dem.set_discharge_rate(0.5 * capacity) == 0.5 * capacity
    assert not dem.feeder_state()["capped"]
    with pytest.warns(FeederCapped, match="capped at"):
        assert dem.set_discharge_rate(2000.0) == pytest.approx(capacity)
    state = dem.feeder_state()
    assert state["capped"] and state["setpoint"] == 2000.0 and state["rate"] == capacity
    assert DemConfig(outlet_width=0.5).orifice_capacity() == 0.0  # narrower than k d: arches


CAP_SEEDS = (0, 1, 2)
CAP_RATIO_SD = 0.015
"""Spread of delivered / capacity over the piles of CAP_SEEDS with the capped
feeder (``_capped_discharge``): 1.009, 0.982, 1.005 (measured once each)."""


def _capped_discharge(seed, duration=3.0):
    """A 600-disk pile under a feeder whose 4 m opening passes 1.19 t/s (C = 0.1
    makes the bound bite below the 2 t/s setpoint, which the zone can feed)."""
    cfg = dataclasses.replace(config_for_particles(600), outlet_width=4.0, beverloo_c=0.1)
    dem = packed_pile(cfg, 600, seed=seed)
    settle(dem, max_time=2.0)
    with pytest.warns(FeederCapped):
        rate = dem.set_discharge_rate(2000.0)
    dem.advance(1.0)
    dem.discharged()
    dem.advance(duration)
    return dem.discharged()["mass"].sum(), rate * duration, float(dem.mass.max())


@pytest.mark.slow
def test_capped_feeder_delivers_what_the_opening_passes_over_seeds():
    """Each pile: never more than the capped rate times the time plus what the
    credit carries (a disk or two), an exact rule of the feeder. Over the seeds:
    the mean delivered rate within three standard errors of the capacity
    (spread measured, CAP_RATIO_SD), far from the 1.69x the setpoint asks."""
    ratios = []
    for seed in CAP_SEEDS:
        delivered, allowed, heaviest = _capped_discharge(seed)
        assert delivered <= allowed + 2 * heaviest
        ratios.append(delivered / allowed)
    band = 3 * CAP_RATIO_SD / math.sqrt(len(ratios))
    assert abs(np.mean(ratios) - 1.0) <= band, ratios


def test_pouring_puts_every_kilogram_and_id_into_the_dem():
    cfg = config_for_particles(80)
    dem = Dem(cfg, seed=3)
    lots = [137.5, 600.0, 1234.25, 45.0]
    ids = [dem.emit(m, 0.4, 1.1, F16, k, inlet=k % 2) for k, m in enumerate(lots)]
    dem.advance(0.5)
    for k, m in enumerate(lots):
        rows = np.isin(dem.id, ids[k])
        assert dem.mass[rows].sum() == pytest.approx(m, rel=1e-14)
        assert (dem.tracking_id[rows] == k).all()
    assert np.concatenate(ids).size == np.unique(np.concatenate(ids)).size == dem.n
    d = 2 * dem.radius
    assert d.min() >= cfg.diameter_min and d.max() <= cfg.diameter_max


def _pile_energy_history(dt_factor, steps, chunks):
    cfg = dataclasses.replace(config_for_particles(150), restitution=0.5)
    dem = packed_pile(cfg, 150, seed=2)
    dem.set_dt(dt_factor * dem.stable_dt, force=dt_factor > 1)
    energies = [dem.energy()["total"]]
    for _ in range(chunks):
        dem.step(steps)
        energies.append(dem.energy()["total"])
    return np.array(energies), dem


def test_energy_decays_at_derived_step():
    stable, dem = _pile_energy_history(1.0, 500, 6)
    assert np.isfinite(stable).all()
    assert stable[-1] < stable[0]
    assert (np.diff(stable) <= 1e-9 * abs(stable[0])).all()  # never gains energy
    assert dem.failure is None


def test_forced_step_far_above_the_limit_stops_naming_what_when_and_why():
    # 8 x stable_dt = 0.53 t_c, twice the 0.26 t_c measured unstable on a dense pile
    cfg = dataclasses.replace(config_for_particles(150), restitution=0.5)
    dem = packed_pile(cfg, 150, seed=2)
    dem.set_dt(8.0 * dem.stable_dt, force=True)
    with pytest.raises(DemBlowUp) as info:
        dem.advance(2.0)
    error = info.value
    assert error.kind in ("speed", "outside", "energy", "overlap")
    assert 0.0 < error.time < 2.0 and error.step == dem.steps_done
    assert f"t = {error.time:.6g} s (step {error.step})" in str(error)
    assert "8 x the stability limit" in str(error)
    speed = np.hypot(dem.vel[:, 0], dem.vel[:, 1]).max()
    assert speed < 3 * dem.speed_limit  # stopped at once, not at 1.3 km/s
    with pytest.raises(DemBlowUp):  # a blown-up DEM does not step on
        dem.step(1)


def _two_disks():
    cfg = DemConfig(floor_width=10.0, inlets=[[0.0, 4.0]])
    dem = Dem(cfg)
    dem.place([[-1.0, 0.3], [1.0, 0.3]], 100.0, 0.5, 1.0, F16, 1)
    return dem


def test_guard_names_each_cause():
    dem = _two_disks()
    dem.step(10)
    dem.pos[0] = [8.0, 1.0]
    with pytest.raises(DemBlowUp, match="outside the container at x = 8 m") as info:
        dem.step(1)
    assert info.value.kind == "outside" and "within the stability limit" in info.value.cause
    dem = _two_disks()
    dem.vel[1] = [0.0, 1e4]
    with pytest.raises(DemBlowUp, match="at 1e\\+04 m/s, above the limit") as info:
        dem.step(1)
    assert info.value.kind == "speed" and info.value.step == 1
    dem = _two_disks()
    dem.step(200)  # the guard's first check takes the energy budget
    dem.vel[:, 0] = [5.0, -5.0]  # energy from nowhere, below the speed limit
    with pytest.raises(DemBlowUp, match="mechanical energy") as info:
        dem.step(200)
    assert info.value.kind == "energy"
    dem = _two_disks()
    dem.place([[-1.0 + 0.1 * dem.radius[0], 0.3]], 100.0, 0.5, 1.0, F16, 2)
    with pytest.raises(DemBlowUp, match="overlap of 0.9") as info:
        dem.step(200)
    assert info.value.kind == "overlap"


def test_step_above_the_limit_is_refused_with_the_limit_in_the_message():
    dem = Dem(DemConfig())
    with pytest.raises(ValueError, match=f"{dem.stable_dt:.4g} s"):
        dem.set_dt(2 * dem.stable_dt)
    with pytest.raises(ValueError, match="stability limit"):
        Dem(DemConfig(), dt=1.5 * dem.stable_dt)
    dem.set_dt(2 * dem.stable_dt, force=True)
    assert dem.dt == 2 * dem.stable_dt


if __name__ == "__main__":
    import sys

    for seed in map(int, sys.argv[1:]):
        print(seed, round(_poured_repose_angle(seed), 2), flush=True)
