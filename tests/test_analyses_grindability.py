"""Bond work index, block reconciliation and its sensitivity on synthetic mill data.

The synthetic mill is built with the foundation: particles from a quadratic
hardness source (10 blocks of 10 m) and a constant-hardness source enter the
mill in alternating loads and leave as product after an exponential
residence time; an EventStore records ``enter`` and ``product`` events. The
grindability observed at the mill is that of its content: G = 1 / BWI with
BWI the mass-weighted mean of 12 kWh/t * h over the particles in the mill,
computed directly from the store at each sample, not by the code under test.
"""

import numpy as np
import pandas as pd
import pytest

from cosim.analyses import grindability, sensitivity
from cosim.blockmodel import ConstantHardness, QuadraticHardness
from cosim.errors import ValidationError
from cosim.events import EventStore
from cosim.particles import ParticleStore
from cosim.sizes import blasted_fractions, d_passing

MILL, GONE = 1, 2


def test_bond_work_index_uses_the_corrected_units():
    # Bond: W[kWh/t] = BWI (10/sqrt(P80[um]) - 10/sqrt(F80[um])) with BWI = 15 kWh/t,
    # F80 = 2000 um, P80 = 75 um; 1 kWh/t = 3600 J/kg
    w_kwh_t = 15.0 * (10 / np.sqrt(75.0) - 10 / np.sqrt(2000.0))
    bwi = grindability.bond_work_index(w_kwh_t * 3600.0, 2e-3, 75e-6)
    assert bwi == pytest.approx(15.0, rel=1e-12)
    assert np.isnan(grindability.bond_work_index(1.0, 1e-4, 2e-4))   # no reduction


def test_bond_signals_from_events():
    rng = np.random.default_rng(0)
    store = ParticleStore()
    events = EventStore(":memory:")
    f_in = blasted_fractions(rng, 1, x50=0.004, x_max=0.02)[0]
    f_out = blasted_fractions(rng, 1, x50=5e-5, x_max=1e-3)[0]
    for k in range(60):                 # 100 kg in and out every second
        t = float(k)
        ids = store.add(mass=100.0, f=f_in, grade=0.5, hardness=1.0, owner=MILL, time=t)
        events.record("enter", "mill", t, store, store.slots(ids))
        store.f[store.slots(ids)] = f_out
        events.record("product", "mill", t, store, store.slots(ids))
    times = np.arange(0.0, 60.0, 1.0)
    table = events.particles()
    signals = grindability.bond_signals(times, np.full(times.size, 2.0e6),
                                        table[table.type == "enter"],
                                        table[table.type == "product"], window=10.0)
    late = signals[signals.time >= 10]
    np.testing.assert_allclose(late.product_rate_kg_s, 100.0)
    np.testing.assert_allclose(late.work_j_kg, 2.0e4)
    np.testing.assert_allclose(late.f80_m, d_passing(f_in, 0.8))
    expected = 2.0e4 / (3.6 * (10 / np.sqrt(d_passing(f_out, 0.8))
                               - 10 / np.sqrt(d_passing(f_in, 0.8))))
    np.testing.assert_allclose(late.bwi_kwh_t, expected)
    np.testing.assert_allclose(late.grindability_t_kwh, 1 / expected)


def mill_scene(seed: int, *, loads: int = 40, dt: float = 1.0, mean_residence: float = 60.0):
    """Synthetic mill fed by alternating loads; returns signals, feed, product, x, store."""
    rng = np.random.default_rng(seed)
    store = ParticleStore()
    events = EventStore(":memory:")
    left, right = QuadraticHardness(0.0, 100.0), ConstantHardness(1.0)
    advance = 100.0 / (loads // 2)
    leave_at = {}
    times, observed, held = [], [], []
    t, load = 0.0, 0
    while t < loads * 30.0 + 300.0:
        t += dt
        if load < loads and t >= load * 30.0:
            n = 150
            if load % 2 == 0:
                x = (load // 2) * advance + rng.uniform(0, advance, n)
                h, source = left(x), "left"
            else:
                x = 200.0 + rng.uniform(0, 2.0, n)
                h, source = right(x), "right"
            ids = store.add(mass=rng.uniform(50, 150, n), f=blasted_fractions(rng, n),
                            grade=0.5, hardness=h, owner=MILL, time=t,
                            position=np.column_stack((x, np.zeros(n), np.zeros(n))))
            events.record("appear", source, t, store, store.slots(ids))
            events.record("enter", "mill", t, store, store.slots(ids))
            for i, r in zip(ids, rng.exponential(mean_residence, n)):
                leave_at[int(i)] = t + r
            load += 1
        in_mill = np.flatnonzero(store.owner == MILL)
        due = in_mill[np.array([leave_at[int(i)] <= t for i in store.id[in_mill]], dtype=bool)]
        if due.size:
            events.record("product", "mill", t, store, due)
            store.set_owner(due, GONE, t)
        in_mill = store.owner == MILL
        m = store.mass[in_mill]
        times.append(t)
        held.append(m.sum())
        observed.append(1.0 / (12.0 * (m @ store.hardness[in_mill]) / m.sum())
                        if m.sum() > 0 else np.nan)
    table = events.particles()
    signals = pd.DataFrame({"time": times, "grindability_t_kwh": observed,
                            "mass_in_mill": held})
    feed, product = table[table.type == "enter"], table[table.type == "product"]
    appear = table[(table.type == "appear") & (table.asset == "left")]
    x = pd.Series(appear["x"].to_numpy(), index=appear["particle_id"].to_numpy())
    return signals, feed, product, x, table


def block_setup(table, x):
    block_of = pd.Series(grindability.block_index(x.to_numpy(), 0.0, 10.0, 10), index=x.index)
    appear = table[table.type == "appear"].set_index("particle_id")
    blocks = block_of.reindex(appear.index)
    mass = appear["mass"].groupby(blocks).sum().reindex(range(10)).to_numpy()
    hard = ((appear["mass"] * appear["hardness"]).groupby(blocks).sum()
            .reindex(range(10)).to_numpy() / mass)
    return block_of, mass, hard


def test_block_grindability_inversely_related_to_hardness():
    signals, feed, product, x, table = mill_scene(0)
    block_of, mass, hard = block_setup(table, x)
    result = grindability.backtrack(signals, feed, product, block_of, mass, window=30.0)
    enough = result["alpha_sum"][-1] >= 0.1
    assert enough.sum() == 10
    corr = np.corrcoef(result["final"], hard)[0, 1]
    assert corr <= -0.8, corr
    # the reconciled values move away from the flat prior towards 1/(12 h)
    truth = 1.0 / (12.0 * hard)
    assert np.mean(np.abs(result["final"] - truth)) < np.mean(np.abs(result["prior"] - truth))


def test_mill_mass_by_block_balances():
    signals, feed, product, x, table = mill_scene(1, loads=6)
    block_of, mass, _ = block_setup(table, x)
    times = signals["time"].to_numpy()
    per_block, total = grindability.mill_mass_by_block(times, feed, product, block_of, 10)
    np.testing.assert_allclose(total, signals["mass_in_mill"], rtol=1e-9, atol=1e-6)
    assert np.all(per_block.sum(axis=1) <= total + 1e-6)
    assert per_block.sum() > 0


def test_reconcile_weights_follow_the_paper():
    g = np.array([2.0, np.nan, 4.0])
    mi = np.array([[10.0, 0.0], [10.0, 5.0], [0.0, 20.0]])
    m = np.array([20.0, 20.0, 40.0])
    m0 = np.array([100.0, 50.0])
    hist, alpha_sum = grindability.reconcile(g, mi, m, m0, prior=1.0, alpha0=0.1)
    a0 = 10.0 ** 2 / (100.0 * 20.0)           # block 0 at k=1
    assert hist[0, 0] == pytest.approx((0.1 * 1.0 + a0 * 2.0) / (0.1 + a0))
    assert hist[1, 1] == pytest.approx(1.0)   # NaN observation: prior kept
    a1 = 20.0 ** 2 / (50.0 * 40.0)
    assert hist[2, 1] == pytest.approx((0.1 + a1 * 4.0) / (0.1 + a1))
    assert alpha_sum[2, 0] == pytest.approx(a0)
    with pytest.raises(ValidationError, match="block_mass"):
        grindability.reconcile(g, mi, m, np.array([0.0, 1.0]), prior=1.0)


def test_sensitivity_degrades_with_location_error():
    signals, feed, product, x, table = mill_scene(0)
    block_of, mass, hard = block_setup(table, x)
    sweep = sensitivity.grindability_sensitivity(
        signals, feed, product, x, start=0.0, block_length=10.0, n_blocks=10,
        block_mass=mass, block_hardness=hard, dxs=[0.0, 25.0], seeds=[1, 2])
    at0 = sweep[sweep.dx == 0]
    at25 = sweep[sweep.dx == 25]
    assert np.allclose(at0.rel_deviation, 0.0)
    assert (at25.rel_deviation > 0.005).all()
    assert at25["corr"].mean() > at0["corr"].mean()   # less inversely related
    with pytest.raises(ValidationError, match="dxs"):
        sensitivity.grindability_sensitivity(
            signals, feed, product, x, start=0.0, block_length=10.0, n_blocks=10,
            block_mass=mass, block_hardness=hard, dxs=[-1.0], seeds=[1])


def test_sensitivity_points_on_a_process_pool_equal_the_serial_sweep():
    """The sweep's points as a batch (cosim.batch) on 2 processes: the same frame,
    row for row and bit for bit, as one after the other in this process."""
    from cosim import batch

    signals, feed, product, x, table = mill_scene(0, loads=10)
    _, mass, hard = block_setup(table, x)
    options = dict(start=0.0, block_length=10.0, n_blocks=10, block_mass=mass,
                   block_hardness=hard, dxs=[0.0, 12.5, 25.0], seeds=[1, 2])
    serial = sensitivity.grindability_sensitivity(signals, feed, product, x, **options)
    with batch.LocalExecutor(2) as executor:
        pooled = sensitivity.grindability_sensitivity(signals, feed, product, x,
                                                      executor=executor, **options)
    assert list(zip(serial.dx, serial.seed)) == [(d, s) for d in (0.0, 12.5, 25.0)
                                                 for s in (1, 2)]
    pd.testing.assert_frame_equal(serial, pooled, check_exact=True)
    assert serial.attrs["failed"] == pooled.attrs["failed"] == []
