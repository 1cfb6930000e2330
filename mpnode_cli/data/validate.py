"""Check a dataset file completely before anything reads it: `check_dataset(path) -> Report`.

Every field of `docs/dataset-format.md` is checked against the others: array shapes and
dtypes, indices (`graph_index`, `split`) inside their ranges, the root attributes against
the arrays they describe (`num_nodes`, `node_dim`, `control_dim`, `dt` against `time`), the
JSON attributes, the format name and version, and that every stored value is finite; in a
virtual merge (`mpnode merge --virtual`), first that its shards are where HDF5 reads them
from. A file that passes can be read by every verb; one that does not gets one line per
problem.

`mpnode check` prints the report; every reader (`TrajectoryData.load`, hence train,
finetune, evaluate, zeroshot, and `mpnode info`) calls `require_valid` first, so that bad
data never starts a run.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from mpnode_cli.data import integrity
from mpnode_cli.data.arrays import BLOCK_VALUES, nonfinite
from mpnode_cli.data.hdf5 import (
    DENSE_GRAPH_MAX_NODES,
    FORMAT,
    FORMAT_VERSION,
    OPTIONAL_ATTRS,
    REQUIRED_ATTRS,
    SPLIT_NAMES,
    DatasetFormatError,
    _py,
)
from mpnode_cli.data.virtual import virtual_source_problems
from mpnode_cli.graphs import Graphs, degree_range
from mpnode_cli.limits import MULTIPLICITY_MAX
from mpnode_cli.terminal import suggested

# Relative slack when comparing sample spacing with `dt` (float32 time in hand-made files).
_DT_RTOL = 1e-4


@dataclass
class Report:
    """What a check found.

    Attributes:
        path: the file checked. kind: "dataset" or "checkpoint".
        problems: one line each; empty when the file is valid.
        summary: facts about the file (JSON-able), as far as they could be read.
    """

    path: Path
    kind: str
    problems: list[str] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.problems

    def to_dict(self) -> dict[str, Any]:
        return {"path": str(self.path), "kind": self.kind, "valid": self.ok,
                "problems": list(self.problems), "summary": self.summary}


def require_valid(path: str | Path) -> None:
    """Raise unless `path` is a valid dataset.

    Raises:
        FileNotFoundError: no such file.
        DatasetFormatError: one line: the first problem, and how many more there are.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no such dataset file: {path}")
    report = check_dataset(path)
    if not report.ok:
        more = len(report.problems) - 1
        tail = f" (and {more} more: {suggested('check', Path(path))})" if more else ""
        raise DatasetFormatError(f"{path} is not a valid dataset: {report.problems[0]}{tail}")


def check_dataset(path: str | Path, *, deep: bool = False) -> Report:
    """Check every field of a dataset file against the format and against each other;
    `deep`: then read every byte, verifying its checksums (`integrity.deep_problems`)."""
    report = Report(Path(path), "dataset")
    if not report.path.is_file():
        report.problems.append(f"no such file: {path}" if not report.path.exists()
                               else f"{path} is not a regular file")
        return report
    try:
        f = h5py.File(report.path, "r")
    except OSError:
        report.problems.append(f"{path} is not an HDF5 file")
        return report
    with f:
        try:
            integrity.preflight(report.path)  # before `f` reads an attribute
            _Checker(f, report).run()
            report.problems += integrity.deep_problems(f) if deep and report.ok else []
            if report.ok:
                report.summary["checksums"] = integrity.checksum_summary(f, verified=deep)
        except integrity.HDF5_ERRORS as exc:  # a damaged file
            report.problems.append(integrity.name_damage(f, exc))
        except (ValueError, TypeError) as exc:  # h5py on a file it reads oddly
            report.problems.append(f"{path} could not be read completely: {exc}")
    return report


class _Checker:
    """One pass over an open file; each method adds problems and summary facts."""

    def __init__(self, f: h5py.File, report: Report):
        self.f, self.report = f, report
        self.problems, self.summary = report.problems, report.summary
        self.edge_graphs: Graphs | None = None  # version 2's edge lists, once checked

    def problem(self, text: str) -> None:
        self.problems.append(text)

    def run(self) -> None:
        attrs = {key: _py(value) for key, value in self.f.attrs.items()}
        if not self._format(attrs):
            return  # another kind of file: nothing else is meaningful
        missing = virtual_source_problems(self.f)
        if missing:  # the rest would only find the fill values read in their place
            self.problems += missing
            return
        missing = [name for name in REQUIRED_ATTRS if name not in attrs]
        if missing:
            self.problem(f"missing root attributes: {', '.join(missing)}")
        attrs = {**OPTIONAL_ATTRS, **attrs}
        states = self._array("states", required=True)
        if states is None:
            return
        if states.ndim != 4:
            self.problem(f"states must be [K, T, N, D], got shape {states.shape}")
            return
        k, t, n, d = states.shape
        system = attrs.get("system")
        self.summary.update({"system": system if isinstance(system, str) else None,
                             "trajectories": k, "samples": t,
                             "num_nodes": n, "node_dim": d})
        if k < 1 or t < 2 or n < 1 or d < 1:
            self.problem(f"states has shape {states.shape}: a dataset needs at least one "
                         "trajectory, two samples, one node and one state")
        names = self._names(attrs, "state_names", d, "node_dim")
        self._periodic(attrs, names)
        u = self._controls(attrs, k, t, n)
        self._attrs(attrs, n, d, u)
        g = self._graph(k, n, attrs.get("format_version"))
        self._time(attrs, t)
        self._split(k)
        self._optional(k, t, g)
        self._system(attrs, names, d)
        for name in ("states", "controls", *(f"hidden/{h}" for h in self._hidden_names())):
            if name in self.f and isinstance(self.f[name], h5py.Dataset):
                self._finite(name)
        if "fingerprint" in attrs and not self.problems:
            self._fingerprint(attrs["fingerprint"], states)

    def _fingerprint(self, stored: Any, states: h5py.Dataset) -> None:
        """A recorded fingerprint (`mpnode import`, predictions) must still be the data's."""
        from mpnode_cli.data.fingerprint import fingerprint
        from mpnode_cli.data.hdf5 import read_graphs

        per_row = max(1, int(np.prod(states.shape[1:])))
        controls = self.f["controls"] if "controls" in self.f else None
        arrays = (states, read_graphs(self.f), self.f["graph_index"][()], self.f["time"][()])
        rows = max(1, BLOCK_VALUES // per_row)
        have = fingerprint(*arrays, controls=controls, rows=rows)
        self.summary["fingerprint"] = have
        # Written before controls counted, a file with controls recorded the digest of
        # the rest: still the data's own.
        if stored != have and controls is not None and stored == fingerprint(*arrays,
                                                                             rows=rows):
            return
        if stored != have:
            self.problem(f"attribute fingerprint {str(stored)[:12]}... is not the data's "
                         f"({have[:12]}...): the arrays changed after the file was written; "
                         "delete the attribute if that was meant")

    def _format(self, attrs: dict[str, Any]) -> bool:
        name, version = attrs.get("format"), attrs.get("format_version")
        if not isinstance(name, str) or name != FORMAT:
            what = f"format '{name}'" if name is not None else "no 'format' attribute"
            self.problem(f"not an {FORMAT} file ({what})")
            return False
        self.summary["format"] = f"{FORMAT} v{version}"
        if not isinstance(version, int) or isinstance(version, bool) or version < 1:
            self.problem(f"format_version must be a positive integer, got {version!r}")
        elif version > FORMAT_VERSION:
            self.problem(f"format_version {version} is newer than this mpnode reads (up to "
                         f"{FORMAT_VERSION}): upgrade mpnode")
        return True

    def _array(self, name: str, *, required: bool) -> h5py.Dataset | None:
        if name not in self.f:
            if required:
                self.problem(f"missing dataset '{name}'")
            return None
        obj = self.f[name]
        if not isinstance(obj, h5py.Dataset):
            self.problem(f"'{name}' must be a dataset, not a group")
            return None
        if obj.dtype.kind not in "biuf":
            self.problem(f"'{name}' must hold numbers, not {obj.dtype}")
            return None
        return obj

    def _shape(self, name: str, obj: h5py.Dataset, want: tuple, meaning: str) -> bool:
        """Shape `want` (None: any size on that axis); a problem if it differs."""
        ok = len(obj.shape) == len(want) and all(
            w is None or s == w for s, w in zip(obj.shape, want, strict=True))
        if not ok:
            shown = ", ".join("*" if w is None else str(w) for w in want)
            self.problem(f"{name} has shape {list(obj.shape)}, expected [{shown}] {meaning}")
        return ok

    def _names(self, attrs: dict[str, Any], key: str, size: int, dim: str) -> list[str]:
        raw = attrs.get(key)
        try:
            names = json.loads(raw) if isinstance(raw, str) else None
        except ValueError:
            names = None
        if not isinstance(names, list) or not all(isinstance(x, str) for x in names):
            self.problem(f"{key} must be a JSON list of strings, e.g. "
                         f"'[\"x\", \"y\"]', got {raw!r}")
            return []
        if len(names) != size:
            self.problem(f"{key} has {len(names)} names but {dim} is {size}")
        return names

    def _periodic(self, attrs: dict[str, Any], state_names: list[str]) -> None:
        """`periodic_states` (format version 3; absent: none): state names, each once."""
        raw = attrs.get("periodic_states")
        try:
            periodic = json.loads(raw) if isinstance(raw, str) else None
        except ValueError:
            periodic = None
        if not isinstance(periodic, list) or not all(isinstance(x, str) for x in periodic):
            self.problem(f"periodic_states must be a JSON list of state names, got {raw!r}")
            return
        unknown = [name for name in periodic if name not in state_names]
        if unknown or len(set(periodic)) != len(periodic):
            self.problem(f"periodic_states {periodic} must name distinct states among "
                         f"state_names {state_names}")
        if periodic:
            self.summary["periodic_states"] = periodic

    def _controls(self, attrs: dict[str, Any], k: int, t: int, n: int) -> int:
        names = self._names(attrs, "control_names", len(_json_list(attrs["control_names"])),
                            "control_dim")
        u = len(names)
        controls = self._array("controls", required=u > 0)
        if controls is not None:
            if u == 0:
                self.problem("controls is present but control_names is empty")
            else:
                self._shape("controls", controls, (k, t, n, u), "[K, T, N, U]")
        self.summary["control_dim"] = u
        return u

    def _attrs(self, attrs: dict[str, Any], n: int, d: int, u: int) -> None:
        for key, have in (("num_nodes", n), ("node_dim", d), ("control_dim", u)):
            value = attrs.get(key)
            if value is None:
                continue
            if not _is_int(value):
                self.problem(f"attribute {key} must be an integer, got {value!r}")
            elif value != have:
                self.problem(f"attribute {key} is {value} but the arrays have {have}")
        system = attrs.get("system")
        if system is not None and (not isinstance(system, str) or not system):
            self.problem(f"attribute system must be a non-empty string, got {system!r}")
        seed = attrs.get("seed")
        if seed is not None and not _is_int(seed):
            self.problem(f"attribute seed must be an integer, got {seed!r}")
        config = attrs.get("config")
        try:
            parsed = json.loads(config) if isinstance(config, str) else None
        except ValueError:
            parsed = None
        if not isinstance(parsed, dict):
            self.problem(f"attribute config must be a JSON object, got {config!r:.60}")

    def _graph(self, k: int, n: int, version: Any) -> int:
        """The graphs: edge lists (version 2) and the matrices (required in version 1,
        optional in version 2, where they must agree with the edges; version 4 allows a
        multigraph: an edge of multiplicity w is w messages, and w in the matrix); returns G."""
        v1 = version == 1
        multi = _is_int(version) and version >= 4
        before, in_degree = len(self.problems), None
        g = self._edges(n, multi) if not v1 else None
        adjacency = self._array("graph/adjacency", required=v1)
        if adjacency is not None and self._shape("graph/adjacency", adjacency, (None, n, n),
                                                  "[G, N, N]"):
            if g is not None and adjacency.shape[0] != g:
                self.problem(f"graph/adjacency holds {adjacency.shape[0]} graphs but "
                             f"graph/num_edges {g}")
            g = adjacency.shape[0]
            if g < 1:
                self.problem("graph/adjacency holds no graph (G = 0)")
            # Above the threshold a matrix is only scanned, one graph at a time; the same
            # pass sums its rows: the in-degrees of version 1, which has no edge lists.
            in_degree, bad = np.zeros((g, n), np.int64), False
            for i in range(g):
                matrix = adjacency[i]
                if not _counts(matrix, multi):
                    bad = True
                    break
                in_degree[i] = matrix.sum(axis=1)
            if bad:
                self.problem("graph/adjacency must hold only 0 and 1 "
                             "(A[g, i, j] = 1 iff node j sends to node i)" if not multi else
                             "graph/adjacency must hold whole numbers 0–255 (A[g, i, j] the "
                             "edges from node j to node i)")
            elif self.edge_graphs is not None and n <= DENSE_GRAPH_MAX_NODES and (
                    len(self.edge_graphs) == g):
                stored = adjacency[()] if multi else adjacency[()] != 0
                if not np.array_equal(self.edge_graphs.dense(), stored):
                    self.problem("graph/adjacency and graph/edges hold different graphs")
        g = g or 0
        self.summary["graphs"] = g
        if self.edge_graphs is not None:
            in_degree = self.edge_graphs.in_degree()  # [G, N], parallel edges w times
        if g and in_degree is not None and len(self.problems) == before:
            self.summary["in_degree"] = degree_range(in_degree)
        index = self._array("graph_index", required=True)
        if index is not None and self._shape("graph_index", index, (k,), "[K]"):
            if index.dtype.kind not in "iu":
                self.problem(f"graph_index must be integers, not {index.dtype}")
            elif k and g and not (0 <= int(np.min(index)) and int(np.max(index)) < g):
                self.problem(f"graph_index points outside the graphs: values "
                             f"{int(np.min(index))}..{int(np.max(index))}, graphs 0..{g - 1}")
        return g

    def _edges(self, n: int, multi: bool = False) -> int | None:
        """`graph/edges [2, E]` and `graph/num_edges [G]`: ids in 0..N−1, counts that add
        up, no message twice within a graph unless `multi` (format version 4: a multigraph).
        Returns G (None when unreadable)."""
        edges = self._array("graph/edges", required=True)
        counts = self._array("graph/num_edges", required=True)
        if edges is None or counts is None:
            return None
        ok = self._shape("graph/edges", edges, (2, None), "[2, E] (senders, receivers)")
        ok &= self._shape("graph/num_edges", counts, (None,), "[G]")
        if not ok:
            return None
        if edges.dtype.kind not in "iu" or counts.dtype.kind not in "iu":
            self.problem("graph/edges and graph/num_edges must be integers")
            return None
        g, ids, per_graph = counts.shape[0], edges[()].astype(np.int64), counts[()]
        if g < 1:
            self.problem("graph/num_edges holds no graph (G = 0)")
        if (per_graph < 0).any() or int(per_graph.sum()) != ids.shape[1]:
            self.problem(f"graph/num_edges adds up to {int(per_graph.sum())} but graph/edges "
                         f"holds {ids.shape[1]} edges")
            return g
        if ids.size and (ids.min() < 0 or ids.max() >= n):
            self.problem(f"graph/edges holds node ids {int(ids.min())}..{int(ids.max())}; "
                         f"they must lie in 0..{n - 1}")
            return g
        graph_of_edge = np.repeat(np.arange(g, dtype=np.int64), per_graph)
        key = (graph_of_edge * n + ids[1]) * n + ids[0]
        if not multi and len(np.unique(key)) != len(key):
            self.problem("graph/edges holds a message twice within a graph (graphs are "
                         "unweighted: each sender → receiver pair at most once, unless "
                         "format_version 4 says it is a multigraph)")
        else:
            self.edge_graphs = Graphs.from_concatenated(n, ids[0], ids[1], per_graph)
        self.summary["edges"] = int(ids.shape[1])
        return g

    def _time(self, attrs: dict[str, Any], t: int) -> None:
        time = self._array("time", required=True)
        dt = attrs.get("dt")
        dt_ok = isinstance(dt, int | float) and not isinstance(dt, bool) and (
            np.isfinite(dt) and dt > 0)
        if dt is not None and not dt_ok:
            self.problem(f"attribute dt must be a positive finite number, got {dt!r}")
        if time is None or not self._shape("time", time, (t,), "[T] (one time per sample)"):
            return
        ts = time[()].astype(np.float64)
        if not np.isfinite(ts).all():
            self.problem("time holds non-finite values")
            return
        steps = np.diff(ts)
        if (steps <= 0).any():
            at = int(np.argmax(steps <= 0)) + 1
            self.problem(f"time must be strictly increasing (sample {at} is not after {at - 1})")
            return
        if dt_ok and len(steps):
            slack = _DT_RTOL * dt + 1e-9 * float(np.abs(ts).max())
            off = np.abs(steps - dt) > slack
            if off.any():
                first = int(np.argmax(off))
                self.problem(f"attribute dt is {dt:g} but time steps by {steps[first]:g} "
                             f"(between samples {first} and {first + 1}); samples must be "
                             "evenly spaced by dt")
        self.summary["dt"] = dt
        self.summary["t_end"] = float(ts[-1])

    def _split(self, k: int) -> None:
        split = self._array("split", required=True)
        if split is None or not self._shape("split", split, (k,), "[K]"):
            return
        values = split[()]
        if split.dtype.kind not in "iu" or not np.isin(values, (0, 1, 2)).all():
            self.problem("split must hold 0 (train), 1 (validation) or 2 (test) per trajectory")
            return
        counts = np.bincount(values.astype(np.int64), minlength=3)
        self.summary["split"] = {name: int(c) for name, c in zip(SPLIT_NAMES, counts,
                                                                   strict=True)}

    def _optional(self, k: int, t: int, g: int) -> None:
        for name in ("solver/status", "solver/n_f_evals"):
            obj = self._array(name, required=False)
            if obj is not None:
                self._shape(name, obj, (k,), "[K]")
        if "params" in self.f:
            params = self.f["params"]
            if not isinstance(params, h5py.Group):
                self.problem("'params' must be a group")
            else:
                for name in params:
                    obj = self._array(f"params/{name}", required=False)
                    if obj is not None and g and (obj.ndim < 1 or obj.shape[0] != g):
                        self.problem(f"params/{name} has shape {list(obj.shape)}; its first "
                                     f"axis must be the {g} graphs")
                    elif obj is not None and not np.isfinite(obj[()]).all():
                        self.problem(f"params/{name} holds non-finite values")
                for name, value in params.attrs.items():
                    value = _py(value)
                    if not isinstance(value, int | float) or not np.isfinite(value):
                        self.problem(f"params attribute {name} must be a finite number, "
                                     f"got {value!r}")
        for name in self._hidden_names():
            obj = self._array(f"hidden/{name}", required=False)
            if obj is not None and (obj.ndim < 2 or obj.shape[:2] != (k, t)):
                self.problem(f"hidden/{name} has shape {list(obj.shape)}; it must start "
                             f"[K, T] = [{k}, {t}]")

    def _hidden_names(self) -> list[str]:
        hidden = self.f.get("hidden")
        return list(hidden) if isinstance(hidden, h5py.Group) else []

    def _system(self, attrs: dict[str, Any], names: list[str], d: int) -> None:
        """A known system's name promises its states; other data is "custom"."""
        from mpnode_cli.systems.registry import system_class

        system = attrs.get("system")
        if not isinstance(system, str) or system == "custom":
            return
        try:  # built in, or a plug-in this process knows
            want = tuple(system_class(system).state_names)
        except (TypeError, ValueError):
            return
        if len(want) != d:
            self.problem(f"system '{system}' has {len(want)} states per node ({', '.join(want)}) "
                         f"but the file has {d}; name your own data system \"custom\"")

    def _finite(self, name: str) -> None:
        """Count non-finite values block by block and say where the first one is."""
        obj = self.f[name]
        if obj.dtype.kind != "f" or obj.shape[0] == 0:
            return
        line = nonfinite(obj, ("trajectory", "sample", "node", "component"),
                         values=BLOCK_VALUES)
        if line:
            self.problem(f"{name} {line}")


def _json_list(raw: Any) -> list:
    try:
        value = json.loads(raw) if isinstance(raw, str) else None
    except ValueError:
        value = None
    return value if isinstance(value, list) else []


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _counts(matrix: np.ndarray, multi: bool) -> bool:
    """Whether an adjacency matrix holds 0 and 1, or (`multi`) whole numbers 0–255."""
    if not multi:
        return bool(np.isin(matrix, (0, 1)).all())
    values = np.asarray(matrix)
    return bool(((values >= 0) & (values <= MULTIPLICITY_MAX)
                 & (values == np.round(values))).all())
