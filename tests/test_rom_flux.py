"""The ROM's mass-flux fit (``RomModel(target="flux")``, ``minetwin rom train --target flux``).

The training data is test_rom's synthetic design (heaps with the 2-D point-sink
funnel flow): the flux option trains, saves and loads with its target and floor
in the header, and the velocity it predicts carries the fitted flux: in every
cell holding at least the floor's mass, velocity times the cell's mass is the
fitted flux (to rounding, 1e-9 of the largest flux); below it, the flux over
the floor's mass.
"""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_rom import CONTAINER, GRID, synthetic_training, write_design  # noqa: E402

from cosim.errors import ValidationError  # noqa: E402
from surrogate.rom.model import RomModel, flux_samples  # noqa: E402


@pytest.fixture(scope="module")
def data():
    return synthetic_training(samples=40)


def test_the_flux_option_trains_saves_and_loads_its_target(data, tmp_path):
    mass, q_out, q_in, velocity = data
    model = RomModel(GRID, 6, 6, 1e-3, CONTAINER, target="flux", flux_floor=0.25)
    model.fit(mass, q_out, q_in, velocity)
    path = model.save(tmp_path / "flux.npz")
    with np.load(path) as stored:
        header = json.loads(str(stored["header"]))
    assert header["target"] == "flux" and header["flux_floor"] == 0.25
    loaded = RomModel.load(path)
    assert loaded.target == "flux" and loaded.flux_floor == 0.25
    np.testing.assert_array_equal(loaded.predict(mass[3], q_out[3], q_in[3]),
                                  model.predict(mass[3], q_out[3], q_in[3]))
    velocity_fit = RomModel(GRID, 6, 6, 1e-3, CONTAINER).fit(mass, q_out, q_in, velocity)
    assert "target" not in velocity_fit.header()  # a velocity fit's file is as before
    assert RomModel.load(velocity_fit.save(tmp_path / "v.npz")).target == "velocity"
    with pytest.raises(ValidationError, match="^target"):
        RomModel(GRID, target="momentum")
    with pytest.raises(ValidationError, match="^container"):
        RomModel(GRID, target="flux")


def test_the_predicted_velocity_carries_the_fitted_flux(data):
    mass, q_out, q_in, velocity = data
    model = RomModel(GRID, 6, 6, 1e-3, CONTAINER, target="flux").fit(mass, q_out, q_in,
                                                                      velocity)
    full = CONTAINER.areal_density * GRID.dx * GRID.dy
    for k in (0, 17, 39):
        flux = model.predict_flux(mass[k], q_out[k], q_in[k])
        got = model.predict(mass[k], q_out[k], q_in[k])
        floor = np.maximum(mass[k], model.flux_floor * full)[..., None]
        np.testing.assert_allclose(got * floor, flux, rtol=0, atol=1e-9 * np.abs(flux).max())
        filled = mass[k] >= model.flux_floor * full
        np.testing.assert_allclose(got[filled] * mass[k][filled][:, None], flux[filled],
                                   rtol=0, atol=1e-9 * np.abs(flux).max())
    # and the fit itself is close to the training flux (16 % relative, 6 modes)
    fitted = np.array([model.predict_flux(m, q, i) for m, q, i in zip(mass, q_out, q_in)])
    truth = flux_samples(mass, velocity).reshape(fitted.shape)
    assert np.linalg.norm(fitted - truth) / np.linalg.norm(truth) < 0.3


def test_the_cli_trains_a_flux_model(tmp_path):
    from minetwin.cli import main

    write_design(tmp_path, container=CONTAINER)
    out = tmp_path / "model.npz"
    assert main(["rom", "train", "--data", str(tmp_path), "--out", str(out),
                 "--mass-modes", "4", "--velocity-modes", "4", "--ridge", "1",
                 "--target", "flux"]) == 0
    loaded = RomModel.load(out)
    assert loaded.target == "flux" and loaded.flux_floor in (0.25, 0.5, 1.0)
    assert set(loaded.validation["candidates"]) == {"4/4/1/0.25", "4/4/1/0.5", "4/4/1/1"}
    assert "--target flux" in loaded.provenance["regenerate"]
