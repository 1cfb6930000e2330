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
    FORMAT,
    FORMAT_VERSION,
    OPTIONAL_ATTRS,
    REQUIRED_ATTRS,
    SPLIT_NAMES,
    DatasetFormatError,
    _py,
)
from mpnode_cli.data.reads import block_rows
from mpnode_cli.data.validate_graphs import FileChecks, is_int
from mpnode_cli.data.virtual import virtual_source_problems
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


class _Checker(FileChecks):
    """One pass over an open file; each method adds problems and summary facts."""

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

        controls = self.f["controls"] if "controls" in self.f else None
        arrays = (states, read_graphs(self.f), self.f["graph_index"][()], self.f["time"][()])
        rows = block_rows(states, BLOCK_VALUES)
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
        repeated = sorted({x for x in names if names.count(x) > 1})
        if repeated:  # written before mpnode refused them: columns no one can tell apart
            self.problem(f"{key} {names} repeats {', '.join(map(repr, repeated))}: each "
                         "needs its own name; rename them in the file's attribute")
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
            if not is_int(value):
                self.problem(f"attribute {key} must be an integer, got {value!r}")
            elif value != have:
                self.problem(f"attribute {key} is {value} but the arrays have {have}")
        system = attrs.get("system")
        if system is not None and (not isinstance(system, str) or not system):
            self.problem(f"attribute system must be a non-empty string, got {system!r}")
        elif isinstance(system, str) and not system.isprintable():  # echoed to terminals
            self.problem(f"attribute system {system!a} holds characters that are not "
                         "printable (control or direction marks)")
        seed = attrs.get("seed")
        if seed is not None and not is_int(seed):
            self.problem(f"attribute seed must be an integer, got {seed!r}")
        config = attrs.get("config")
        try:
            parsed = json.loads(config) if isinstance(config, str) else None
        except ValueError:
            parsed = None
        if not isinstance(parsed, dict):
            self.problem(f"attribute config must be a JSON object, got {config!r:.60}")

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
