"""Swing-equation power grids, brought into mpnode as a user's own data (`mpnode import`).

Each node i is a synchronous machine, a generator or a consumer, in the second-order
Kuramoto (swing-equation) model of a power grid (Filatrella, Nielsen & Pedersen, Eur. Phys.
J. B 61, 485–491, 2008; Rohden, Sorge, Timme & Witthaut, Phys. Rev. Lett. 109, 064101,
2012), with state [θ, ω], phase and frequency deviation from the grid's nominal frequency:

    θ̇_i = ω_i
    ω̇_i = P_i − γ ω_i + K Σ_j A_ij sin(θ_j − θ_i)

P_i is the node's power injection (positive: it generates, negative: it consumes), drawn
once per trajectory and held constant, so it reaches the model as a control `P` (zero-order
hold, the same value at every sample). The coupling is an unnormalised sum over the
lines, so a hub's restoring force grows with its degree.

The defaults were chosen so that a trajectory is neither trivial nor unbounded on
Barabási–Albert graphs (m = 2) of 10, 20 and 40 nodes: P ~ N(0, 0.5²) minus its mean over
the nodes (the injections balance, Σ_i P_i = 0, so the mean frequency decays as e^{−γt}
instead of drifting), K = 2 and γ = 1, where every sampled grid locks within the horizon
t_end = 20 (frequencies below 0.05 at the end) after a transient of phase slips and
oscillations that lasts about half of it. Locking bounds the raw, unwrapped phases (about
±10 at 40 nodes), so no sine or cosine of θ is needed; with larger P or smaller K some
grids never lock and their phases drift without bound. The fastest mode of the locked grid,
ω² ≈ K (d_max + 1) at a hub of degree d_max, has a period of about 1.1 at 40 nodes, which
dt = 0.2 still resolves.

Usage:
    .venv/bin/python bench/power_grid.py --out datasets/grid-n10.h5 --nodes 10 \\
        --trajectories 500 --graphs 8 --seed 0 --graph-seed 0

or from Python, `make_dataset(out, nodes, trajectories, seed, graph_seed)`. It solves each
trajectory with scipy's `solve_ivp` (DOP853, rtol = atol = 1e-10), writes the arrays `mpnode
import` takes (states.npz with `states [K, T, N, 2]` and `time [T]`, controls.npy `[K, T, N,
1]`, adjacency.npy `[K, N, N]`, one graph per trajectory, so a dataset may hold several
graphs) and runs `python -m mpnode_cli import` on them. Graph g (of `graphs`) is the `ba`
graph `mpnode generate --topology ba --graph-seed S` builds for seed S + g with m edges per
new node (`mpnode_cli.graphs.topologies.make_graph`), and trajectories are spread over the graphs in
contiguous blocks, as `mpnode generate --graphs` spreads them. θ is declared periodic
(`--periodic theta`): the field depends on it only through sin(θ_j − θ_i), so
`mpnode train --periodic embed` may feed the node networks its sine and cosine. The
physical parameters are not stored in the dataset (an imported file records only its
inputs' paths and sha256): they are written beside the arrays as `power_grid.json`
(`--keep-arrays DIR` keeps them).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from mpnode_cli.graphs.topologies import make_graph

ROOT = Path(__file__).resolve().parent.parent

STATE_NAMES = ("theta", "omega")
CONTROL_NAMES = ("P",)


@dataclass(frozen=True)
class SwingParams:
    """The grid's physics and sampling.

    Attributes:
        gamma: damping γ. coupling: line capacity K. power: standard deviation of the
            injections P_i before their mean over the nodes is removed.
        m: edges each new node brings to the Barabási–Albert graph.
        t_end, dt: samples at `0, dt, ..., t_end`.
        omega_box: initial ω uniform in [−omega_box, omega_box] (θ uniform in [−π, π]).
    """

    gamma: float = 1.0
    coupling: float = 2.0
    power: float = 0.5
    m: int = 2
    t_end: float = 20.0
    dt: float = 0.2
    omega_box: float = 1.0

    @property
    def time(self) -> np.ndarray:
        """`[T]` sample times `0, dt, ..., t_end`."""
        steps = round(self.t_end / self.dt)
        if steps < 1 or abs(steps * self.dt - self.t_end) > 1e-9 * max(1.0, self.t_end):
            raise ValueError(f"t_end ({self.t_end:g}) must be a whole number (≥ 1) of dt "
                             f"({self.dt:g}) steps")
        return np.arange(steps + 1) * self.dt


@dataclass(frozen=True)
class PowerGrids:
    """K simulated trajectories, in the arrays `mpnode import` takes.

    Attributes:
        time: `[T]`. states: float64 `[K, T, N, 2]` (θ, ω). controls: float64 `[K, T, N, 1]`
            (P, constant in time). adjacency: uint8 `[K, N, N]`, each trajectory's graph,
            `A[i, j] = 1` iff j sends to i (symmetric). graph_index: `[K]` which of the
            graphs each trajectory runs on. n_f_evals: `[K]` right-hand-side evaluations.
    """

    time: np.ndarray
    states: np.ndarray
    controls: np.ndarray
    adjacency: np.ndarray
    graph_index: np.ndarray
    n_f_evals: np.ndarray


def swing_rhs(adjacency: np.ndarray, power: np.ndarray, gamma: float,
              coupling: float) -> Callable[[float, np.ndarray], np.ndarray]:
    """f(t, y [2N]) → [2N] of one grid, y = [θ (N), ω (N)].

    Args:
        adjacency: `[N, N]`, `A[i, j] = 1` iff j sends to i.
        power: `[N]` injections P.
        gamma, coupling: γ and K.
    """
    n = adjacency.shape[0]
    receivers, senders = np.nonzero(adjacency)  # [E] each
    # Per line rather than as A @ sin(...): O(E) per evaluation instead of O(N²).

    def f(t: float, y: np.ndarray) -> np.ndarray:
        theta, omega = y[:n], y[n:]
        flow = np.bincount(receivers, weights=np.sin(theta[senders] - theta[receivers]),
                           minlength=n)  # [N]: Σ_j A_ij sin(θ_j − θ_i)
        return np.concatenate([omega, power - gamma * omega + coupling * flow])

    return f


def simulate(nodes: int, trajectories: int, seed: int, graph_seed: int, graphs: int = 1,
             params: SwingParams | None = None) -> PowerGrids:
    """Solve `trajectories` grids of `nodes` nodes on `graphs` Barabási–Albert graphs.

    Initial θ ~ U(−π, π), ω ~ U(−omega_box, omega_box) and P ~ N(0, power²) minus its mean
    come from `numpy.random.default_rng(seed)`, one trajectory after another.

    Raises:
        ValueError: a horizon that is not a whole number of steps, or a graph the sizes
            cannot have (m ≥ nodes).
        RuntimeError: a trajectory scipy could not solve.
    """
    from scipy.integrate import solve_ivp

    params = params or SwingParams()
    if not 1 <= graphs <= trajectories:
        raise ValueError(f"need 1 ≤ graphs ≤ trajectories, got {graphs} graphs for "
                         f"{trajectories} trajectories")
    time = params.time
    pool = np.stack([make_graph("ba", nodes, graph_seed + g, m=params.m)
                     for g in range(graphs)])  # [G, N, N]
    graph_index = np.arange(trajectories) * graphs // trajectories  # [K], contiguous blocks
    rng = np.random.default_rng(seed)
    states = np.empty((trajectories, len(time), nodes, 2))
    powers = np.empty((trajectories, nodes))
    n_f_evals = np.empty(trajectories, dtype=np.int64)
    for k in range(trajectories):
        theta0 = rng.uniform(-np.pi, np.pi, nodes)
        omega0 = rng.uniform(-params.omega_box, params.omega_box, nodes)
        power = params.power * rng.standard_normal(nodes)
        power -= power.mean()
        f = swing_rhs(pool[graph_index[k]], power, params.gamma, params.coupling)
        sol = solve_ivp(f, (0.0, time[-1]), np.concatenate([theta0, omega0]), t_eval=time,
                        method="DOP853", rtol=1e-10, atol=1e-10)
        if sol.status != 0:
            raise RuntimeError(f"trajectory {k} failed: {sol.message}")
        states[k] = sol.y.T.reshape(len(time), 2, nodes).transpose(0, 2, 1)  # [T, N, 2]
        powers[k] = power
        n_f_evals[k] = sol.nfev
    controls = np.broadcast_to(powers[:, None, :, None],
                               (trajectories, len(time), nodes, 1)).copy()  # [K, T, N, 1]
    return PowerGrids(time=time, states=states, controls=controls,
                      adjacency=pool[graph_index], graph_index=graph_index,
                      n_f_evals=n_f_evals)


def write_arrays(grids: PowerGrids, folder: Path, record: dict) -> dict[str, Path]:
    """Write the arrays `mpnode import` reads, and `record` as `power_grid.json`, to
    `folder`; return the files by their `mpnode import` option."""
    folder.mkdir(parents=True, exist_ok=True)
    files = {"states": folder / "states.npz", "controls": folder / "controls.npy",
             "adjacency": folder / "adjacency.npy"}
    np.savez(files["states"], states=grids.states, time=grids.time)
    np.save(files["controls"], grids.controls)
    np.save(files["adjacency"], grids.adjacency)
    (folder / "power_grid.json").write_text(json.dumps(record, indent=2) + "\n")
    return files


def make_dataset(out: Path, nodes: int, trajectories: int, seed: int, graph_seed: int, *,
                 graphs: int = 1, params: SwingParams | None = None,
                 dtype: str = "float32", split: str | None = None,
                 work_dir: Path | None = None, force: bool = False) -> Path:
    """Simulate power grids and import them as the mpnode dataset `out`.

    Args:
        out: the `.h5` file to write.
        nodes, trajectories: N and K.
        seed: initial states and injections, and the train/validation/test split.
        graph_seed: graph g is `make_graph("ba", nodes, graph_seed + g, m=params.m)`.
        graphs: G distinct graphs, trajectories spread over them in contiguous blocks.
        params: the physics and sampling (default `SwingParams()`).
        dtype: storage dtype of the dataset, float32 or float64.
        split: train,validation,test fractions (default: `mpnode import`'s).
        work_dir: where the imported arrays and `power_grid.json` are kept; default a
            temporary folder, removed afterwards.
        force: replace an existing `out`.

    Returns:
        `out`.

    Raises:
        RuntimeError: `mpnode import` refused the arrays (its one-line error).
    """
    params = params or SwingParams()
    out = Path(out)
    grids = simulate(nodes, trajectories, seed, graph_seed, graphs, params)
    record = {"equations": "theta' = omega; omega' = P - gamma omega + "
                           "coupling sum_j A_ij sin(theta_j - theta_i)",
              "nodes": nodes, "trajectories": trajectories, "seed": seed,
              "graph_seed": graph_seed, "graphs": graphs, **asdict(params)}
    with tempfile.TemporaryDirectory() as scratch:
        files = write_arrays(grids, Path(work_dir or scratch), record)
        command = [sys.executable, "-m", "mpnode_cli", "import",
                   "--states", str(files["states"]), "--adjacency", str(files["adjacency"]),
                   "--controls", str(files["controls"]),
                   "--state-names", ",".join(STATE_NAMES), "--periodic", "theta",
                   "--control-names", ",".join(CONTROL_NAMES),
                   "--dt", repr(params.dt), "--seed", str(seed), "--dtype", dtype,
                   "--out", str(out)]
        command += ["--split", split] if split else []
        command += ["--force"] if force else []
        path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)
        done = subprocess.run(command, env={**os.environ, "PYTHONPATH": path},
                              capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"mpnode import failed ({done.returncode}): "
                           f"{(done.stderr or done.stdout).strip()}")
    return out


def main(argv: list[str] | None = None) -> None:
    defaults = SwingParams()
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="the .h5 dataset to write")
    parser.add_argument("--nodes", type=int, default=10)
    parser.add_argument("--trajectories", type=int, default=500)
    parser.add_argument("--graphs", type=int, default=1, help="distinct BA graphs")
    parser.add_argument("--seed", type=int, default=0, help="initial states, P and split")
    parser.add_argument("--graph-seed", type=int, default=0, help="graph g has seed S + g")
    for name in ("gamma", "coupling", "power", "t_end", "dt", "omega_box"):
        parser.add_argument(f"--{name.replace('_', '-')}", type=float,
                            default=getattr(defaults, name))
    parser.add_argument("--m", type=int, default=defaults.m, help="BA edges per new node")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    parser.add_argument("--split", default=None, help="train,validation,test fractions")
    parser.add_argument("--keep-arrays", type=Path, default=None,
                        help="folder to keep the imported arrays and power_grid.json in")
    parser.add_argument("--force", action="store_true", help="replace an existing --out")
    args = parser.parse_args(argv)
    params = SwingParams(gamma=args.gamma, coupling=args.coupling, power=args.power, m=args.m,
                         t_end=args.t_end, dt=args.dt, omega_box=args.omega_box)
    try:
        out = make_dataset(args.out, args.nodes, args.trajectories, args.seed, args.graph_seed,
                           graphs=args.graphs, params=params, dtype=args.dtype,
                           split=args.split, work_dir=args.keep_arrays, force=args.force)
    except (ValueError, RuntimeError) as exc:
        sys.exit(f"Error: {exc}")
    from mpnode_cli.data.hdf5 import read_dataset

    ds = read_dataset(out)
    in_degree = ds.adjacency.sum(axis=-1).max(axis=-1)  # [G]
    ranges = ", ".join(f"{name} [{ds.states[..., i].min():.2f}, {ds.states[..., i].max():.2f}]"
                       for i, name in enumerate(ds.state_names))
    print(f"{out}: K={len(ds.states)} T={len(ds.time)} N={ds.num_nodes} graphs={len(in_degree)} "
          f"max in-degree {int(in_degree.max())}; {ranges}; "
          f"P [{ds.controls.min():.2f}, {ds.controls.max():.2f}]")


if __name__ == "__main__":
    main()
