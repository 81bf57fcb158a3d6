"""Bulk dispersion of the ROM: measured from displacements, applied as a random walk."""

import numpy as np
import pytest

from surrogate.rom.dispersion import dispersion_fit, dispersivity, disperse
from surrogate.rom.grid import Grid

GRID = Grid.covering(0.0, 20.0, 0.0, 10.0, 1.0)


def test_the_fit_recovers_the_dispersivity_of_a_random_walk_in_a_shear_flow():
    """Particles in a shear flow u(y) = 0.2 y m/s whose random walk has
    D = alpha |u|, alpha = 0.03 m: the fit over 40 sample pairs gives alpha
    back within 10 % (the cell-mean subtraction removes the mean flow)."""
    rng = np.random.default_rng(3)
    alpha, tau = 0.03, 5.0
    fits = []
    for _ in range(40):
        start = np.column_stack((rng.uniform(2, 8, 4000), rng.uniform(1, 9, 4000)))
        speed = 0.2 * start[:, 1]
        step = np.sqrt(2 * alpha * speed * tau)[:, None] * rng.standard_normal(start.shape)
        end = start + np.column_stack((speed * tau, np.zeros(len(start)))) + step
        ids = np.arange(len(start))
        fits.append(dispersion_fit(GRID, {"time": 0.0, "id": ids, "position": start,
                                          "mass": np.ones(len(start))},
                                   {"time": tau, "id": ids, "position": end,
                                    "mass": np.ones(len(start))}))
    # the shear inside a 1 m cell adds (du/dy * dy)^2 / 12 of spread: small next to 4 D tau
    assert dispersivity(fits) == pytest.approx(alpha, rel=0.1)


def test_no_flow_no_dispersion_and_the_walk_follows_the_local_speed():
    assert dispersivity(np.zeros((5, 2))) == 0.0
    field = np.zeros(GRID.shape + (2,))
    field[:, 10:, 0] = 0.5  # the right half flows at 0.5 m/s
    rng = np.random.default_rng(1)
    position = np.column_stack((np.r_[np.full(2000, 5.0), np.full(2000, 15.0)],
                                np.full(4000, 5.0)))
    disperse(position, field, GRID, 0.04, 2.0, rng)
    still, moving = position[:2000], position[2000:]
    assert np.array_equal(still, np.column_stack((np.full(2000, 5.0), np.full(2000, 5.0))))
    expected = np.sqrt(2 * 0.04 * 0.5 * 2.0)
    assert moving[:, 0].std() == pytest.approx(expected, rel=0.08)
    assert moving[:, 1].std() == pytest.approx(expected, rel=0.08)
