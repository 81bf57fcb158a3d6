"""Every registered storage model keeps the storage contract (``storage_contract``).

Parametrized from the ``minetwin.storage`` registry: a model registered by any
installed package is tested here without a line added.
"""

import warnings

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
