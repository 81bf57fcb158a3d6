"""A third-party storage model: installed by pip, found through the registry, run in
a scenario, held to the storage contract.

``tests/plugins/minetwin_lifo`` is a package of its own (its pyproject registers
``lifo = "minetwin_lifo:LifoStorage"`` in the ``minetwin.storage`` group). It is
installed with pip into a folder of this test (``--target``, so the project's
venv is left as it was) which is then put on the import path, as site-packages
would be.
"""

import importlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from cosim.scenario import build
from cosim.storage import registered_models, storage_class
from storage_contract import CONTRACT, contract_names
from test_mine import EXAMPLE, small_scene

PLUGIN = Path(__file__).parent / "plugins" / "minetwin_lifo"


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    work = tmp_path_factory.mktemp("plugin")
    source = shutil.copytree(PLUGIN, work / "source")  # the build leaves files beside it
    target = work / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                    "--target", str(target), str(source)], check=True, timeout=300)
    sys.path.insert(0, str(target))
    importlib.invalidate_caches()
    yield target
    sys.path.remove(str(target))
    importlib.invalidate_caches()


def test_the_installed_plugin_is_registered_and_joins_the_contract_suite(installed, tmp_path):
    assert registered_models()["lifo"].value == "minetwin_lifo:LifoStorage"
    assert "lifo" in contract_names()  # so test_storage_contract parametrizes over it too
    assert storage_class("lifo").__module__ == "minetwin_lifo"
    for check in CONTRACT:
        check("lifo", tmp_path)


def test_the_plugin_runs_in_a_scenario(installed):
    simulation = build(small_scene(until_s=150.0), storage_model="lifo")
    simulation.run()
    pile = simulation.assets["stockpile"]
    assert pile.model.name == "lifo"
    assert simulation.timeseries["stockpile.discharged_kg"].iloc[-1] > 0
    assert simulation.timeseries["plant.mass_balance_rel_error"].max() < 1e-12
    simulation.close()


def test_an_unknown_model_error_lists_the_installed_plugin(installed, tmp_path):
    env = {**os.environ, "PYTHONPATH": str(installed)}
    result = subprocess.run([sys.executable, "-m", "minetwin.cli", "simulate", str(EXAMPLE),
                             "--out", str(tmp_path), "--storage-model", "magic"],
                            capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode == 2
    assert "'lifo'" in result.stderr and "'fifo'" in result.stderr
    assert "Traceback" not in result.stderr
