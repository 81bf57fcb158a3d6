"""The plug-in's FMU role and FMU file, registered through MineTwin's entry points.

``STAIR_COUNTER_INTERFACE`` is a new role (``minetwin.fmu_roles``): what an FMU that
counts the whole seconds of a run must offer. ``PEBBLE_CRUSHER_FMU`` is a crusher FMU
the package ships as package data (``minetwin.fmus``); a scenario names it as
``fmu = "pebble_crusher"``. tests/test_asset_plugin.py puts a built crusher FMU there
before it installs the package: a real package ships its own.
"""

from pathlib import Path

from cosim.fmu import VariableSpec

STAIR_COUNTER_INTERFACE = (
    VariableSpec("increment", "input", (), "", "Int32"),
    VariableSpec("counter", "output", (), "", "Int32"),
    VariableSpec("elapsed", "output", (), "s"),
)

PEBBLE_CRUSHER_FMU = Path(__file__).with_name("pebble_crusher.fmu")
