"""Scoring against an ensemble of DEM replicas (``surrogate.rom.evaluate``): every model
against each replica, mean and spread; the noise floor over every pair of replicas."""

import numpy as np
import pytest

from cosim.errors import ValidationError
from surrogate.rom import evaluate


def _outflow(order, seconds=120.0):
    """Particles 1..n leaving one per second in ``order`` (ids), 100 kg each."""
    ids = np.asarray(order, dtype=np.uint64)
    return {"time": np.arange(1.0, ids.size + 1.0) * seconds / ids.size,
            "tracking_id": ids, "mass": np.full(ids.size, 100.0),
            "grade": ids.astype(np.float64) / ids.size, "hardness": np.ones(ids.size)}


def test_a_model_is_scored_against_each_replica_and_the_floor_against_every_pair():
    rng = np.random.default_rng(3)
    base = np.arange(1, 121)
    replicas = [_outflow(base)]
    for _ in range(2):                   # replicas: the same lots, locally reordered
        order = base.copy()
        for start in range(0, 120, 10):
            rng.shuffle(order[start:start + 20])
        replicas.append(_outflow(order))
    model = _outflow(base[::-1])         # a model that gets the order backwards
    t0, t1 = 0.0, 120.0
    scored = evaluate.ensemble_score(model, replicas, t0, t1)
    each = [evaluate.score(model, r, t0, t1)["tracking_error"] for r in replicas]
    assert scored["tracking_error"] == pytest.approx(np.mean(each), rel=1e-12)
    spread = scored["tracking_error_spread"]
    assert spread["n"] == 3 and spread["min"] == min(each) and spread["max"] == max(each)
    assert spread["std"] == pytest.approx(np.std(each, ddof=1), rel=1e-12)
    floor = evaluate.noise_floor(replicas, t0, t1)
    pairs = [evaluate.score(replicas[j], replicas[i], t0, t1)["tracking_error"]
             for i, j in ((0, 1), (0, 2), (1, 2))]
    assert floor["tracking_error_spread"]["n"] == 3
    assert floor["tracking_error"] == pytest.approx(np.mean(pairs), rel=1e-12)
    assert 0.0 < floor["tracking_error"] < scored["tracking_error"]
    with pytest.raises(ValidationError, match="at least 2 DEM replicas"):
        evaluate.noise_floor(replicas[:1], t0, t1)


def test_the_replicas_keep_the_reference_and_perturbed_runs_names():
    assert evaluate.replica_names(evaluate.DEM_REPLICAS)[:2] == ["dem", "dem_perturbed"]
    assert evaluate.replica_names(4) == ["dem", "dem_perturbed", "dem_replica2",
                                         "dem_replica3"]
    assert evaluate.DEM_REPLICAS >= 3


def test_the_pass_conditions_hold_or_fail_at_their_bounds():
    scenario = {"tracking_error": {"fifo": 0.8, "mixing": 0.7, "rom": 0.10},
                "tracking_error_dem_noise_floor": 0.081, "speedup_vs_dem": 100.0,
                "wall_s_per_simulated_s": {"rom": 1 / 20.0}}
    assert all(evaluate._targets(scenario).values())
    worse = dict(scenario, tracking_error={"fifo": 0.8, "mixing": 0.7, "rom": 0.1001},
                 tracking_error_dem_noise_floor=0.05, speedup_vs_dem=99.9,
                 wall_s_per_simulated_s={"rom": 1 / 19.9})
    assert not any(value for key, value in evaluate._targets(worse).items()
                   if key != "tracking_error_below_fifo_and_mixing")
    assert evaluate._targets(dict(scenario, tracking_error={
        "fifo": 0.8, "mixing": 0.10, "rom": 0.10}))["tracking_error_below_fifo_and_mixing"] is False
