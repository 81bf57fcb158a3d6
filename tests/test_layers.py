"""Imports run one way: the core, then the surrogate and the process simulator, then
the monitor and the application (docs/architecture.md, "Layers").

Every import statement of every module is read (also those inside functions, which
run later but still tie the layers); an arrow that runs upward fails the test.
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

APPLICATION = ("cosim/cli.py", "cosim/commands/", "cosim/testing/", "monitor/demo_stockpile.py")
"""The top layer, which may import anything: the command line and the pytest plugin,
still inside ``cosim/`` (docs/architecture.md names this as the known exception), and
the demonstration stockpile process that runs the surrogate for the monitor's demo."""

FORBIDDEN = {
    "cosim": {"surrogate", "opcua_server", "monitor", "fmus"},
    "fmus": {"surrogate", "opcua_server", "monitor"},
    "surrogate": {"monitor"},
    "opcua_server": {"surrogate", "monitor"},
    "monitor": {"surrogate", "opcua_server", "fmus"},
}
"""Top-level packages each package must not import."""

KNOWN_UPWARD = {
    ("surrogate/client.py", "opcua_server.security"),
    ("surrogate/client.py", "opcua_server.config"),
}
"""The stockpile client still takes the node map and application URIs from the mock
server's package; they belong in a protocol module both import."""


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
            relative = path.relative_to(ROOT).as_posix()
            if not relative.startswith(APPLICATION):
                yield package, relative


@pytest.mark.parametrize("package, module", list(_modules()), ids=lambda v: str(v))
def test_no_import_runs_upward(package, module):
    upward = [name for name in _imports(ROOT / module)
              if name.split(".")[0] in FORBIDDEN[package] and (module, name) not in KNOWN_UPWARD]
    assert not upward, f"{module} ({package}) imports {upward}"


def test_the_known_upward_imports_still_exist():
    """An exception that is gone must leave the list, so that it cannot come back."""
    for module, name in KNOWN_UPWARD:
        assert name in set(_imports(ROOT / module)), (module, name)
