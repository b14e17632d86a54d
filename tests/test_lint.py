"""No statement computes a comparison and drops it: `a == b` alone on a line (ruff's B015, which `make test` runs
with B018 over the repository), or a comparison inside a chain such as `check(x) and approx(0.1) == y`, which ruff
does not flag. Either way the result goes nowhere, and a test that meant to assert it passes whatever the values."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FOLDERS = ("kernels", "registration", "graph", "slam", "perf", "tests")


def dropped_comparisons(source: str) -> list[int]:
    """Lines of the statements whose value is a comparison, or a chain of and / or / not holding one."""
    lines = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Expr):
            continue
        v = node.value
        if isinstance(v, ast.Compare) or isinstance(v, (ast.BoolOp, ast.UnaryOp)) and any(
                isinstance(x, ast.Compare) for x in ast.walk(v)):
            lines.append(node.lineno)
    return lines


def test_the_check_finds_a_dropped_comparison():
    src = ("import numpy as np\n"
           "np.testing.assert_allclose(t, [0, 1]) and dt == 0.05\n"  # the comparison's result goes nowhere
           "x == 1\n"
           "assert x == 1\n"
           "y = a == b\n"
           "f(a == b)\n")
    assert dropped_comparisons(src) == [2, 3]


def test_no_statement_drops_a_comparison():
    found = [f"{p.relative_to(REPO)}:{line}" for top in FOLDERS for p in sorted((REPO / top).rglob("*.py"))
             for line in dropped_comparisons(p.read_text())]
    assert not found, found
