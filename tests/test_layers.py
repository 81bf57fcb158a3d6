"""Imports run one way: the core, then the protocol, the FMUs, the surrogate and the
process simulator, then the monitor, then the application (docs/architecture.md,
"Layers").

Every import statement of every module is read (also those inside functions, which
run later but still tie the layers); an arrow that runs upward fails the test.
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

APPLICATION = "minetwin"
"""The top layer, which may import anything: the command line, the pytest plugin and
the orchestration of the integration test."""

FORBIDDEN = {
    "cosim": {"opcua_protocol", "surrogate", "opcua_server", "monitor", "fmus", APPLICATION},
    "opcua_protocol": {"surrogate", "opcua_server", "monitor", "fmus", APPLICATION},
    "fmus": {"surrogate", "opcua_server", "monitor", APPLICATION},
    "surrogate": {"opcua_server", "monitor", APPLICATION},
    "opcua_server": {"surrogate", "monitor", APPLICATION},
    "monitor": {"surrogate", "opcua_server", "fmus", APPLICATION},
}
"""Top-level packages each package must not import. The stockpile client
(``surrogate``) and the process simulator (``opcua_server``) meet only in
``opcua_protocol``."""


def _imports(path: Path):
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module


def _modules():
    for package in FORBIDDEN:
        for path in sorted((ROOT / package).rglob("*.py")):
            yield package, path.relative_to(ROOT).as_posix()


def test_every_package_has_its_layer():
    """A new top-level package must be placed in a layer before it can be imported."""
    packages = {p.parent.name for p in ROOT.glob("*/__init__.py")}
    assert packages <= set(FORBIDDEN) | {APPLICATION}, packages - set(FORBIDDEN)


@pytest.mark.parametrize("package, module", list(_modules()), ids=lambda v: str(v))
def test_no_import_runs_upward(package, module):
    upward = [name for name in _imports(ROOT / module)
              if name.split(".")[0] in FORBIDDEN[package]]
    assert not upward, f"{module} ({package}) imports {upward}"
