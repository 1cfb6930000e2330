"""Every function in `mpnode_cli/` fits in one sitting: at most `MAX_LINES` lines.

A longer function is split into named stages, each read top to bottom, rather than left
to grow; this reads the source with `ast`, so it costs no imports.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "mpnode_cli"
# Lines from `def` to the function's last line (a signature and docstring count, the
# decorators above it do not).
MAX_LINES = 100


def _function_lengths() -> dict[str, int]:
    """`path:line name` → lines, for every function and method in the package."""
    lengths = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                where = f"{path.relative_to(PACKAGE.parent)}:{node.lineno} {node.name}"
                lengths[where] = node.end_lineno - node.lineno + 1
    return lengths


def test_no_function_is_over_max_lines():
    lengths = _function_lengths()
    assert len(lengths) > 100  # the walk found the package
    long = {where: n for where, n in lengths.items() if n > MAX_LINES}
    assert not long, f"functions over {MAX_LINES} lines (split them into named stages): {long}"
