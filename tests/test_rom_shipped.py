"""The paper-scale ROMs that ship with the package: surrogate/rom/data/paper_rom_loose.npz
(the registered fit under the loose packing, the default), paper_rom.npz (the fixed
grid) and paper_rom_registered.npz (the registered fit without packing, an option).

Its header's provenance names the committed paper design it was trained on (the
SHA-256 of the very files in the repository), the design's runs and seeds, the
code version and the command that regenerates it. The check against a reduced
regeneration: the final fit redone here with the options the file's model
selection chose (the selection's cross-validation, 3-4 minutes, is what is left
out) predicts the same velocity fields on the training states. Across machines
the linear algebra may round differently (and an SVD may flip a mode's sign), so
the predictions, not the raw mode arrays, are compared, to 1e-9 of the field.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from surrogate.rom import doe, evaluate, paper_design
from surrogate.rom.model import RomModel
from surrogate.rom.provenance import data_digest
from surrogate.rom.storage import (DEFAULT_MODEL, FIXED_GRID_MODEL, LOOSE_MODEL,
                                    REGISTERED_MODEL, VOID_GAP, RomStorage)

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def shipped():
    return RomModel.load(DEFAULT_MODEL)


@pytest.fixture(scope="module", params=[FIXED_GRID_MODEL, REGISTERED_MODEL, LOOSE_MODEL],
                ids=["fixed_grid", "registered", "loose"])
def model_file(request):
    """Each model file that ships: the fixed grid, the registered fit without packing and
    the registered fit under the loose packing (the default)."""
    return request.param


def test_the_shipped_model_is_small_and_names_what_it_was_trained_on(model_file):
    assert model_file.stat().st_size <= 10e6
    shipped = RomModel.load(model_file)
    provenance = shipped.provenance
    data = ROOT / provenance["data"]
    assert data.resolve() == paper_design.DATA_DIR.resolve()
    assert provenance["data_sha256"] == data_digest(data)  # the committed design, unchanged
    assert provenance["design"] == "paper"
    design = paper_design.paper_design()
    keys = {paper_design.run_key(design, run): run.seed for run in design.runs}
    assert provenance["runs"] and all(keys[r["key"]] == r["seed"] for r in provenance["runs"])
    assert len(provenance["code_version"]) >= 40 and "+dirty" not in provenance["code_version"]
    assert provenance["regenerate"].startswith(
        f"minetwin rom train --data {provenance['data']} --out ")
    meta = doe.read_meta(data)
    assert shipped.grid.to_dict() == meta["grid"] and shipped.dem_config == meta["dem_config"]
    validation = provenance["options"].get("validation")
    if validation is not None:  # the scenes the options were chosen on, unchanged
        digests = [data_digest(ROOT / folder)
                   for folder in (validation if isinstance(validation, list) else [validation])]
        assert provenance["validation_sha256"] == (
            digests if isinstance(validation, list) else digests[0])
        assert shipped.validation["selected_by"] == "tracking on validation scenes"


@pytest.mark.parametrize("model_file, packing", [(REGISTERED_MODEL, "none"),
                                                 (LOOSE_MODEL, "loose")],
                         ids=["registered", "loose"])
def test_a_registered_fit_runs_as_it_was_chosen(model_file, packing):
    """A registered fit keeps the storage settings it was chosen under, and the
    storage takes them; its choice is the best candidate it records among those that rest
    (under the loose packing, all of them), by the criterion it records."""
    model = RomModel.load(model_file)
    assert model.registration == "height"
    storage = RomStorage(model_file)
    assert (storage.packing, storage.landing_spread) == (packing, 2.9)
    assert storage.void_gap == model.storage_settings.get("void_gap", VOID_GAP)
    assert storage.packing_density == model.storage_settings["packing_density"] == \
        pytest.approx(564.1891533925966, rel=1e-15)
    assert model.dispersivity == 0.0 and model.provenance["options"]["dispersivity"] == 0.0
    record = model.validation
    chosen = f"{model.n_mass_modes}/{model.n_velocity_modes}/{model.ridge:g}"
    hanging = record["candidates_hanging_mass_share"]
    resting = [key for key, share in hanging.items() if share <= record["hanging_limit"]]
    assert record["hanging_limit_met"] and chosen in resting
    assert record["candidates"][chosen] == record["validation_tracking_error"]
    # chosen by what the file says it was chosen by (the option: the mean over scenes)
    if record.get("select_by", "mean") == "mean":
        assert record["validation_tracking_error"] == min(
            record["candidates"][key] for key in resting)
    else:
        assert record["select_by"] == "floor-excess"
        excess = record["candidates_floor_excess"]
        assert excess[chosen] == record["validation_floor_excess"] == min(
            excess[key] for key in resting)
        assert record["validation_floor_excess"] == pytest.approx(max(
            scene["mean"] - record["validation_scene_floors"][name]
            for name, scene in record["validation_scenes"].items()), abs=1e-15)


@pytest.mark.slow  # about 30 s: the final fit on the whole paper design
def test_a_reduced_regeneration_predicts_what_the_shipped_model_predicts(model_file, tmp_path):
    shipped = RomModel.load(model_file)
    data = ROOT / shipped.provenance["data"]
    options = shipped.provenance["options"]
    again = evaluate.train(data, tmp_path / "again.npz", shipped.n_mass_modes,
                           shipped.n_velocity_modes, shipped.ridge,
                           registration=options.get("registration"),
                           storage_options={k: options.get(k)
                                            for k in evaluate.STORAGE_SETTINGS},
                           dispersivity=options.get("dispersivity"))
    assert again.storage_settings == shipped.storage_settings
    assert again.n_samples == shipped.n_samples
    for name, (low, high) in shipped.ranges.items():
        assert again.ranges[name] == pytest.approx([low, high], rel=1e-9, abs=1e-12), name
    assert again.dispersivity == pytest.approx(shipped.dispersivity, rel=1e-9)
    assert again.rest_fraction == shipped.rest_fraction > 0.0
    assert again.container.to_dict() == shipped.container.to_dict()
    samples = doe.load_samples(data)
    rows = np.linspace(0, samples["time"].size - 1, 40).astype(int)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the training states are inside the training range
        for k in rows:
            args = (samples["mass"][k], samples["discharge_rate"][k], samples["inflow_rate"][k])
            expected, got = shipped.predict(*args), again.predict(*args)
            scale = max(float(np.abs(expected).max()), 1e-12)
            np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9 * scale)


def test_the_rom_storage_runs_on_the_shipped_model_by_default(shipped):
    assert DEFAULT_MODEL == LOOSE_MODEL
    storage = RomStorage()
    assert storage.model.provenance == shipped.provenance
    config = paper_design.paper_config()
    assert storage.container.x_max - storage.container.x_min == pytest.approx(
        config.floor_width, rel=0.1)


def test_a_pile_held_before_the_first_step_is_laid_at_once_inside_the_training_range(shipped):
    """Bins that come before the stockpile's first step (the mock 800xA's initial
    inventory) are the pile the plant started with: laid at once by the sandpile
    rule, not dropped through the surface DEM, not counted as inflow; 1,500 t of
    them make a pile inside the shipped model's training range. Later bins fall
    through the surface layer."""
    from surrogate.rom.grid import mass_field
    from surrogate.stockpile import StockpileAsset

    asset = StockpileAsset("rom", seed=3)
    bins = 6000  # 1,500 t in CV101's 250 kg bins
    ids = asset.receive_bins(np.arange(1, bins + 1, dtype=np.uint64), np.full(bins, 250.0),
                             np.full(bins, 0.012), np.full(bins, 1.3), np.zeros(bins, int),
                             np.zeros(bins))
    storage = asset.storage
    assert len(storage.surface_dem) == 0 and storage.held_mass() == pytest.approx(1.5e6, rel=1e-12)
    assert set(storage.held_ids().tolist()) == set(ids.tolist())
    mass = mass_field(shipped.grid, storage._pos, storage._mass)
    assert shipped.check_ranges(mass, 1200.0, 0.0, shipped.mass_residual(mass), warn=False) == {}
    asset.set_discharge_rate(1200.0)
    asset.step(1.0)
    late = asset.receive_bin(bins + 1, 1200.0, 0.006, 1.0)
    assert len(storage.surface_dem) == late.size  # falling from the inlet


def test_the_mine_lays_a_rom_stockpiles_initial_fill_as_a_pile():
    """The paper-scale mine's 1.9 kt of earlier production goes straight into the
    ROM's bulk (``Stockpile.prefill``), not through its surface DEM."""
    from cosim.scenario import build, load

    simulation = build(load(ROOT / "examples" / "paper_scale.toml"), storage_model="rom",
                       progress=False)
    try:
        pile = simulation.assets["stockpile"]
        assert pile.model.name == "rom" and len(pile.model.surface_dem) == 0
        assert pile.model.held_mass() == pytest.approx(1.9e6, rel=1e-12)
    finally:
        simulation.close()
