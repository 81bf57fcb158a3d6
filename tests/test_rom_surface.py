"""Surface-layer DEM of the ROM stockpile: fall, impact, hand-over to the bulk."""

import numpy as np
import pytest

from cosim import sizes
from cosim.errors import ValidationError
from cosim.particles import ParticleStore
from surrogate.rom import doe
from surrogate.rom.container import Container
from surrogate.rom.grid import Grid, mass_field
from surrogate.rom.model import RomModel
from surrogate.rom.storage import RomStorage
from surrogate.rom.surface import surface_heights
from surrogate.rom.surface_dem import SurfaceDem

G = 9.81
CONTAINER = Container(x_min=-10.0, x_max=10.0, floor=0.0, outlet_x=0.0, inlet_x=1.0,
                      areal_density=1600.0, repose_angle=0.6, outlet_width=2.0)
GRID = Grid.covering(-10.0, 10.0, 0.0, 8.0, 1.0)
CONFIG = doe.training_config()


def test_a_falling_particle_follows_the_closed_form_and_joins_after_its_impact():
    surface = SurfaceDem(CONFIG, CONTAINER, impact_time=0.05)
    start = surface.add(np.array([7], np.uint64), np.array([100.0]))[0]
    height = start[1] - surface.radius[0]
    v0 = CONFIG.inlet_velocity
    landing = (-v0 + np.sqrt(v0 ** 2 + 2 * G * height)) / G  # bottom reaches the floor
    t = 0.0
    while t + 0.1 < landing - 0.05:  # well before the impact: exactly ballistic
        assert surface.advance(0.1, 0.5, np.empty((0, 2)), np.empty(0))[0].size == 0
        t += 0.1
        expected = start[1] - v0 * t - 0.5 * G * t ** 2
        assert surface.pos[0, 1] == pytest.approx(expected, abs=1e-9)
        assert surface.pos[0, 0] == start[0]
    ids, mass, position = surface.advance(landing - t + 0.1, 0.5, np.empty((0, 2)), np.empty(0))
    assert ids.tolist() == [7] and mass.tolist() == [100.0] and len(surface) == 0
    assert abs(position[0, 0] - CONTAINER.inlet_x) <= 0.5 * CONFIG.inlet_width + 0.05
    # it joins at the end of its impact window: on the floor or at most one rebound above it
    radius = 0.5 * CONFIG.diameter_of_mass(100.0)
    rebound = CONFIG.restitution * (v0 + G * landing) * surface.impact_time
    assert radius - 0.01 <= position[0, 1] <= radius + rebound + 0.01


def test_a_column_piled_high_beside_the_stream_does_not_take_the_fall_out_of_closed_form():
    """The bulk's heights count the mass in each packing column, so a column where the
    flow converged stands far above the pile (in the paper-scale mine, hundreds of metres
    over the outlet beside the inlet). A particle falling from the inlet cannot reach it:
    it stays in closed form down to the bed under the stream. One that has hit
    something and moves sideways is checked against the whole bed."""
    width = 0.5
    column = np.array([[5.25, 1.0]])  # one column, 4 m from the inlet's stream
    column_mass = np.array([1600.0 * width * 40.0])  # 40 m of bulk by its mass
    assert surface_heights(CONTAINER, width, column, column_mass).max() == pytest.approx(40.0)
    surface = SurfaceDem(CONFIG, CONTAINER, impact_time=0.05)
    start = surface.add(np.array([7], np.uint64), np.array([100.0]))[0]
    assert start[1] < 40.0
    v0 = CONFIG.inlet_velocity
    for step in range(1, 4):
        surface.advance(0.1, width, column, column_mass)
        t = 0.1 * step
        assert surface.pos[0, 1] == pytest.approx(start[1] - v0 * t - 0.5 * G * t ** 2,
                                                  abs=1e-9)
    bed, bed_radius = surface.boundary(width, column, column_mass)
    surface.vel[0, 0] = 0.1
    assert surface._entry_heights(bed, bed_radius)[0] == pytest.approx(
        (bed[:, 1] + bed_radius).max() + CONFIG.diameter_max)


def test_the_floor_bounce_keeps_the_dems_restitution_at_the_surface_step():
    """Closing speed out/in at the floor, resolved at t_c / 5 (the surface DEM's
    step, the DEM's own): its restitution within 3 %."""
    surface = SurfaceDem(CONFIG, CONTAINER, impact_time=10.0)
    surface.add(np.array([1], np.uint64), np.array([CONFIG.sphere_mass(CONFIG.diameter_min)]))
    while surface.pos[0, 1] > 1.0:
        surface.advance(0.01, 0.5, np.empty((0, 2)), np.empty(0))
    speeds = []
    for _ in range(2000):
        surface.advance(surface.dt, 0.5, np.empty((0, 2)), np.empty(0))
        speeds.append(surface.vel[0, 1])
    speeds = np.array(speeds)
    impact = int(np.argmin(speeds))
    rebound = speeds[impact:].max()
    assert rebound / -speeds[impact] == pytest.approx(CONFIG.restitution, rel=0.03)


def test_bad_surface_options_are_refused_by_name():
    with pytest.raises(ValidationError, match="surface"):
        RomStorage(surface="sandpile")
    with pytest.raises(ValidationError, match="surface_dt_safety_factor"):
        SurfaceDem(CONFIG, CONTAINER, dt_safety_factor=2.0)
    with pytest.raises(ValidationError, match="impact_time"):
        SurfaceDem(CONFIG, CONTAINER, impact_time=0.0)


def _sink_model() -> RomModel:
    """A ROM of the 2-D point-sink funnel flow on triangular heaps (as tests/test_rom.py)."""
    rng = np.random.default_rng(1)
    x, y = GRID.centres()
    centres = np.column_stack([g.ravel() for g in np.meshgrid(x, y)])
    masses, velocities, q_out, q_in = [], [], [], []
    for _ in range(30):
        gx, gy = np.meshgrid(np.arange(-9.8, 10, 0.4), np.arange(0.2, 8, 0.4))
        height, centre = rng.uniform(4, 7.5), rng.uniform(-2, 2)
        inside = gy < height - 0.6 * np.abs(gx - centre)
        position = np.column_stack((gx[inside], gy[inside]))
        field = mass_field(GRID, position, np.full(len(position), 256.0))
        rate = rng.uniform(0, 400)
        r = np.maximum(np.linalg.norm(centres, axis=1), 0.5)
        flow = -rate / (1600.0 * np.pi * r)[:, None] * centres / r[:, None]
        masses.append(field)
        velocities.append(flow.reshape(GRID.ny, GRID.nx, 2) * (field > 0)[..., None])
        q_out.append(rate), q_in.append(rng.uniform(0, 300))
    return RomModel(GRID, 6, 6, 1e-3, CONTAINER, CONFIG.to_dict()).fit(
        np.array(masses), np.array(q_out), np.array(q_in), np.array(velocities))


def _run(model, seed, steps=30, **storage_options):
    """A heap of 256 kg particles fed 2 x 100 kg and discharged at 200 kg/s each
    second for ``steps`` s: the store, the storage, the ids received and left."""
    store = ParticleStore(capacity=4096)
    storage = RomStorage(model, rng=np.random.default_rng(seed),
                         **storage_options).bind(store, 1)
    gx, gy = np.meshgrid(np.arange(-7.8, 8, 0.4), np.arange(0.2, 6, 0.4))
    inside = gy < 5.5 - 0.6 * np.abs(gx)
    ids = store.add(mass=np.full(inside.sum(), 256.0), f=sizes.swebrec(), grade=0.3,
                    hardness=1.0, owner=1)
    storage.place(ids, np.column_stack((gx[inside], gy[inside])))
    received, left = [ids], []
    for k in range(steps):
        new = store.add(mass=np.full(2, 100.0), f=sizes.swebrec(), grade=0.7, hardness=2.0,
                        owner=1)
        storage.receive(new, float(k))
        received.append(new)
        leaving = storage.step(float(k), 1.0, 200.0)
        store.set_owner(store.slots(leaving), 2, k + 1.0)
        left.append(leaving)
    return store, storage, np.concatenate(received), np.concatenate(left)


@pytest.mark.filterwarnings("ignore::surrogate.rom.model.OutOfTrainingRange")
def test_rom_with_the_surface_dem_and_dispersion_conserves_ids_and_mass_and_repeats_itself():
    model = _sink_model()
    model.dispersivity = 0.02  # the random walk about the mean flow runs too
    store, storage, received, left = _run(model, seed=5)
    assert storage.surface_dem is not None and storage.surface == "dem"
    held = storage.held_ids()
    assert np.unique(left).size == left.size
    assert np.array_equal(np.sort(np.concatenate((left, held))), np.sort(received))
    assert store.total_mass(2) == pytest.approx(200.0 * 30, abs=256.0)
    assert store.total_mass(1) + store.total_mass(2) == pytest.approx(
        store.mass[store.slots(received)].sum(), rel=1e-12)
    # the newcomers landed on the heap near the inlet, not at its foot
    newcomers = np.setdiff1d(held, received[: received.size - 60])
    landed = store.position[store.slots(newcomers)]
    assert np.median(np.abs(landed[:, 0] - CONTAINER.inlet_x)) < 3.0
    again = _run(model, seed=5)
    assert np.array_equal(again[3], left)
    assert np.array_equal(again[0].position[again[0].slots(held)], store.position[store.slots(held)])


def _dem_newcomers_rest_x(seed: int):
    """The training DEM, a settled 30 t pile, 15 s of inflow at 200 kg/s: where each
    newcomer is 4-5 s after it entered [m from the inlet]; and the pile before it."""
    cfg = doe.training_config()
    dem, feed = doe.build_pile(cfg, 30e3, seed=seed)
    pile = dem.snapshot()
    rests = []
    for second in range(19):
        if second < 15:
            doe.emit_lots(dem, feed, 200.0)
        dem.advance(1.0)
        snap = dem.snapshot()
        rests.append(snap["position"][(snap["residence_time"] >= 4.0)
                                      & (snap["residence_time"] < 5.0), 0])
    return cfg, pile, np.concatenate(rests) - cfg.inlets[0][0]


def _surface_newcomers_rest_x(cfg, pile, impact_time: float, seed: int):
    """The ROM's surface layer on the same pile: 30 newcomers of 40-170 kg, one per 0.5 s,
    in the fixed-bed DEM for ``impact_time`` [s], then (short windows) the angle-of-repose
    rule; where they come to rest [m from the inlet]."""
    from surrogate.rom.surface import column_width, deposit, settle, surface_heights

    container = doe.container_of(cfg, doe.areal_density(pile, doe.grid_of(cfg)),
                                 doe.repose_angle(pile))
    bulk_pos, bulk_mass = pile["position"].copy(), pile["mass"]
    width = column_width(container, float(np.median(bulk_mass)))
    settle(container, width, bulk_pos, bulk_mass)
    masses = np.random.default_rng(seed).uniform(40.0, 170.0, 30)
    surface = SurfaceDem(cfg, container, impact_time=impact_time,
                         rng=np.random.default_rng(seed + 1))
    landed = []
    for k, mass in enumerate(masses):
        surface.add(np.array([k], np.uint64), np.array([mass]))
        landed.append(surface.advance(0.5, width, bulk_pos, bulk_mass)[2][:, 0])
    for _ in range(10):
        landed.append(surface.advance(0.5, width, bulk_pos, bulk_mass)[2][:, 0])
    x = np.concatenate(landed)
    if impact_time > 1.0:
        return x - container.inlet_x
    heights = surface_heights(container, width, bulk_pos, bulk_mass)
    return deposit(container, width, heights, masses[: x.size], np.random.default_rng(seed + 2),
                   landing_x=x)[:, 0] - container.inlet_x


NEWCOMER_SEEDS = (0, 1, 2, 3)


@pytest.mark.slow
def test_where_newcomers_come_to_rest_matches_the_dem_and_a_longer_dem_window_does_not():
    """Where newcomers come to rest, pooled over four piles and feeds (seeds 0-3), as the
    median distance from the inlet: the ROM's surface layer (DEM impact, then the
    angle-of-repose rule) within 1.2 m of the DEM's, and 2 s in the fixed-bed DEM at
    least 2 m further out than the DEM (why the impact window is short; see
    surrogate.rom.surface_dem).

    One pile is chaotic (its 5th percentile moved by 4 m between instruction sets, and
    the surface layer sometimes sends one feed far down a flank), so the bounds come from
    every 4-of-8 subset of seeds 0-7, compiled for this AMD EPYC and for numba's generic
    CPU (``python tests/test_rom_surface.py 0 1 2 3 4 5 6 7``): surface layer - DEM
    0.55 m (sd 0.20, largest 1.04); 2 s window - DEM 3.96 m (sd 0.65, smallest 2.37);
    DEM alone 1.0 m. The bounds are those means plus or minus three standard deviations.
    """
    dem_x, rom_x, long_x = [], [], []
    for seed in NEWCOMER_SEEDS:
        cfg, pile, rest = _dem_newcomers_rest_x(seed)
        dem_x.append(rest)
        rom_x.append(_surface_newcomers_rest_x(cfg, pile, 0.05, seed))
        long_x.append(_surface_newcomers_rest_x(cfg, pile, 2.0, seed))
    dem, rom, long = (float(np.median(np.abs(np.concatenate(x)))) for x in (dem_x, rom_x, long_x))
    assert rom - dem <= 1.2, (dem, rom, long)
    assert long - dem >= 2.0, (dem, rom, long)


def test_the_feeder_draws_across_its_opening_in_proportion_to_the_column_weights():
    """Of the packing columns over the opening, each gives mass in proportion to its
    weight (the ROM's: the field's downward speed there); weight 0 gives nothing;
    without weights the draw is even."""
    from surrogate.rom.surface import feeder_take

    container = Container(x_min=-10.0, x_max=10.0, floor=0.0, outlet_x=0.0, inlet_x=0.0,
                          areal_density=1000.0, repose_angle=0.5, outlet_width=4.0,
                          feeder_zone_height=1.0)
    rng = np.random.default_rng(5)
    centres = np.repeat(np.arange(-10.0, 10.0) + 0.5, 50)  # 20 columns of 1 m, 50 particles each
    position = np.stack([centres + rng.uniform(-0.4, 0.4, centres.size),
                         rng.uniform(0.0, 1.0, centres.size)], axis=1)
    mass = np.ones(centres.size)
    opening = slice(8, 12)  # the columns centred at -1.5, -0.5, 0.5 and 1.5 m
    weight = np.zeros(20)
    weight[opening] = [1.0, 3.0, 0.0, 2.0]
    for weights, share in ((weight, [10.0, 30.0, 0.0, 20.0]), (None, [15.0] * 4)):
        drained = np.zeros(20)
        taken, credit = feeder_take(container, 1.0, position, mass, drained, 60.0, weights)
        assert taken.size == 60 and credit == 0.0
        np.testing.assert_allclose(drained[opening], share, atol=1.0)
        assert drained.sum() == drained[opening].sum()  # nothing from beside the opening
        assert np.all(np.abs(position[taken, 0]) <= 2.0)


if __name__ == "__main__":
    import sys

    for seed in map(int, sys.argv[1:]):
        cfg, pile, rest = _dem_newcomers_rest_x(seed)
        medians = [np.median(np.abs(x)) for x in (
            rest, _surface_newcomers_rest_x(cfg, pile, 0.05, seed),
            _surface_newcomers_rest_x(cfg, pile, 2.0, seed))]
        print(seed, "median |x - inlet| [m]: DEM %.2f, surface layer %.2f, 2 s window %.2f"
              % tuple(medians), flush=True)


@pytest.mark.parametrize("spread, low, high", [(0.0, 0.0, 1.0), (3.0, 2.6, 3.4)])
def test_the_landing_spread_scatters_where_the_surface_dem_leaves_particles(spread, low, high):
    """400 particles of 10 kg left by the surface DEM at the inlet of an empty
    container: without a spread they build one small heap there (its half-width
    sqrt(4000 kg / (rho_A tan(repose))) = 1.9 m); with ``landing_spread`` = 3 m
    their x has a standard deviation of about 3 m. Measured over the storage's seeds
    0-4: 0.727-0.732 m without, 2.73-3.04 m with the spread; medians within 0.26 m of
    the inlet."""
    store = ParticleStore(capacity=512)
    storage = RomStorage(_sink_model(), rng=np.random.default_rng(3),
                         landing_spread=spread).bind(store, 1)
    ids = store.add(mass=np.full(400, 10.0), f=sizes.swebrec(), grade=0.5, hardness=1.0,
                    owner=1)
    mass = store.mass[store.slots(ids)]
    heights = surface_heights(CONTAINER, storage._column_width(mass), np.empty((0, 2)),
                              np.empty(0))  # the empty container's floor
    storage._land(ids, mass, np.column_stack((np.full(400, CONTAINER.inlet_x), np.ones(400))),
                  heights)
    x = storage._pos[:, 0]
    assert x.size == 400 and CONTAINER.x_min <= x.min() and x.max() <= CONTAINER.x_max
    assert low <= x.std() <= high
    assert abs(np.median(x) - CONTAINER.inlet_x) < 0.5


def test_a_negative_landing_spread_is_refused_by_name():
    with pytest.raises(ValidationError, match="landing_spread"):
        RomStorage(landing_spread=-1.0)
