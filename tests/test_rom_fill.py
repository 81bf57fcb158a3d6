"""The flux fit's fitted fill (``RomModel(target="flux", fill_law="dem")``).

The training data is test_rom's synthetic design (heaps with the 2-D point-sink
funnel flow) with its flowing cells made looser: a cell whose speed is above
0.01 m/s holds 0.7 of its mass (a dilated flowing zone). The option trains,
saves and loads with ``fill_law`` in its header and its tables, its tables are
the bin means of the covered cells' fill (computed here again cell by cell),
and the velocity it predicts is the fitted flux over
max(min(M, phi(|F| / M_full) M_full), f0 M_full) with phi interpolated here
by hand; on a packed pile (every covered cell full) the flowing cells so move
faster than the plain flux fit moves them, by 1 / phi.
"""

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_rom import CONTAINER, GRID, synthetic_training, write_design  # noqa: E402

from cosim.errors import ValidationError  # noqa: E402
from surrogate.rom.model import COVER_FILL, FILL_LAW_BINS, RomModel  # noqa: E402

FEEDER = dataclasses.replace(CONTAINER, outlet_width=2.0)  # feeder cells x = -0.5, 0.5
FULL = FEEDER.areal_density * GRID.dx * GRID.dy


@pytest.fixture(scope="module")
def data():
    mass, q_out, q_in, velocity = synthetic_training(samples=40)
    speed = np.sqrt((velocity ** 2).sum(-1))
    return mass * np.where(speed > 0.01, 0.7, 1.0), q_out, q_in, velocity


def _table(fill, j, use):
    """Bin means (j, fill) over the cells ``use``, by a plain loop."""
    sums = {}
    for f, jj in zip(fill[use], j[use]):
        b = max(k for k, edge in enumerate(FILL_LAW_BINS) if jj >= edge)
        s = sums.setdefault(b, [0.0, 0.0, 0])
        s[0] += jj
        s[1] += f
        s[2] += 1
    keys = sorted(sums)
    return (np.array([sums[k][0] / sums[k][2] for k in keys]),
            np.array([sums[k][1] / sums[k][2] for k in keys]))


def _interp(x, xs, ys):
    """Piecewise-linear, constant beyond the ends (by hand)."""
    if x <= xs[0]:
        return ys[0]
    for k in range(1, len(xs)):
        if x <= xs[k]:
            return ys[k - 1] + (ys[k] - ys[k - 1]) * (x - xs[k - 1]) / (xs[k] - xs[k - 1])
    return ys[-1]


def test_the_fill_law_round_trips_and_its_tables_are_the_bin_means(data, tmp_path):
    mass, q_out, q_in, velocity = data
    model = RomModel(GRID, 6, 6, 1e-3, FEEDER, target="flux", fill_law="dem")
    model.fit(mass, q_out, q_in, velocity)
    path = model.save(tmp_path / "fill.npz")
    with np.load(path) as stored:
        assert json.loads(str(stored["header"]))["fill_law"] == "dem"
    loaded = RomModel.load(path)
    assert loaded.fill_law == "dem" and loaded.target == "flux"
    for k in (2, 21):
        np.testing.assert_array_equal(loaded.predict(mass[k], q_out[k], q_in[k]),
                                      model.predict(mass[k], q_out[k], q_in[k]))
    # the tables, again: covered = the cell above holds COVER_FILL full cells
    fill = mass / FULL
    j = np.sqrt(((velocity * mass[..., None]) ** 2).sum(-1)) / FULL
    covered = np.zeros(mass.shape, bool)
    covered[:, :-1] = fill[:, 1:] >= COVER_FILL
    feeder = np.zeros((GRID.ny, GRID.nx), bool)
    x, _ = GRID.centres()
    feeder[0] = np.abs(x) <= 1.0
    for name, cells in (("feeder", feeder), ("bulk", ~feeder)):
        want_j, want_fill = _table(fill, j, covered & cells[None])
        np.testing.assert_allclose(model.arrays[f"fill_law_{name}_j"], want_j, rtol=1e-12)
        np.testing.assert_allclose(model.arrays[f"fill_law_{name}_fill"], want_fill,
                                   rtol=1e-12)
    # the dilated flowing cells are what the law finds: fill 0.7 where they move fast
    assert model.arrays["fill_law_bulk_fill"][0] > 0.9
    assert model.arrays["fill_law_bulk_fill"][-1] < 0.8
    # a velocity fit and a plain flux fit write no fill law
    assert "fill_law" not in RomModel(GRID, 6, 6, 1e-3, FEEDER, target="flux").fit(
        mass, q_out, q_in, velocity).header()
    with pytest.raises(ValidationError, match="^fill_law"):
        RomModel(GRID, container=FEEDER, fill_law="dem")  # velocity target
    with pytest.raises(ValidationError, match="^fill_law"):
        RomModel(GRID, container=FEEDER, target="flux", fill_law="speed")


def test_the_velocity_is_the_flux_over_the_fitted_fill(data):
    mass, q_out, q_in, velocity = data
    model = RomModel(GRID, 6, 6, 1e-3, FEEDER, target="flux", fill_law="dem").fit(
        mass, q_out, q_in, velocity)
    plain = RomModel(GRID, 6, 6, 1e-3, FEEDER, target="flux").fit(mass, q_out, q_in, velocity)
    feeder = np.zeros((GRID.ny, GRID.nx), bool)
    feeder[0] = np.abs(GRID.centres()[0]) <= 1.0
    a = model.arrays
    for k in (0, 17, 39):
        covered = np.zeros(mass[k].shape, bool)
        covered[:-1] = mass[k][1:] >= COVER_FILL * FULL
        packed = np.where(covered, FULL, mass[k])  # a pile packed as the ROM packs it
        flux = model.predict_flux(packed, q_out[k], q_in[k])
        got = model.predict(packed, q_out[k], q_in[k])
        want = np.empty_like(got)
        for row in range(GRID.ny):
            for col in range(GRID.nx):
                jj = np.hypot(*flux[row, col]) / FULL
                name = "feeder" if feeder[row, col] else "bulk"
                phi = _interp(jj, a[f"fill_law_{name}_j"], a[f"fill_law_{name}_fill"])
                divisor = max(min(packed[row, col], phi * FULL), model.flux_floor * FULL)
                want[row, col] = flux[row, col] / divisor
        scale = np.abs(want).max()
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(model.fitted_fill(packed, q_out[k], q_in[k]) * FULL
                                   * got[..., 1], flux[..., 1], rtol=0,
                                   atol=1e-9 * np.abs(flux).max())
        # the flowing covered cells move faster than the plain flux fit moves them
        # (same regression: the fill law changes the divisor only), by 1 / phi
        phi = model.fitted_fill(packed, q_out[k], q_in[k])
        fast = covered & (phi < 0.85)
        assert fast.any()
        ratio = (np.hypot(*got[fast].T)
                 / np.hypot(*plain.predict(packed, q_out[k], q_in[k])[fast].T))
        np.testing.assert_allclose(ratio, 1.0 / phi[fast], rtol=1e-9)
        assert np.all(ratio > 1.15)


def test_the_cli_trains_a_fill_law_model(tmp_path):
    from minetwin.cli import main

    write_design(tmp_path, container=FEEDER)
    out = tmp_path / "model.npz"
    assert main(["rom", "train", "--data", str(tmp_path), "--out", str(out),
                 "--mass-modes", "4", "--velocity-modes", "4", "--ridge", "1",
                 "--target", "flux", "--flux-floor", "0.5", "--fill-law", "dem"]) == 0
    loaded = RomModel.load(out)
    assert loaded.fill_law == "dem" and "fill_law_bulk_fill" in loaded.arrays
    assert "--fill-law dem" in loaded.provenance["regenerate"]
