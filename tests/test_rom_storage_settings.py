"""A ROM model file keeps the storage options it was chosen under
(``RomModel.storage_settings``) and ``RomStorage`` takes them as its defaults;
options given to the storage win, and a model without settings runs as before."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_rom import CONTAINER, GRID, synthetic_training, write_design  # noqa: E402

from cosim.errors import ValidationError  # noqa: E402
from surrogate.rom import evaluate  # noqa: E402
from surrogate.rom.model import RomModel  # noqa: E402
from surrogate.rom.storage import RomStorage  # noqa: E402

SETTINGS = {"packing": "none", "packing_density": 1200.0, "landing_spread": 1.5}


def test_the_storage_takes_the_models_settings_unless_told_otherwise(tmp_path):
    mass, q_out, q_in, velocity = synthetic_training()
    model = RomModel(GRID, n_mass_modes=6, n_velocity_modes=6, ridge=1e-3,
                     container=CONTAINER).fit(mass, q_out, q_in, velocity)
    plain = RomStorage(model, surface="rule")
    assert (plain.packing, plain.packing_density, plain.landing_spread) == ("avalanche", None,
                                                                            0.0)
    assert plain.container.areal_density == CONTAINER.areal_density
    model.storage_settings = dict(SETTINGS)
    loaded = RomModel.load(model.save(tmp_path / "set.npz"))
    assert loaded.storage_settings == SETTINGS
    storage = RomStorage(loaded, surface="rule")
    assert (storage.packing, storage.packing_density, storage.landing_spread) == (
        "none", 1200.0, 1.5)
    assert storage.container.areal_density == 1200.0
    assert storage.bulk_areal_density() == 1200.0
    told = RomStorage(loaded, surface="rule", packing="column", packing_density=1500.0,
                      landing_spread=0.0)
    assert (told.packing, told.packing_density, told.landing_spread) == ("column", 1500.0, 0.0)


def test_train_keeps_the_storage_options_and_a_given_walk_and_refuses_bad_ones(tmp_path):
    data = write_design(tmp_path / "design")
    model = evaluate.train(data, tmp_path / "m.npz", n_mass_modes=2, n_velocity_modes=2,
                           ridge=1.0, storage_options={"packing": "column",
                                                       "landing_spread": None})
    assert model.storage_settings == {"packing": "column"}
    assert RomModel.load(tmp_path / "m.npz").storage_settings == {"packing": "column"}
    assert RomModel.load(tmp_path / "m.npz").provenance["options"]["packing"] == "column"
    walked = evaluate.train(data, None, n_mass_modes=2, n_velocity_modes=2, ridge=1.0,
                            dispersivity=0.25)
    assert walked.dispersivity == 0.25 and walked.validation["dispersivity"]["given"]
    with pytest.raises(ValidationError, match="dispersivity"):
        evaluate.train(data, None, n_mass_modes=2, n_velocity_modes=2, ridge=1.0,
                       dispersivity=-0.1)
    for options, field in (({"packing": "heap"}, "packing"),
                           ({"packing_density": 0.0}, "packing_density"),
                           ({"landing_spread": -1.0}, "landing_spread"),
                           ({"void_gap": -1.0}, "void_gap"),
                           ({"transport": "repack"}, "storage_options")):
        with pytest.raises(ValidationError, match=field):
            evaluate.train(data, None, n_mass_modes=2, n_velocity_modes=2, ridge=1.0,
                           storage_options=options)
    with pytest.raises(ValidationError, match="validation"):
        evaluate.train(data, None, validation=data)


def test_the_regenerating_command_repeats_a_flag_given_several_times():
    """Several validation folders come back as one ``--validation`` each, in order;
    floats as short as they read back exactly."""
    from surrogate.rom.provenance import regenerate_command

    command = regenerate_command("d", "m.npz", {"validation": ["a", "b"], "rom_seeds": 2,
                                                "packing_density": 564.1891533925966,
                                                "ridge": None, "hanging_limit": 0.01})
    assert command == ("minetwin rom train --data d --out m.npz --validation a --validation b "
                       "--rom-seeds 2 --packing-density 564.1891533925966 --hanging-limit 0.01")
