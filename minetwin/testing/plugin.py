"""pytest plugin for MineTwin co-simulation tests (entry point ``pytest11``: ``minetwin``).

Installed with the package, so a user's test file only needs the fixtures'
names; nothing to copy. Fixtures:

``run_scenario``
    ``run_scenario(path, until=..., overrides={...}, seed=...)`` runs a
    scenario TOML in a temporary folder and returns a ``ScenarioRun``
    (``timeseries`` DataFrame, ``events`` EventStore, ``summary`` dict).
``load_fmu``
    ``load_fmu(path, interface="crusher"|"mill"|...)`` loads an FMU with fmpy
    and validates it against the asset's interface (a missing variable fails
    with the file, the variable and what was expected).
``mock_800xa``
    a running mock 800xA OPC UA server (lockstep: it advances only when the
    stockpile client says so) on a free 127.0.0.1 port, with certificates
    and user credentials made for the test.
``stockpile_client``
    ``stockpile_client(model="fifo")``: the stockpile asset attached to
    ``mock_800xa`` as an OPC UA client, driven in lockstep.
``reference_check``
    ``reference_check(timeseries, reference_csv, scenario=...)``: compare a
    run with a reference CSV (tolerances from the scenario's ``[reference]``
    table), failing with the comparison table; ``--minetwin-record``
    rewrites the reference instead, ``--minetwin-plots DIR`` keeps the PNG
    overlays of failing signals.

Assertions live in ``minetwin.testing`` (``assert_mass_balance``,
``assert_ids_accounted``, ``assert_signal_within_band``,
``assert_matches_reference``, ``assert_step_response``). This module
imports only pytest at load time, so it costs nothing in test runs that do
not use it.
"""

from __future__ import annotations

from pathlib import Path

import pytest


def pytest_addoption(parser) -> None:
    group = parser.getgroup("minetwin", "MineTwin co-simulation tests")
    group.addoption("--minetwin-record", action="store_true", default=False,
                    help="write the run's signals to the reference CSVs that reference_check "
                         "is given, instead of comparing (review the diff before committing)")
    group.addoption("--minetwin-plots", metavar="DIR", default=None,
                    help="folder for PNG overlays of signals outside their reference band "
                         "(default: the test's temporary folder)")


def pytest_configure(config) -> None:
    config.addinivalue_line("markers",
                            "cosim: a MineTwin co-simulation test (runs a scenario, FMU or "
                            "OPC UA exchange)")


def pytest_report_header(config) -> str:
    return "minetwin: co-simulation fixtures run_scenario, load_fmu, mock_800xa, " \
           "stockpile_client, reference_check"


@pytest.fixture
def run_scenario(tmp_path_factory):
    """Callable ``run_scenario(path, until=None, overrides=None, seed=None, **options)``."""
    from minetwin.testing.scenario import run_scenario as run

    runs = []

    def _run(path, until=None, overrides=None, seed=None, **options):
        out = tmp_path_factory.mktemp(f"run-{Path(path).stem}")
        result = run(path, until=until, overrides=overrides, seed=seed, out=out, **options)
        runs.append(result)
        return result

    yield _run
    for result in runs:
        result.close()


@pytest.fixture
def load_fmu():
    """Callable ``load_fmu(path, interface, name=None, parameters=None)`` -> validated component."""
    from minetwin.testing.fmus import load_validated_fmu

    loaded = []

    def _load(path, interface="crusher", name=None, parameters=None):
        component = load_validated_fmu(path, interface, name=name, parameters=parameters)
        loaded.append(component)
        return component

    yield _load
    for component in loaded:
        component.finish()


@pytest.fixture
def mock_800xa(tmp_path_factory):
    """A running mock 800xA server in lockstep on a free 127.0.0.1 port (stopped after)."""
    from minetwin.testing.opcua import MockPlantServer

    server = MockPlantServer(tmp_path_factory.mktemp("mock800xa"))
    server.start()
    yield server
    server.stop()


@pytest.fixture
def stockpile_client(mock_800xa):
    """Callable ``stockpile_client(model="fifo", seed=0, **options)`` -> ``LockstepStockpile``.

    ``client.run(until=S)`` advances server and client together and returns
    an ``ExchangeResult`` (``assert_mass_balance()``, ``assert_ids_accounted()``).
    """
    from minetwin.testing.opcua import LockstepStockpile

    clients = []

    def _attach(model="fifo", seed=0, **options):
        client = LockstepStockpile(mock_800xa, model=model, seed=seed, **options)
        clients.append(client)
        return client

    yield _attach
    for client in clients:
        client.close()


@pytest.fixture
def reference_check(request, tmp_path):
    """Callable ``reference_check(timeseries, reference_csv, scenario=None, signals=None)``."""
    from minetwin.testing.assertions import assert_matches_reference
    from minetwin.testing.reference import ReferenceResult, ReferenceSpec

    record = request.config.getoption("--minetwin-record")
    plots = request.config.getoption("--minetwin-plots")

    def _check(timeseries, reference_csv, scenario=None, signals=None):
        __tracebackhide__ = True
        spec = ReferenceSpec.from_scenario(scenario) if scenario is not None else None
        names = signals or (spec.signals if spec else None)
        if record:
            if names is None:
                names = list(ReferenceResult.read(reference_csv).signals)
            ReferenceResult.from_timeseries(timeseries, names).write(reference_csv)
            return None
        reference = ReferenceResult.read(reference_csv)
        tolerances = ({name: spec.tolerance(name) for name in reference.signals}
                      if spec else None)
        plot_dir = Path(plots) / request.node.name if plots else tmp_path / "overlays"
        return assert_matches_reference(timeseries, reference, signals=names,
                                        tolerances=tolerances, plot_dir=plot_dir)

    return _check
