"""The package's shape: no file in `mpnode_cli/` over `FILE_LIMIT` lines, no function or
method over `FUNCTION_LIMIT` lines, with a ratchet for today's offenders.

A function's size is its body without the docstring: `end_lineno` of the `def` minus the
line of its first statement after the docstring, plus one (signature, decorators and
docstring do not count; comments and blank lines inside the body do). A nested function
counts on its own and inside its parent. Where two definitions share a qualified name
(a property's getter and setter), the larger counts. A file's size is its line count
(`wc -l`), of `.py` files only. The source is read with `ast`, so this imports nothing.

No two modules import each other, directly or round a longer loop: imports inside
functions count (they run), those under `if TYPE_CHECKING:` do not.

The ratchet: `FILE_RATCHET` and `FUNCTION_RATCHET` list what is over its limit today,
with its size. A listed one may shrink (lower its entry when it does) but not grow; one
that meets its limit must leave the list; anything not listed must meet the limit.
"""

from __future__ import annotations

import ast
from functools import cache
from pathlib import Path

import networkx as nx

PACKAGE = Path(__file__).resolve().parents[1] / "mpnode_cli"
FILE_LIMIT = 400
FUNCTION_LIMIT = 60

# Over the limit today: path → lines. Lower an entry when its file shrinks; remove it once
# the file meets the limit.
FILE_RATCHET: dict[str, int] = {}
# Over the limit today: "path::Class.function" → body lines (docstring excluded).
FUNCTION_RATCHET: dict[str, int] = {}


def body_lines(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Lines from the first statement after the docstring to the function's last line."""
    body = node.body
    first = body[0] if body else None
    if (isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant)
            and isinstance(first.value.value, str)):
        body = body[1:]
    return node.end_lineno - body[0].lineno + 1 if body else 0


def function_sizes(tree: ast.AST, where: str) -> dict[str, int]:
    """`where::Qual.name` → body lines, for every function and method in `tree`."""
    sizes: dict[str, int] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                key = f"{where}::{prefix}{child.name}"
                sizes[key] = max(sizes.get(key, 0), body_lines(child))
                visit(child, f"{prefix}{child.name}.")
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")
            else:
                visit(child, prefix)

    visit(tree, "")
    return sizes


@cache
def package_sizes() -> tuple[dict[str, int], dict[str, int]]:
    """(path → lines, `path::function` → body lines) over every `.py` file of the package."""
    files: dict[str, int] = {}
    functions: dict[str, int] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        where = path.relative_to(PACKAGE.parent).as_posix()
        text = path.read_text(encoding="utf-8")
        files[where] = len(text.splitlines())
        functions.update(function_sizes(ast.parse(text, filename=str(path)), where))
    return files, functions


def ratchet_problems(sizes: dict[str, int], ratchet: dict[str, int], limit: int) -> list[str]:
    """What breaks the ratchet: a new offender, a listed one that grew, one that is fixed."""
    problems = []
    for name, size in sorted(sizes.items()):
        if name not in ratchet and size > limit:
            problems.append(f"{name}: {size} lines, over the limit of {limit} (split it)")
    for name, listed in sorted(ratchet.items()):
        size = sizes.get(name, 0)
        if size <= limit:
            problems.append(f"{name}: {size} lines now meets the limit of {limit}; "
                            "remove it from the ratchet")
        elif size > listed:
            problems.append(f"{name}: grew from {listed} to {size} lines (over the limit "
                            f"of {limit}: it may only shrink)")
    return problems


def test_files_are_at_most_file_limit_lines():
    files, _ = package_sizes()
    assert len(files) > 50  # the walk found the package
    problems = ratchet_problems(files, FILE_RATCHET, FILE_LIMIT)
    assert not problems, "\n".join(problems)


def test_functions_are_at_most_function_limit_lines():
    _, functions = package_sizes()
    assert len(functions) > 500  # the walk found the package's functions
    problems = ratchet_problems(functions, FUNCTION_RATCHET, FUNCTION_LIMIT)
    assert not problems, "\n".join(problems)


def test_body_lines_leave_out_the_docstring_and_count_nested_functions():
    source = '''
class A:
    @property
    def p(self):
        """Doc
        string."""
        x = 1

        return x

def outer():
    def inner():
        pass
    return inner

def only_doc():
    """Nothing else."""
'''
    sizes = function_sizes(ast.parse(source), "m.py")
    assert sizes == {"m.py::A.p": 3, "m.py::outer": 3, "m.py::outer.inner": 1,
                     "m.py::only_doc": 0}


def test_the_ratchet_refuses_new_grown_and_fixed_entries():
    ratchet = {"a": 70, "b": 70, "c": 70}
    sizes = {"a": 69, "b": 71, "c": 60, "d": 61, "e": 60}
    problems = ratchet_problems(sizes, ratchet, 60)
    assert [p.split(":")[0] for p in problems] == ["d", "b", "c"]
    assert ratchet_problems({"a": 65}, {"a": 70}, 60) == []  # shrinking is fine


def imports_of(tree: ast.AST, modules: set[str]) -> set[str]:
    """The package modules a module's source imports at run time (in functions too, not
    under `if TYPE_CHECKING:`); `from package import module` names the module."""
    typing_only = {id(n) for node in ast.walk(tree)
                   if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING"
                   for part in node.body for n in ast.walk(part)}
    found = set()
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.ImportFrom) and node.module:
            for alias in node.names:
                full = f"{node.module}.{alias.name}"
                found.add(full if full in modules else node.module)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return found & modules


def import_cycles(sources: dict[str, str]) -> list[list[str]]:
    """Every loop of imports among `sources` (module name → its source), each starting
    at its first module by name."""
    graph = nx.DiGraph()
    modules = set(sources)
    for name, text in sources.items():
        graph.add_node(name)
        graph.add_edges_from((name, other) for other in imports_of(ast.parse(text), modules)
                             if other != name)
    loops = [c[c.index(min(c)):] + c[:c.index(min(c))] for c in nx.simple_cycles(graph)]
    return sorted(loops)


def test_no_modules_import_each_other():
    sources = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        sources[name] = path.read_text(encoding="utf-8")
    cycles = import_cycles(sources)
    assert not cycles, "\n".join(" -> ".join(c + c[:1]) for c in cycles)


def test_a_loop_through_a_function_import_is_found_and_a_typing_one_is_not():
    sources = {"p.a": "def f():\n    from p.b import g\n",
               "p.b": "from p import c\n",
               "p.c": "import p.a\n",
               "p.d": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import p.a\n",
               "p": ""}
    assert import_cycles(sources) == [["p.a", "p.b", "p.c"]]

