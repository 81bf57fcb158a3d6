"""Hand-overs between storage models (cosim.handover): the pile moves exactly.

From a model without geometry (FIFO) to the DEM the pile is laid out by its order
of leaving and dropped to rest: the DEM then runs without blowing up, holds every
id with its mass and attributes, and the next particles to leave are those FIFO
would have sent first (they lie nearest the outlet). Back to FIFO, the order of
leaving is the DEM's.
"""

import numpy as np
import pytest

from cosim import sizes
from cosim.handover import hand_over
from cosim.particles import ParticleStore
from cosim.storage import make_storage

OWNER = 2
CONFIG = {"floor_width": 20.0, "inlets": [[0.0, 9.0]], "outlets": [0.0], "outlet_width": 3.0,
          "side_wall_height": 8.0, "diameter_min": 0.4, "diameter_max": 0.6,
          "normal_stiffness": 8.0e6, "rolling_resistance": 0.2}


def _fifo_pile(n=300, seed=3):
    rng = np.random.default_rng(seed)
    store = ParticleStore(first_id=100)
    store.add_attribute("tracking_id", np.uint64, 0)
    ids = store.add(mass=rng.uniform(150, 250, n), f=sizes.swebrec(),
                    grade=rng.uniform(0, 1, n), hardness=rng.uniform(1, 2, n), owner=OWNER,
                    tracking_id=np.arange(n) // 10)
    fifo = make_storage("fifo").bind(store, OWNER)
    fifo.receive(ids, 0.0)
    fifo.step(0.0, 1.0, 130.0)  # a partial particle of credit is owed
    return store, fifo


def test_a_fifo_pile_handed_to_the_dem_lies_in_its_order_of_leaving_and_settles():
    store, fifo = _fifo_pile()
    order, credit = fifo.held_ids().copy(), fifo.feeder_credit_kg
    mass = store.total_mass(OWNER)
    dem = make_storage("dem", config=CONFIG, rng=np.random.default_rng(1))
    handed = hand_over(fifo, dem, 1.0)
    assert np.array_equal(handed, order)
    assert dem.feeder_credit_kg == pytest.approx(credit)
    assert np.array_equal(np.sort(dem.dem.id), np.sort(order))
    slots = store.slots(dem.dem.id)
    np.testing.assert_array_equal(dem.dem.mass, store.mass[slots])
    np.testing.assert_array_equal(dem.dem.tracking_id, store.attribute("tracking_id")[slots])
    assert dem.held_mass() == pytest.approx(mass, rel=1e-12)
    assert dem.dem.max_overlap_ratio() < 0.05
    # the first tenth to leave by FIFO lies lower and nearer the outlet than the last tenth
    position = dict(zip(dem.dem.id.tolist(), dem.dem.pos.tolist()))
    first, last = ([np.hypot(*position[i]) for i in part.tolist()]
                   for part in (order[:30], order[-30:]))
    assert np.median(first) < np.median(last)
    left = [dem.step(1.0 + k, 1.0, 200.0) for k in range(3)]  # runs on: no blow-up
    gone = np.concatenate(left)
    assert gone.size and np.unique(gone).size == gone.size
    store.set_owner(store.slots(gone), OWNER + 1, 4.0)
    assert dem.held_mass() + store.mass[store.slots(gone)].sum() == pytest.approx(mass, rel=1e-12)
    back = make_storage("fifo")
    held = dem.held_ids().copy()
    hand_over(dem, back, 4.0)
    assert np.array_equal(back.held_ids(), held)  # the DEM's order of leaving, kept
    assert back.held_mass() == pytest.approx(dem.held_mass(), rel=1e-12)
