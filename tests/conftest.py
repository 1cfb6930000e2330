"""Shared fixtures."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest
import torch

if TYPE_CHECKING:
    from mpnode_cli.data.dataset import TrajectoryData

ROOT = Path(__file__).resolve().parents[1]

# The files whose tests take longest (`pytest --durations`, one thread, 11-2026), slowest
# first. `make test` hands whole files to two workers in collection order, so these go
# first and the short files fill in at the end, and both workers finish near together.
SLOW_FIRST = ("test_experiments", "test_distributed", "test_training", "test_quadrotor",
              "test_readme", "test_signals", "test_ensemble", "test_resume_transactional",
              "test_solver", "test_solver_compact", "test_solver_fused",
              "test_ensemble_reports", "test_predict")


def pytest_collection_modifyitems(items: list) -> None:
    """The slow files first (`SLOW_FIRST`), the rest in their order; a file's tests stay
    together and in order (a stable sort)."""
    rank = {name: i for i, name in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.stem, len(rank)))


def child_env(**extra: str) -> dict[str, str]:
    """This interpreter's environment for a child process (`python -m mpnode_cli ...`):
    this checkout's package first on the path, one OpenMP thread, then `extra`."""
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)
    return {**os.environ, "PYTHONPATH": path, "OMP_NUM_THREADS": "1", **extra}

def rounding_apart(steps, scale, dtype: torch.dtype = torch.float64):
    """How far two solves that take the same steps may drift apart when their arithmetic
    rounds differently: another batch size or composition (a matmul's blocking, a
    vectorised against a scalar `pow`), another kernel, BLAS or thread count.

    A step of an s-stage method (s ≤ 7 here) forms each stage and the update as sums of at
    most s + 1 terms, so each path rounds a step's result by at most γ_{s+1}·|y| of its
    own (Higham, *Accuracy and Stability of Numerical Algorithms*, 2nd ed., §4.2); two
    paths by twice that, 16·u·|y|. The flow carries each step's deviation to the output
    multiplied by its growth |∂y(t)/∂y(s)|. With `scale` a bound on |y| times that growth
    over the solve, the outputs differ by at most 16·u·steps·scale (a number, or a tensor
    of them broadcast against the outputs).
    """
    return 16 * torch.finfo(dtype).eps / 2 * steps * scale


def doc_commands(text: str) -> list[list[str]]:
    """Every command of a markdown text's ```bash blocks, in order, as shell words: a line
    and its `\\`-continued lines make one command; `#` comments are dropped."""
    import re
    import shlex

    commands = []
    for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S):
        for line in block.replace("\\\n", " ").splitlines():
            if words := shlex.split(line, comments=True):
                commands.append(words)
    return commands


def fhn(t, y, a_graph, p):
    """examples/fitzhugh_nagumo.py's equations, written again from FitzHugh (1961):
    y = [v (N), w (N)], `a_graph` `[N, N]`, `p` its parameters by name."""
    n = a_graph.shape[0]
    v, w = y[:n], y[n:]
    pull = a_graph @ v - a_graph.sum(axis=1) * v
    return np.concatenate([v - v**3 / 3 - w + p["I"] + p["c"] * pull,
                           p["eps"] * (v + p["a"] - p["b"] * w)])


def fhn_reference(ds, k: int) -> np.ndarray:
    """Trajectory k of an FHN dataset solved again by scipy from its stored initial state,
    on its stored graph: `[T, N, 2]`."""
    from scipy.integrate import solve_ivp

    x0 = ds.states[k, 0].astype(np.float64)  # (N, 2)
    n = x0.shape[0]
    a = ds.adjacency[ds.graph_index[k]].astype(np.float64)
    sol = solve_ivp(fhn, (ds.time[0], ds.time[-1]), np.concatenate([x0[:, 0], x0[:, 1]]),
                    t_eval=ds.time, args=(a, ds.scalar_params), rtol=1e-10, atol=1e-12,
                    method="DOP853")
    return np.stack([sol.y[:n].T, sol.y[n:].T], axis=-1)  # (T, N, 2)


if os.environ.get("MPNODE_TEST_TORCH_THREADS"):
    # A numeric test must hold at any thread count (a reduction split over threads rounds
    # otherwise): `MPNODE_TEST_TORCH_THREADS=2 make test` runs the suite that way.
    torch.set_num_threads(int(os.environ["MPNODE_TEST_TORCH_THREADS"]))
    # The computing verbs set torch's threads from MPNODE_THREADS (default 1) for the rest
    # of the process, and child processes read it too: the same count for them.
    os.environ.setdefault("MPNODE_THREADS", os.environ["MPNODE_TEST_TORCH_THREADS"])
elif os.environ.get("PYTEST_XDIST_WORKER"):
    # `make test` runs two worker processes on a 2-core machine: at torch's default of one
    # thread per core they would oversubscribe it (the CLI's thread policy is the same rule).
    torch.set_num_threads(1)


def lorenz_experiment(title: str, t_end: float, steps: str, run_epochs: int = 0) -> str:
    """An experiment spec (TOML) whose first step, "data", generates Lorenz on 3 nodes: 16
    trajectories sampled every 0.05 up to `t_end`; with `run_epochs`, a step "run" trains
    on it that long; `steps` follow."""
    run = (f'[[steps]]\nid = "run"\nverb = "train"\ndata = "data"\nepochs = {run_epochs}\n'
           if run_epochs else "")
    return (f'title = "{title}"\npaper = "p"\n[[steps]]\nid = "data"\nverb = "generate"\n'
            f'system = "lorenz"\nnodes = 3\ntrajectories = 16\nt_end = {t_end}\ndt = 0.05\n'
            + run + steps)


@pytest.fixture
def float64_default():
    """Run a test with float64 as torch's default dtype (rollouts compared to ~1e-9)."""
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)


def synthetic(k: int, t: int, seed: int, dt: float = 0.1, nodes: int = 3) -> TrajectoryData:
    """K random trajectories of `nodes` nodes × 2 features on a complete graph, all "train",
    in memory (system "toy", file name `toy<seed>.h5`, fingerprint `str(seed)`)."""
    import numpy as np

    from mpnode_cli.data.dataset import TrajectoryData
    from mpnode_cli.graphs.matrices import Graphs

    rng = np.random.default_rng(seed)
    states = rng.normal(size=(k, t, nodes, 2)).cumsum(axis=1) * [1.0, 5.0] + [0.0, 2.0]
    return TrajectoryData(
        states=torch.tensor(states, dtype=torch.float32), controls=None,
        graphs=Graphs.from_adjacency(np.ones((1, nodes, nodes), np.uint8)),
        graph_index=torch.zeros(k, dtype=torch.long),
        time=torch.arange(t, dtype=torch.float64) * dt,
        split=torch.zeros(k, dtype=torch.uint8), system="toy", state_names=("a", "b"),
        control_names=(), path=Path(f"toy{seed}.h5"), fingerprint=str(seed))


def invoke(*args, **kw):
    """`mpnode ARGS` through typer's CliRunner (arguments as strings; `kw` as
    `CliRunner.invoke` takes them, e.g. `input`)."""
    from typer.testing import CliRunner

    from mpnode_cli.cli.app import app

    return CliRunner().invoke(app, [str(a) for a in args], **kw)


def one_line_error(result, code: int = 2) -> str:
    """The one `Error:` line of a refused command, after checking its exit code and that
    it printed no traceback."""
    assert result.exit_code == code, result.output
    assert "Traceback" not in result.output, result.output
    lines = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert len(lines) == 1, result.output
    return lines[0]


@pytest.fixture(scope="session")
def user_files(tmp_path_factory) -> dict[str, Path]:
    """A user's files and what mpnode makes of them, by name, for tests of what the verbs
    write: `states` [6, 5, 3, 2], `adjacency` [3, 3] and `x0` [2, 3, 2] (.npy), `edges` (an
    edge-list text file), `data` (their `mpnode import`), `run` (a model trained on it
    for one epoch) and `checkpoint` (its best.pt)."""
    root = tmp_path_factory.mktemp("user")
    rng = np.random.default_rng(0)
    files = {name: root / f"{name}.npy" for name in ("states", "adjacency", "x0")}
    np.save(files["states"], rng.normal(size=(6, 5, 3, 2)))
    np.save(files["adjacency"], np.ones((3, 3), np.uint8))
    np.save(files["x0"], rng.normal(size=(2, 3, 2)))
    files["edges"] = root / "edges.txt"
    files["edges"].write_text("0 1\n1 2\n2 0\n")
    files["data"], files["run"] = root / "data.h5", root / "run"
    for args in (["import", "--states", files["states"], "--adjacency", files["adjacency"],
                  "--dt", 0.1, "--out", files["data"]],
                 ["train", files["data"], "--epochs", 1, "--batch-size", 2, "--no-plots",
                  "--run-dir", files["run"]]):
        result = invoke(*args)
        assert result.exit_code == 0, result.output
    files["checkpoint"] = files["run"] / "checkpoints" / "best.pt"
    return files


@pytest.fixture
def own_user_files(user_files, tmp_path) -> dict[str, Path]:
    """`user_files` copied into this test's folder: a test may overwrite or lose them."""
    import shutil

    root = user_files["data"].parent
    shutil.copytree(root, tmp_path, dirs_exist_ok=True)
    return {name: tmp_path / path.relative_to(root) for name, path in user_files.items()}


@pytest.fixture(scope="session")
def tiny_checkpoint(tmp_path_factory) -> Path:
    """A one-epoch MP-NODE checkpoint on 8 Lorenz trajectories of 3 nodes (D = 3): a model
    for `simulate` and `evaluate` to read."""
    from typer.testing import CliRunner

    from mpnode_cli.cli.app import app
    from mpnode_cli.config.generate import GenerateConfig
    from mpnode_cli.data.generate import generate

    root = tmp_path_factory.mktemp("tiny")
    data = generate(GenerateConfig(system="lorenz", nodes=3, trajectories=8, t_end=0.2,
                                   dt=0.05, out=root / "l3.h5")).path
    result = CliRunner().invoke(app, ["train", str(data), "--epochs", "1", "--batch-size", "8",
                                      "--no-plots", "--run-dir", str(root / "run")])
    assert result.exit_code == 0, result.output
    return root / "run" / "checkpoints" / "best.pt"


# Run by `guarded_cli` in a child process: CLI commands under a cap on address space.
_GUARDED = """
import json, resource, sys
resource.setrlimit(resource.RLIMIT_AS, (int(sys.argv[1]), int(sys.argv[1])))
from typer.testing import CliRunner
from mpnode_cli.cli.app import app
results = []
for args in json.loads(sys.argv[2]):
    result = CliRunner().invoke(app, args, input="")
    results.append({"exit_code": result.exit_code, "output": result.output})
print(json.dumps(results))
"""


def guarded_cli(*commands: list, memory: int = 3 * 2**30, timeout: float = 120,
                **env: str) -> list:
    """CLI results (`exit_code`, `output`) of `commands` run one after another in a child
    process whose address space is capped at `memory` bytes, with `env` added to its
    environment.

    For inputs that once made a verb allocate without bound: such a verb then fails in the
    child (MemoryError, or a kill at `timeout` seconds) instead of exhausting the machine,
    and a crash (a segfault) fails the test instead of ending the test run.
    """
    import json
    import subprocess
    import sys
    from types import SimpleNamespace

    args = json.dumps([[str(a) for a in command] for command in commands])
    proc = subprocess.run([sys.executable, "-c", _GUARDED, str(memory), args],
                          env=child_env(**env), capture_output=True, text=True,
                          timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return [SimpleNamespace(**r) for r in json.loads(proc.stdout.splitlines()[-1])]


@pytest.fixture
def entry_point(monkeypatch):
    """`entry_point(name, target, folder)`: make `target` ("module:Class", importable from
    `folder`) the one installed mpnode system entry point called `name`, for this test.
    The registry's cache and the imported module are cleared afterwards."""
    import importlib.metadata
    import sys

    from mpnode_cli.systems import registry

    modules: list[str] = []

    def install(name: str, target: str, folder: Path) -> None:
        monkeypatch.syspath_prepend(str(folder))
        point = importlib.metadata.EntryPoint(name, target, registry.ENTRY_POINT_GROUP)
        monkeypatch.setattr(importlib.metadata, "entry_points",
                            lambda group=None: [point] if group == registry.ENTRY_POINT_GROUP
                            else [])
        registry.entry_point_systems.cache_clear()
        modules.append(target.split(":")[0])

    yield install
    registry.entry_point_systems.cache_clear()
    for module in modules:
        sys.modules.pop(module, None)


def gene_data(folder: Path, grid: int = 2, trajectories: int = 48, t_end: float = 2.0,
              name: str = "gene") -> Path:
    """`folder/<name>.h5`: gene dynamics on a grid × grid ER graph, sampled every 0.1 up to
    `t_end` (48 trajectories split 34 / 7 / 7 by default)."""
    from mpnode_cli.config.generate import GenerateConfig
    from mpnode_cli.data.generate import generate

    out = folder / f"{name}.h5"
    generate(GenerateConfig(system="gene", grid=grid, topology="er", trajectories=trajectories,
                            t_end=t_end, dt=0.1, out=out))
    return out


@pytest.fixture(scope="session")
def gene_2x2(tmp_path_factory) -> Path:
    """Gene dynamics on a 2×2 grid (ER graph): 48 trajectories × 21 samples."""
    return gene_data(tmp_path_factory.mktemp("data"))


@pytest.fixture(scope="session")
def gene_ba4(tmp_path_factory) -> Path:
    """Gene dynamics on a 4-node BA graph: 8 trajectories × 21 samples (seed 1)."""
    from mpnode_cli.config.generate import GenerateConfig
    from mpnode_cli.data.generate import generate

    out = tmp_path_factory.mktemp("data") / "gene-ba4.h5"
    generate(GenerateConfig(system="gene", nodes=4, topology="ba", trajectories=8,
                            t_end=2.0, dt=0.1, seed=1, out=out))
    return out
