"""Options of this example test folder.

``--crusher NAME`` runs the plant with another crusher FMU (a built FMU name
such as ``cone_crusher`` or a path to an ``.fmu``), as a process engineer
would after swapping in a new crusher model: the reference comparison then
says whether the plant still behaves. The fixtures themselves (run_scenario,
load_fmu, reference_check, mock_800xa, stockpile_client) come from the
``minetwin`` pytest plugin installed with MineTwin.
"""

import pytest


def pytest_addoption(parser):
    parser.addoption("--crusher", default="crusher",
                     help="crusher FMU for the plant tests (default: crusher)")


@pytest.fixture
def crusher_fmu(request):
    return request.config.getoption("--crusher")
