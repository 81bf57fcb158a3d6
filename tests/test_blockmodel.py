import numpy as np
import pytest

from cosim.blockmodel import (BlockModel, ConstantHardness, QuadraticHardness,
                              StepHardness, hardness_function, mwd_signal)
from cosim.errors import ValidationError


def test_hardness_profiles():
    assert ConstantHardness(1.0)(np.arange(3)).tolist() == [1, 1, 1]
    assert StepHardness(at=20)(np.array([0, 19.9, 20, 50])).tolist() == [1, 1, 2, 2]
    q = QuadraticHardness(0, 100, 1, 2)
    assert q(np.array([0, 50, 100])).tolist() == [1, 2, 1]
    assert np.all((q(np.linspace(-10, 110, 200)) >= 1) & (q(np.linspace(-10, 110, 200)) <= 2))
    assert hardness_function({"kind": "step", "at": 5}) == StepHardness(at=5)
    with pytest.raises(ValidationError, match="hardness.kind"):
        hardness_function({"kind": "cubic"})


def test_mwd_signal_with_and_without_location_error():
    q = QuadraticHardness(0, 100)
    x = np.linspace(0, 100, 1001)
    exact = mwd_signal(q, x, beta=0.4)
    assert np.allclose(exact, q(x) ** 0.4)
    noisy1 = mwd_signal(q, x, beta=0.4, location_error=12.5, rng=np.random.default_rng(7))
    noisy2 = mwd_signal(q, x, beta=0.4, location_error=12.5, rng=np.random.default_rng(7))
    assert np.array_equal(noisy1, noisy2)
    assert not np.allclose(noisy1, exact)
    assert np.abs(noisy1 - exact).max() < 2 ** 0.4 - 1 + 1e-9
    with pytest.raises(ValidationError, match="rng"):
        mwd_signal(q, x, location_error=1.0)


def test_block_model_grid():
    model = BlockModel.along(0.0, 100.0, 10.0, hardness=QuadraticHardness(0, 100), grade=0.2)
    assert model.n_cells == 10
    assert model.centres[:, 0].tolist() == [5, 15, 25, 35, 45, 55, 65, 75, 85, 95]
    assert model.cell_of([[0.1, 1, 1], [99.9, 1, 1], [100.1, 1, 1], [-1, 0, 0]]).tolist() == \
        [0, 9, -1, -1]
    assert np.allclose(model.properties["grindability"], 1 / model.properties["hardness"])
    assert model.masses[0] == pytest.approx(2700 * 10 * 20 * 10)
    grid = BlockModel(origin=(0, 0, 0), cell_size=(1, 2, 3), shape=(2, 3, 4))
    centres = grid.centres
    assert np.array_equal(grid.cell_of(centres), np.arange(24))
    with pytest.raises(ValidationError, match="cell_size"):
        BlockModel(origin=(0, 0, 0), cell_size=(1, 0, 1), shape=(1, 1, 1))
