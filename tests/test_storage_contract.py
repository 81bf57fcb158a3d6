"""Every registered storage model keeps the storage contract (``storage_contract``).

Parametrized from the ``minetwin.storage`` registry: a model registered by any
installed package is tested here without a line added.
"""

import warnings

import numpy as np
import pytest

from storage_contract import CONTRACT, contract_names


@pytest.fixture(scope="module")
def model_files(tmp_path_factory):
    return tmp_path_factory.mktemp("storage_contract")


@pytest.mark.parametrize("check", CONTRACT, ids=lambda check: check.__name__[len("check_"):])
@pytest.mark.parametrize("name", contract_names())
def test_registered_storage_model_keeps_the_contract(name, check, model_files):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # small piles lie outside a ROM's training ranges
        check(name, model_files)


@pytest.mark.parametrize("name", contract_names())
def test_the_stockpile_asset_seeds_every_model_with_its_seed(name, model_files):
    """``minetwin stockpile --model NAME --seed N``: the asset's generator, seeded by N,
    is the storage model's ``rng`` whatever the model (the ROM's seed was ignored)."""
    from storage_contract import CONTRACT_OPTIONS
    from surrogate.stockpile import StockpileAsset

    options = CONTRACT_OPTIONS[name](model_files) if name in CONTRACT_OPTIONS else {}
    asset = StockpileAsset(name, seed=17, storage_options=options)
    assert asset.storage.rng is asset.rng
    again = StockpileAsset(name, seed=17, storage_options=options)
    other = StockpileAsset(name, seed=18, storage_options=options)
    assert asset.rng.bit_generator.state == again.rng.bit_generator.state
    assert asset.rng.bit_generator.state != other.rng.bit_generator.state


def test_a_rom_stockpile_follows_its_seed(model_files):
    from storage_contract import CONTRACT_OPTIONS
    from surrogate.stockpile import StockpileAsset

    def positions(seed):
        asset = StockpileAsset("rom", seed=seed,
                               storage_options=CONTRACT_OPTIONS["rom"](model_files))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for k in range(3):
                asset.receive_bin(k + 1, 800.0, 0.3, 1.0)
                asset.step(0.5)
        return asset.particle_table(limit=1000)["x"]

    np.testing.assert_array_equal(positions(3), positions(3))
    assert not np.array_equal(positions(3), positions(4))  # the surface layer draws from it
