"""A plug-in's mistakes are one `Error:` line naming its file, class and method, exit 2, and no
file written.

Once: a right-hand side of the wrong shape gave a traceback from the solver; a sampler of
the wrong shape gave "not enough values to unpack", naming neither the plug-in nor the
method; a file that called `sys.exit(0)` as it was imported made `generate` exit 0 with
nothing written. Each case below is the example system (examples/fitzhugh_nagumo.py) with
one mistake put in.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from conftest import invoke, one_line_error

EXAMPLE = (Path(__file__).resolve().parents[2] / "examples" / "fitzhugh_nagumo.py").read_text()

RETURN_F = "        return f\n"
RETURN_DY = "            return torch.stack((dv, dw), dim=-1)  # [K, N, 2]\n"
DRAW = "        return rng.uniform(-self.ic_box, self.ic_box, size=(k, adjacency.shape[0], 2))\n"
RHS = "    def rhs(self, adjacency, params) -> RHS:\n"


def method(source: str) -> str:
    """`source` (one method, indented once) put into the class before `rhs`."""
    return source + "\n" + RHS


# The mistake (text in the example → its replacement) and the words of the error line.
MISTAKES = {
    "rhs of the wrong shape": (
        (RETURN_DY, "            return dv\n"), "rhs", "returned shape [4, 4] torch.float64"),
    "rhs of float32": (
        (RETURN_DY, RETURN_DY.replace(")  #", ").float()  #")), "rhs", "torch.float32"),
    "rhs that is no function": ((RETURN_F, "        return 42\n"), "rhs", "not a function"),
    "rhs that raises": (
        (RETURN_DY, "            return dv / {}[0]\n"), "rhs", "raised KeyError"),
    "rhs that is NaN": (
        (RETURN_DY, RETURN_DY.replace("dim=-1)", "dim=-1) * float('nan')")), "rhs",
        "NaN or inf at the initial states of 4 of 4"),
    "sampler of the wrong shape": (
        (DRAW, DRAW.replace(", 2))", "))")), "sample_initial",
        "initial states [k, N, D] of shape [4, 4], expected [4, 4, 2]"),
    "sampler of NaN": (
        (DRAW, DRAW.replace("2))\n", "2)) * np.nan\n")), "sample_initial", "NaN or inf"),
    "sampler that misuses numpy": (
        (DRAW, DRAW.replace("return", "return np.ones(3) +")), "sample_initial",
        "operands could not be broadcast"),
    "sample without its inputs": (
        (RHS, method("    def sample(self, adjacency, k, rng):\n"
                     "        return self.sample_initial(adjacency, k, rng)\n")),
        "sample", "not (initial states, inputs)"),
    "graph parameters that exit": (
        (RHS, method("    def graph_params(self, adjacency, rng):\n"
                     "        import sys\n        sys.exit(3)\n")),
        "graph_params", "called sys.exit(3)"),
    "reject of a number": (
        (RHS, method("    def reject(self, states):\n        return 3\n")), "reject",
        "expected bool [4]"),
    "simulate of a dict": (
        (RHS, method("    def simulate(self, *args, **kwargs):\n        return {}\n")),
        "simulate", "not a Simulation"),
}


@pytest.mark.parametrize("mistake", list(MISTAKES))
def test_a_plugins_mistake_names_its_file_class_and_method(tmp_path, mistake):
    (old, new), name, words = MISTAKES[mistake]
    assert old in EXAMPLE
    path = tmp_path / "mine.py"
    path.write_text(EXAMPLE.replace(old, new))
    out = tmp_path / "x.h5"
    result = invoke("generate", "--system-file", path, "--nodes", 4, "--trajectories", 4,
                    "--t-end", 1, "--out", out)
    line = one_line_error(result)
    assert f"FitzHughNagumo.{name} ({path})" in line and words in line, line
    assert not out.exists()


@pytest.mark.parametrize(("source", "words"), [
    ("import sys\nsys.exit(0)\n", "called sys.exit(0) as it was imported"),
    ("raise SystemExit('bye')\n", "called sys.exit('bye') as it was imported"),
    (EXAMPLE + "\nimport sys\nsys.exit()\n", "called sys.exit(None)"),
    ("import os\nos._exit(0)\n", "called os._exit(0)"),  # would end the test run itself
])
def test_a_plugin_that_exits_as_it_is_imported_is_one_line(tmp_path, source, words):
    path = tmp_path / "mine.py"
    path.write_text(source)
    out = tmp_path / "x.h5"
    line = one_line_error(invoke("generate", "--system-file", path, "--out", out))
    assert f"--system-file {path} does not import: it {words}" in line, line
    assert not out.exists()
    assert os._exit.__module__ == "posix" or os._exit.__name__ == "_exit"  # given back


@pytest.mark.parametrize(("old", "new", "words"), [
    ('"c": 0.1}', '"c": "strong"}', "declares defaults = "),
    ('("v", "w")', '"vw"', "declares state_names = 'vw', not a tuple"),
    ('("v", "w")', '("v", "v")', "declares state_names = ('v', 'v'), not a tuple of at least "
     "one name, each once"),
    ("default_nodes: ClassVar[int] = 4", "default_nodes: ClassVar[int] = 0",
     "declares default_nodes = 0, not a whole number"),
    ('"trajectories": 200, "t_end"', '"trajectories": 200, "horizon"',
     "declares data_defaults = "),
])
def test_a_plugins_declarations_are_checked_as_it_loads(tmp_path, old, new, words):
    assert old in EXAMPLE
    path = tmp_path / "mine.py"
    path.write_text(EXAMPLE.replace(old, new))
    line = one_line_error(invoke("generate", "--system-file", path, "--out", tmp_path / "x.h5"))
    assert f"--system-file {path}: the system FitzHughNagumo {words}" in line, line


def test_an_entry_point_that_exits_as_it_loads_is_one_line(tmp_path, entry_point):
    (tmp_path / "exits_on_import.py").write_text("import sys\nsys.exit(0)\n")
    entry_point("mine", "exits_on_import:Mine", tmp_path)
    line = one_line_error(invoke("generate", "mine", "--out", tmp_path / "x.h5"))
    assert "entry point 'mine' (exits_on_import:Mine) does not load: it called " \
           "sys.exit(0)" in line, line
    assert not (tmp_path / "x.h5").exists()


def test_a_plugin_that_exits_while_it_runs_is_one_line_and_leaves_nothing(tmp_path):
    path, out = tmp_path / "mine.py", tmp_path / "x.h5"
    path.write_text(EXAMPLE.replace(RETURN_DY, "            os._exit(0)\n" + RETURN_DY)
                    .replace("import numpy as np\n", "import os\n\nimport numpy as np\n", 1))
    line = one_line_error(invoke("generate", "--system-file", path, "--nodes", 4,
                                 "--trajectories", 4, "--out", out))
    assert f"FitzHughNagumo.rhs ({path}): it called os._exit(0)" in line, line
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["mine.py"]
    assert os._exit.__module__ == "posix" or os._exit.__name__ == "_exit"  # given back


def test_a_plugin_named_custom_is_refused(tmp_path):
    path = tmp_path / "mine.py"
    assert 'name: ClassVar[str] = "fhn"' in EXAMPLE
    path.write_text(EXAMPLE.replace('name: ClassVar[str] = "fhn"',
                                    'name: ClassVar[str] = "custom"'))
    line = one_line_error(invoke("generate", "--system-file", path, "--out", tmp_path / "x.h5"))
    assert "'custom' names the data mpnode import makes" in line, line
    assert not (tmp_path / "x.h5").exists()
