"""The contract every registered storage model keeps (``cosim.storage``).

Plain check functions, so the parametrized suite (``test_storage_contract.py``,
one case per name in the ``minetwin.storage`` registry) and the plug-in test
(``test_storage_plugin.py``, a model installed by pip) run the same checks.

Each check builds the model by its registered name with ``make_storage(name,
rng=..., **CONTRACT_OPTIONS.get(name, {}))``: a registered model that needs no
options is tested as it is; the two that need a trained or sized state (ROM,
DEM) get small ones here so the suite stays fast.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from cosim import sizes
from cosim.particles import ParticleStore
from cosim.storage import StorageModel, make_storage, registered_models, storage_class

OWNER, OUT = 3, 4
"""Owner index of the storage in the test store, and of the particles that left."""

CAPABILITIES = ("has_geometry", "checkpointable")
"""Boolean capabilities a view or the checkpoint reads from the class."""

BINS, BIN_PARTICLES = 6, 8
"""Inflow: a bin of 8 particles (50-150 kg) in each of the first 6 steps."""

STEPS, DT, RATE = 12, 0.5, 600.0
"""Steps [-], step [s] and feeder rate [kg/s]: about 3.6 t out of 4.8 t in."""


def _rom_options(tmp: Path) -> dict:
    sys.path.insert(0, str(Path(__file__).parent))
    from test_rom_opcua import synthetic_rom

    path = tmp / "synthetic.rom.npz"
    if not path.exists():
        synthetic_rom(samples=20).save(path)
    return {"model": str(path)}


def _dem_options(tmp: Path) -> dict:
    from surrogate.dem.builders import config_for_particles

    return {"config": config_for_particles(BINS * BIN_PARTICLES).to_dict()}


CONTRACT_OPTIONS = {"rom": _rom_options, "dem": _dem_options}
"""Options of the registered models that cannot run without some (name -> builder)."""


def contract_names() -> list[str]:
    """The names the suite runs over: every registered storage model."""
    return list(registered_models())


def build(name: str, tmp: Path, seed: int = 7) -> StorageModel:
    options = CONTRACT_OPTIONS[name](tmp) if name in CONTRACT_OPTIONS else {}
    return make_storage(name, rng=np.random.default_rng(seed), **options)


def run(model: StorageModel, steps: int = STEPS, start: int = 0, store=None,
        feed_seed: int = 11):
    """Feed bins and step; return the store and per step (leaving ids, held ids)."""
    if store is None:
        store = ParticleStore()
        model.bind(store, OWNER)
    rng = np.random.default_rng(feed_seed + start)
    trace = []
    for k in range(start, start + steps):
        t = k * DT
        if k < BINS:
            ids = store.add(mass=rng.uniform(50.0, 150.0, BIN_PARTICLES), f=sizes.swebrec(),
                            grade=rng.uniform(0.0, 1.0, BIN_PARTICLES), hardness=1.0,
                            owner=OWNER, time=t)
            model.receive(ids, t)
        leaving = np.asarray(model.step(t, DT, RATE), dtype=np.uint64)
        store.set_owner(store.slots(leaving), OUT, t + DT)
        trace.append((leaving, np.sort(model.held_ids())))
    return store, trace


def check_mass_and_ids_are_conserved(name: str, tmp: Path) -> None:
    """Every id received is held or has left, exactly once; mass likewise."""
    model = build(name, tmp)
    store, trace = run(model)
    received = np.sort(store.id)  # nothing is removed from the test store
    left = np.concatenate([leaving for leaving, _ in trace])
    assert left.size, f"{name}: the feeder took nothing in {STEPS * DT} s at {RATE} kg/s"
    assert np.unique(left).size == left.size, f"{name}: a particle left twice"
    held = trace[-1][1]
    assert np.unique(held).size == held.size, f"{name}: a particle is held twice"
    assert not np.isin(left, held).any(), f"{name}: a particle left and is still held"
    np.testing.assert_array_equal(np.sort(np.concatenate((left, held))), received)
    assert (store.owner[store.slots(held)] == OWNER).all()
    total = float(store.mass.sum())
    held_mass = float(store.mass[store.slots(held)].sum())
    left_mass = float(store.mass[store.slots(left)].sum())
    assert abs(held_mass + left_mass - total) <= 1e-12 * total
    assert abs(model.held_mass() - held_mass) <= 1e-12 * total
    for (leaving, now), (_, before) in zip(trace[1:], trace[:-1]):
        assert np.isin(leaving, before).all() or np.isin(leaving, now, invert=True).all()


def check_capabilities_are_declared_class_attributes(name: str, tmp: Path) -> None:
    """Capabilities are read from the class (declared on the base with defaults)."""
    cls = storage_class(name)
    assert issubclass(cls, StorageModel)
    for capability in CAPABILITIES:
        assert capability in vars(StorageModel), capability
        assert isinstance(getattr(cls, capability), bool), f"{name}.{capability}"
    model = build(name, tmp)
    for capability in CAPABILITIES:
        assert capability not in vars(model), f"{name} sets {capability} per instance"
    store, _ = run(model, steps=3)
    held = store.slots(model.held_ids())
    if cls.has_geometry:  # its own positions, in the pile's x-y plane
        assert np.isfinite(store.position[held, :2]).all()
        assert (store.position[held, 2] == 0.0).all()
        assert np.ptp(store.position[held, 0]) > 0, f"{name}: every particle at one x"


def check_rng_seeds_the_model(name: str, tmp: Path) -> None:
    """``rng`` keyword: same seed, same result (ids, order and positions)."""
    first, second = build(name, tmp, seed=5), build(name, tmp, seed=5)
    store_a, trace_a = run(first)
    store_b, trace_b = run(second)
    for (leave_a, held_a), (leave_b, held_b) in zip(trace_a, trace_b):
        np.testing.assert_array_equal(leave_a, leave_b)
        np.testing.assert_array_equal(held_a, held_b)
    np.testing.assert_array_equal(first.held_ids(), second.held_ids())
    np.testing.assert_array_equal(store_a.position, store_b.position)
    rng = np.random.default_rng(1)
    assert build_with_rng(name, tmp, rng).rng is rng


def build_with_rng(name: str, tmp: Path, rng) -> StorageModel:
    options = CONTRACT_OPTIONS[name](tmp) if name in CONTRACT_OPTIONS else {}
    return make_storage(name, rng=rng, **options)


def check_checkpoint_restores_exactly(name: str, tmp: Path) -> None:
    """A model that declares ``checkpointable`` goes on, after a save and a load of the
    stockpile checkpoint, exactly as the one that was saved."""
    from surrogate.checkpoint import load_checkpoint, save_checkpoint

    model = build(name, tmp)
    if not type(model).checkpointable:
        return
    store, _ = run(model, steps=4)
    path = tmp / f"{name}.checkpoint"
    save_checkpoint(path, {"store": store, "model": model})
    restored = load_checkpoint(path)
    assert type(restored["model"]) is type(model)
    _, go_on = run(model, steps=6, start=4, store=store)
    _, resumed = run(restored["model"], steps=6, start=4, store=restored["store"])
    for (leave_a, held_a), (leave_b, held_b) in zip(go_on, resumed):
        np.testing.assert_array_equal(leave_a, leave_b)
        np.testing.assert_array_equal(held_a, held_b)
    np.testing.assert_array_equal(store.position, restored["store"].position)


def check_prediction_is_of_held_particles(name: str, tmp: Path) -> None:
    """``predict``: ids held, each share within its particle's mass, no more than held."""
    model = build(name, tmp)
    store, _ = run(model, steps=4)
    ids, share = model.predict(5.0, RATE)
    held = model.held_ids()
    assert np.isin(ids, held).all()
    assert (share >= 0).all() and (share <= store.mass[store.slots(ids)] + 1e-9).all()
    assert share.sum() <= model.held_mass() * (1 + 1e-12)
    assert share.sum() > 0


def check_feed_profile_grows_with_the_horizon(name: str, tmp: Path) -> None:
    """``predict_each``: one feed per horizon, of held particles, the mass never
    less for a longer horizon, the longest one ``predict``'s exactly."""
    model = build(name, tmp)
    run(model, steps=4)
    horizons = [1.0, 2.5, 5.0]
    profile = model.predict_each(horizons, RATE)
    assert len(profile) == len(horizons)
    masses = [share.sum() for _, share in profile]
    assert masses == sorted(masses) and masses[0] > 0
    assert all(np.isin(ids, model.held_ids()).all() for ids, _ in profile)
    ids, share = model.predict(5.0, RATE)
    np.testing.assert_array_equal(profile[-1][0], ids)
    np.testing.assert_array_equal(profile[-1][1], share)


CONTRACT = (check_mass_and_ids_are_conserved, check_capabilities_are_declared_class_attributes,
            check_rng_seeds_the_model, check_checkpoint_restores_exactly,
            check_prediction_is_of_held_particles, check_feed_profile_grows_with_the_horizon)
"""The checks every registered storage model passes."""
