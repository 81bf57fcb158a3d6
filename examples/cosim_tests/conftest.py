"""Options and shared runs of this example test folder.

``--crusher NAME`` runs the plant with another crusher FMU (a built FMU name
such as ``cone_crusher`` or a path to an ``.fmu``), as a process engineer
would after swapping in a new crusher model: the reference comparison then
says whether the plant still behaves. The fixtures used here (run_scenario's
machinery, load_fmu, reference_check, mock_800xa, stockpile_client) come from
the ``minetwin`` pytest plugin installed with MineTwin.
"""

from pathlib import Path

import pytest

from minetwin.testing.scenario import run_scenario

SCENARIO = Path(__file__).parent / "plant.toml"


def pytest_addoption(parser):
    parser.addoption("--crusher", default="crusher",
                     help="crusher FMU for the plant tests (default: crusher)")


@pytest.fixture(scope="session")
def crusher_fmu(request):
    return request.config.getoption("--crusher")


@pytest.fixture(scope="module")
def plant_run(tmp_path_factory, crusher_fmu):
    """One 700 s run of the plant shared by the tests of a module (the same call as the
    plugin's function-scoped ``run_scenario`` fixture, kept for the whole module)."""
    run = run_scenario(SCENARIO, until=700.0, overrides={"assets.crusher.fmu": crusher_fmu},
                       out=tmp_path_factory.mktemp("plant"))
    yield run
    run.close()
