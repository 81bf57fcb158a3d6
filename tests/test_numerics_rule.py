"""The core and the DEM take exp, log, power and cbrt from ``cosim.numerics``, not numpy.

numpy chooses its loops for these by the CPU's instruction set, and its AVX-512 loops
round differently (``cosim.numerics``); a call from plain Python code in ``cosim`` or
``surrogate/dem`` would make seeded runs differ between machines again. Inside numba
kernels (``@njit``) numpy's names compile to the C library's functions and are allowed.
"""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DISPATCHED = {"exp", "log", "power", "cbrt", "log10", "log2", "log1p", "expm1", "exp2",
              "arctan2"}
COMPILED = {"njit", "jit", "vectorize", "guvectorize"}


def _compiled(function: ast.AST) -> bool:
    for decorator in getattr(function, "decorator_list", []):
        target = decorator.func if isinstance(decorator, ast.Call) else decorator
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name in COMPILED:
            return True
    return False


def _numpy_calls(tree: ast.AST):
    """(line, name) of np.<dispatched>(...) calls outside compiled functions."""
    found = []

    def visit(node, compiled):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            compiled = compiled or _compiled(node)
        if (not compiled and isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                and isinstance(node.func.value, ast.Name) and node.func.value.id == "np"
                and node.func.attr in DISPATCHED):
            found.append((node.lineno, node.func.attr))
        for child in ast.iter_child_nodes(node):
            visit(child, compiled)

    visit(tree, False)
    return found


def test_no_numpy_transcendental_function_outside_numba_kernels():
    files = sorted((ROOT / "cosim").rglob("*.py")) + sorted((ROOT / "surrogate" / "dem")
                                                            .rglob("*.py"))
    offending = [f"{path.relative_to(ROOT)}:{line}: np.{name}"
                 for path in files for line, name in _numpy_calls(ast.parse(path.read_text()))]
    assert offending == []


def test_the_rule_sees_a_call_and_spares_a_kernel():
    source = ("import numpy as np\nfrom numba import njit\n"
              "def f(x):\n    return np.exp(x)\n"
              "@njit(cache=True)\ndef g(x):\n    return np.exp(x)\n")
    assert _numpy_calls(ast.parse(source)) == [(4, "exp")]
