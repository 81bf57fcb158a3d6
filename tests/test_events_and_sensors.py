import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings, strategies as st

from cosim import sizes
from cosim.errors import ValidationError
from cosim.events import EventStore
from cosim.particles import ParticleStore
from cosim.sensors import Box, VirtualSensor, observe


def store_with(n, rng):
    store = ParticleStore()
    store.add(mass=rng.uniform(10, 150, n), f=sizes.blasted_fractions(rng, n),
              grade=rng.uniform(0, 1, n), hardness=rng.uniform(1, 2, n),
              position=rng.uniform(0, 10, (n, 3)), owner=rng.integers(0, 3, n))
    return store


def test_event_store_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    particles = store_with(20, rng)
    path = tmp_path / "events.sqlite"
    with EventStore(path) as events:
        events.record("appear", "source_left", 0.0, particles, np.arange(10))
        events.record("load", "truck_1", 5.0, particles, np.arange(10), location=(1, 2, 0))
        events.record("dump", "truck_1", 60.0, particles, np.arange(5))
        with pytest.raises(ValidationError, match="type"):
            events.record("teleport", "x", 1.0, particles, [0])
    with EventStore(path) as events:
        frame = events.events()
        assert frame["type"].tolist() == ["appear", "load", "dump"]
        assert events.events(t0=1.0, t1=100.0)["type"].tolist() == ["load", "dump"]
        assert len(events.events(asset="truck_1")) == 2
        history = events.history(3)
        assert history["type"].tolist() == ["appear", "load", "dump"]
        assert history["mass"].iloc[0] == particles.mass[3]
        assert np.allclose(history[[f"f{k}" for k in range(16)]].iloc[0], particles.f[3])
        assert len(events.particles(type="load")) == 10
        ev, pa = events.to_parquet(tmp_path / "pq")
        assert len(pd.read_parquet(pa)) == 25
        assert events.record("pass", "jaw", 70.0, particles, [1]) == 3


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 200), st.integers(0, 10_000))
def test_sensor_over_all_particles_equals_plain_mass_weighted_mean(n, seed):
    store = store_with(n, np.random.default_rng(seed))
    expected = np.sum(store.mass * store.grade) / store.mass.sum()
    assert observe(store, "grade") == pytest.approx(expected, rel=1e-12)
    everything = Box((-1, -1, -1), (11, 11, 11))
    assert observe(store, "grade", box=everything) == pytest.approx(expected, rel=1e-12)
    f = observe(store, "f", box=everything)
    assert np.allclose(f, store.mass @ store.f / store.mass.sum())


def test_sensor_by_owner_and_box_and_moving_average():
    rng = np.random.default_rng(1)
    store = store_with(300, rng)
    owned = store.owner == 1
    expected = np.sum(store.mass[owned] * store.hardness[owned]) / store.mass[owned].sum()
    assert observe(store, "hardness", owner=1) == pytest.approx(expected)
    box = Box((0, 0, 0), (5, 5, 5))
    inside = box.contains(store.position)
    expected = np.sum(store.mass[inside] * store.grade[inside]) / store.mass[inside].sum()
    assert observe(store, "grade", box=box) == pytest.approx(expected)
    assert np.isnan(observe(store, "grade", box=Box((20, 20, 20), (30, 30, 30))))

    sensor = VirtualSensor("grade", owner=2, window=10.0)
    store.grade[store.owner == 2] = 0.2
    assert sensor.sample(store, 0.0) == pytest.approx(0.2)
    store.grade[store.owner == 2] = 0.4
    assert sensor.sample(store, 5.0) == pytest.approx(0.3)
    assert sensor.sample(store, 10.0) == pytest.approx(0.4)
    size_sensor = VirtualSensor("f", owner=2)
    size_sensor.sample(store, 0.0)
    assert 0.01 < size_sensor.d80 < 1.0
