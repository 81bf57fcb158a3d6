import numpy as np
import pytest

from cosim import sizes
from cosim.errors import ValidationError
from cosim.particles import ParticleStore
from cosim.storage import FifoStorage, MixingStorage, make_storage

STORAGE = 7


def filled(model, n=50, seed=0):
    rng = np.random.default_rng(seed)
    store = ParticleStore()
    ids = store.add(mass=rng.uniform(50, 150, n), f=sizes.swebrec(),
                    grade=np.linspace(0, 1, n), hardness=1.0, owner=STORAGE)
    model.bind(store, STORAGE)
    model.receive(ids, 0.0)
    return store, ids


@pytest.mark.parametrize("name", ["fifo", "mixing"])
def test_discharge_follows_rate_within_one_particle_and_conserves(name):
    model = make_storage(name)
    store, ids = filled(model)
    total = store.total_mass()
    out = []
    for k in range(100):
        leaving = model.step(k * 0.5, 0.5, 100.0)
        out.extend(leaving.tolist())
        store.set_owner(store.slots(leaving), 8, k * 0.5)
        left = store.total_mass(8)
        assert abs(left - 100.0 * 0.5 * (k + 1)) < 150.0 or model.held_ids().size == 0
    assert len(out) == len(set(out))
    assert store.total_mass(8) + model.held_mass() == pytest.approx(total, rel=1e-12)
    assert sorted(out + model.held_ids().tolist()) == sorted(ids.tolist())


def test_fifo_is_first_in_first_out():
    model = FifoStorage()
    store, ids = filled(model)
    leaving = model.step(0.0, 10.0, 200.0)
    assert leaving.tolist() == ids[: leaving.size].tolist()


def test_mixing_is_seeded_and_mixes():
    a = MixingStorage(rng=np.random.default_rng(5))
    b = MixingStorage(rng=np.random.default_rng(5))
    _, ids = filled(a)
    filled(b)
    assert a.held_ids().tolist() == b.held_ids().tolist()
    assert a.held_ids().tolist() != ids.tolist()


@pytest.mark.parametrize("name", ["fifo", "mixing"])
def test_prediction_covers_the_horizon(name):
    model = make_storage(name)
    store, _ = filled(model)
    ids, mass = model.predict(30.0, 20.0)
    assert mass.sum() == pytest.approx(600.0)
    assert np.all(mass <= store.mass[store.slots(ids)] + 1e-9)


def test_bad_rate_and_name():
    model = FifoStorage()
    filled(model)
    with pytest.raises(ValidationError, match="discharge_rate"):
        model.step(0, 1, 2500.0)
    with pytest.raises(ValidationError, match="discharge_rate"):
        model.step(0, 1, float("nan"))
    with pytest.raises(ValidationError, match="storage_model"):
        make_storage("magic")
