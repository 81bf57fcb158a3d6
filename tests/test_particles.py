import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from cosim import sizes
from cosim.errors import ValidationError
from cosim.particles import NO_OWNER, ParticleStore

F = sizes.swebrec()


def make_store(n=10, **kw):
    store = ParticleStore(capacity=4)
    ids = store.add(mass=np.arange(1, n + 1, dtype=float), f=F, grade=0.5, hardness=1.0, **kw)
    return store, ids


def test_add_returns_sequential_ids_and_grows():
    store, ids = make_store(100)
    assert ids.dtype == np.uint64
    assert list(ids) == list(range(100))
    assert len(store) == 100
    assert store.total_mass() == pytest.approx(5050.0)
    assert np.allclose(store.f.sum(axis=1), 1.0)


def test_remove_keeps_rows_dense_and_ids_reachable():
    store, ids = make_store(10)
    store.remove([0, 5, 9])
    assert len(store) == 7
    assert sorted(store.id.tolist()) == [1, 2, 3, 4, 6, 7, 8]
    slots = store.slots([8, 1])
    assert store.mass[slots].tolist() == [9.0, 2.0]
    with pytest.raises(ValidationError, match="id: must be"):
        store.slots([5])


def test_owner_iteration_and_transfer():
    store, ids = make_store(6, owner=[0, 1, 0, 2, 1, 0])
    groups = {o: sorted(store.id[s].tolist()) for o, s in store.by_owner()}
    assert groups == {0: [0, 2, 5], 1: [1, 4], 2: [3]}
    store.set_owner(store.slots([3]), 1, time=5.0)
    assert store.total_mass(1) == pytest.approx(2 + 5 + 4)
    assert store.time_in_owner[store.slots([3])][0] == 5.0


def test_extrinsic_attributes():
    store, ids = make_store(3)
    store.add_attribute("mwd")
    assert np.isnan(store.attribute("mwd")).all()
    store.attribute("mwd")[:] = [1, 2, 3]
    store.add(mass=1.0, f=F, grade=0.1, hardness=2.0, mwd=7.0)
    assert store.attribute("mwd").tolist() == [1, 2, 3, 7]
    store.add_attribute("tracking_id", np.uint64, 0)
    assert store.attribute("tracking_id").dtype == np.uint64
    with pytest.raises(ValidationError, match="attributes"):
        store.add(mass=1.0, f=F, grade=0.1, hardness=2.0, colour=1.0)
    with pytest.raises(ValidationError, match="attribute"):
        store.attribute("nope")


@pytest.mark.parametrize("kwargs, field", [
    (dict(mass=[1.0, -1.0]), "mass"),
    (dict(mass=[1.0, np.nan]), "mass"),
    (dict(mass=[1.0, 0.0]), "mass"),
    (dict(grade=[0.5, 1.5]), "grade"),
    (dict(grade=[0.5, -0.1]), "grade"),
    (dict(hardness=[1.0, 0.0]), "hardness"),
    (dict(hardness=[1.0, np.inf]), "hardness"),
    (dict(f=np.full(16, 0.1)), "f"),
    (dict(position=[[0, 0, np.nan], [0, 0, 0]]), "position"),
    (dict(grade=[0.1, 0.2, 0.3]), "grade"),
])
def test_bad_batches_are_refused_and_leave_the_store_unchanged(kwargs, field):
    store, _ = make_store(5)
    before = store.gather()
    batch = dict(mass=[1.0, 2.0], f=F, grade=0.5, hardness=1.0)
    batch.update(kwargs)
    with pytest.raises(ValidationError, match=f"^{field}: must be"):
        store.add(**batch)
    after = store.gather()
    assert all(np.array_equal(before[k], after[k]) for k in before)
    assert store.add(mass=1.0, f=F, grade=0.5, hardness=1.0)[0] == 5


def test_explicit_ids_round_trip_through_batches():
    source, _ = make_store(5)
    source.add_attribute("tracking_id", np.uint64, 0)
    source.attribute("tracking_id")[:] = 42
    batch = source.gather(source.slots([1, 3]))
    target = ParticleStore()
    ids = target.add_batch(batch)
    assert ids.tolist() == [1, 3]
    assert target.attribute("tracking_id").tolist() == [42, 42]
    with pytest.raises(ValidationError, match="ids"):
        target.add_batch(batch)
    assert len(target) == 2


def test_where_and_gather():
    store, _ = make_store(10)
    heavy = store.where(store.mass > 7)
    assert heavy.tolist() == [7, 8, 9]
    frame = store.to_dataframe(store.slots(heavy))
    assert list(frame["id"]) == [7, 8, 9]
    assert "f15" in frame and "x" in frame and "origin_x" in frame


ops = st.lists(st.one_of(
    st.tuples(st.just("add"), st.integers(1, 20), st.integers(0, 3)),
    st.tuples(st.just("remove"), st.integers(0, 1000), st.integers(0, 20)),
    st.tuples(st.just("move"), st.integers(0, 1000), st.integers(0, 3)),
), max_size=40)


@settings(max_examples=60, deadline=None)
@given(ops)
def test_no_id_or_kilogram_is_lost_or_duplicated(operations):
    store = ParticleStore(capacity=2)
    rng = np.random.default_rng(0)
    alive: dict[int, float] = {}
    for op, a, b in operations:
        if op == "add":
            masses = rng.uniform(1, 100, a)
            ids = store.add(mass=masses, f=F, grade=0.3, hardness=1.0, owner=b)
            alive.update(zip(ids.tolist(), masses.tolist()))
        elif op == "remove" and alive:
            keys = sorted(alive)
            chosen = {keys[(a + k * 7) % len(keys)] for k in range(min(b, len(keys)))}
            store.remove(list(chosen))
            for key in chosen:
                del alive[key]
        elif op == "move" and len(store):
            store.set_owner(store.slots(store.where(store.owner == b % 4)), (b + 1) % 4, 1.0)
        assert len(store) == len(alive)
        assert sorted(store.id.tolist()) == sorted(alive)
        assert len(set(store.id.tolist())) == len(store)
        assert store.total_mass() == pytest.approx(sum(alive.values()), rel=1e-12)
        if alive:
            key = next(iter(alive))
            assert store.mass[store.slots([key])][0] == alive[key]
        assert np.all((store.f >= 0) & (store.f <= 1))
        assert np.allclose(store.f.sum(axis=1), 1.0, atol=1e-12)
        assert sum(len(s) for _, s in store.by_owner()) == len(store)


def test_one_million_particles_fit():
    store = ParticleStore(capacity=1024)
    ids = store.add(mass=np.full(1_000_000, 100.0), f=F, grade=0.5, hardness=1.0,
                    owner=NO_OWNER)
    assert len(store) == 1_000_000
    store.remove(ids[::2])
    assert len(store) == 500_000
    assert store.total_mass() == pytest.approx(5e7)
