"""What a system's methods must return, checked where mpnode calls them.

A system of your own is code mpnode did not write, and its mistakes (a right-hand side of
the wrong shape, a sampler that forgets an axis, an exception, a `sys.exit`) would surface
far from their cause, as a traceback or as someone else's error ("not enough values to
unpack"). `CheckedSystem` is a system as `generate` calls it: each method's result is
checked against the contract `System` documents (shapes, dtypes, finite values), and any
error inside it becomes a `PluginError`, one line that names the file, the class and the
method (`mpnode_cli.systems.plugin_calls`, which also checks the vector field the solver
calls, `checked_rhs`).

A `ValueError` is how a system refuses its inputs on purpose ("fhn on 'ba' needs more than
2 nodes"), so one raised by mpnode's own code passes unchanged; one that went through a
plug-in's code is named after it, as its numpy slips are `ValueError`s too.

A vector field that is NaN or inf at the initial states the system drew is an error, not a
trajectory to redraw: the states are checked finite first, so the fault is the field's (a
division by a zero degree, a wrong sign under a root), and redrawing would only hide it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from mpnode_cli.graphs.matrices import EdgeList
from mpnode_cli.systems.plugin_calls import (
    PluginError,
    call,
    described,
    named,
    where,
)

if TYPE_CHECKING:
    from mpnode_cli.systems.base import Simulation, System


def numbers(value: Any, shape: tuple[int, ...], here: str, what: str) -> np.ndarray:
    """`value` as float64 of `shape`, finite.

    Args:
        value: what a method returned. shape: the shape it must have.
        here: the method (`where`). what: the value, as the message names it.

    Raises:
        PluginError: not an array of real numbers, another shape, or NaN or inf.
    """
    try:
        array = np.asarray(value)
    except Exception:  # ragged lists, objects numpy refuses
        array = np.asarray(None)
    if array.dtype.kind not in "biuf":
        raise PluginError(f"{here} returned {described(value)} as {what}, not an array of "
                          "real numbers")
    if array.shape != shape:
        raise PluginError(f"{here} returned {what} of shape {list(array.shape)}, expected "
                          f"{list(shape)}")
    bad = ~np.isfinite(array)
    if bad.any():
        raise PluginError(f"{here} returned {int(bad.sum())} NaN or inf value(s) in {what} "
                          f"(the first at {list(map(int, np.argwhere(bad)[0]))})")
    return array.astype(np.float64)


def named_arrays(value: Any, here: str, what: str, lead: int | None,
                 like: Mapping[str, tuple[int, ...]] | None) -> dict[str, np.ndarray]:
    """A method's `name → array` result (parameters, inputs), each of real numbers, finite.

    Args:
        value: what the method returned. here: the method (`where`). what: the result,
            as the message names it.
        lead: the leading axis each array must have (K trajectories), or None.
        like: name → shape the first call gave (the same names and shapes are needed
            every time, since results are stacked), or None on the first call.

    Raises:
        PluginError: not a dict of arrays of real numbers, another leading axis, other
            names or shapes than the first call's, or NaN or inf.
    """
    if not isinstance(value, Mapping):
        raise PluginError(f"{here} returned {described(value)} as {what}, not a dict of "
                          "arrays by name")
    arrays = {}
    for name, item in value.items():
        try:
            array = np.asarray(item)
        except Exception:  # ragged lists, objects numpy refuses
            array = np.asarray(None)
        if lead is not None and (array.ndim == 0 or len(array) != lead):
            raise PluginError(f"{here} returned {what} '{name}' of shape "
                              f"{list(array.shape)}, expected {lead} along its first axis")
        numbers(array, array.shape, here, f"{what} '{name}'")
        arrays[str(name)] = array  # its dtype kept: the system reads it back as it gave it
    if like is not None:
        got = {name: a.shape[1:] if lead is not None else a.shape for name, a in arrays.items()}
        if got != dict(like):
            raise PluginError(f"{here} returned {what} {got}, but {dict(like)} before: every "
                              "call must give the same names and shapes")
    return arrays


def check_simulation(sim: Any, here: str, batch: int, samples: int, nodes: int,
                     node_dim: int, control_dim: int) -> Simulation:
    """A `simulate` result against its contract (`Simulation`'s shapes).

    Raises:
        PluginError: not a `Simulation`, or a field of another type or shape.
    """
    import torch

    from mpnode_cli.systems.base import Simulation

    if not isinstance(sim, Simulation):
        raise PluginError(f"{here} returned {described(sim)}, not a Simulation")
    expected = {"states": (batch, samples, nodes, node_dim), "status": (batch,),
                "n_f_evals": (batch,)}
    if sim.controls is not None or control_dim:
        expected["controls"] = (batch, samples, nodes, control_dim)
    if sim.rejected is not None:
        expected["rejected"] = (batch,)
    fields = {name: getattr(sim, name) for name in expected}
    fields |= {f"hidden '{name}'": value for name, value in sim.hidden.items()}
    for name, value in fields.items():
        want = expected.get(name)
        if not isinstance(value, torch.Tensor) or (
                want is not None and tuple(value.shape) != want) or (
                want is None and tuple(value.shape[:2]) != (batch, samples)):
            shown = list(want) if want is not None else f"[{batch}, {samples}, ...]"
            raise PluginError(f"{here} returned {name} of {described(value)}, expected a "
                              f"tensor of shape {shown}")
    return sim


def check_graph(graph: Any, n: int, here: str) -> np.ndarray | EdgeList:
    """A graph a system built: `[n, n]` of 0 and 1, or an `EdgeList` of `n` nodes.

    Raises:
        PluginError: another type, size or values.
    """
    if isinstance(graph, EdgeList):
        if graph.num_nodes != n:
            raise PluginError(f"{here} returned an edge list of {graph.num_nodes} nodes, "
                              f"expected {n}")
        return graph
    array = numbers(graph, (n, n), here, "the adjacency matrix")
    if not np.isin(array, (0, 1)).all():
        raise PluginError(f"{here} returned an adjacency matrix holding values other than "
                          "0 and 1")
    return np.asarray(graph)


class CheckedSystem:
    """A system as `generate` calls it: its methods' results checked, their errors named.

    Declarations (`name`, `state_names`, `sparse`, `recipe()`, ...) are read through to the
    system. Results stacked across calls (each graph's parameters, each draw's inputs) must
    have the same names and shapes every time.

    Attributes:
        system: the system itself.
    """

    def __init__(self, system: System) -> None:
        self.system = system
        self._params: dict[str, tuple[int, ...]] | None = None  # the first call's, by name
        self._inputs: dict[str, tuple[int, ...]] | None = None

    def __getattr__(self, name: str) -> Any:
        if name == "system":  # not set yet (a copy being built): no recursion through here
            raise AttributeError(name)
        return getattr(self.system, name)

    def graph(self, topology: str, n: int, seed: int) -> np.ndarray | EdgeList:
        """`System.graph`, checked: `[n, n]` of 0 and 1, or an `EdgeList` of n nodes."""
        return check_graph(call(self.system, "graph", topology, n, seed), n,
                           where(self.system, "graph"))

    def graph_params(self, graph: np.ndarray | EdgeList,
                     rng: np.random.Generator) -> dict[str, np.ndarray]:
        """`System.graph_params`, checked: name → finite array, the same every graph."""
        params = named_arrays(call(self.system, "graph_params", graph, rng),
                              where(self.system, "graph_params"), "parameters", None,
                              self._params)
        if self._params is None:
            self._params = {name: a.shape for name, a in params.items()}
        return params

    def sample(self, graph: np.ndarray | EdgeList, k: int,
               rng: np.random.Generator) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """`System.sample` (or the `sample_initial` it defaults to), checked: float64
        `[k, N, D]` finite initial states, and inputs with a leading axis of k."""
        if _overrides(self.system, "sample"):
            here, drawn = where(self.system, "sample"), call(self.system, "sample", graph, k,
                                                              rng)
        else:  # the default `sample`: the same draws, named after the method written
            here = where(self.system, "sample_initial")
            drawn = (call(self.system, "sample_initial", graph, k, rng), {})
        if not (isinstance(drawn, tuple) and len(drawn) == 2):
            raise PluginError(f"{here} returned {described(drawn)}, not (initial states, "
                              "inputs)")
        y0 = numbers(drawn[0], (k, graph.shape[0], len(self.system.state_names)), here,
                     "initial states [k, N, D]")
        inputs = named_arrays(drawn[1], here, "inputs", k, self._inputs)
        if self._inputs is None:
            self._inputs = {name: a.shape[1:] for name, a in inputs.items()}
        return y0, inputs

    def simulate(self, adjacency: Any, params: dict[str, Any], y0: Any, ts: Any,
                 inputs: dict[str, Any], *, solver: Any, progress: Any = None) -> Simulation:
        """`System.simulate`, checked against `Simulation`'s shapes; errors are named after
        `simulate`, or after `rhs` for a system that keeps the default (one solve of it)."""
        method = "simulate" if _overrides(self.system, "simulate") else "rhs"
        try:
            sim = self.system.simulate(adjacency, params, y0, ts, inputs, solver=solver,
                                       progress=progress)
        except BaseException as exc:
            raise named(self.system, method, exc) from None
        return check_simulation(sim, where(self.system, method), len(y0), len(ts),
                                y0.shape[1], len(self.system.state_names),
                                len(self.system.control_names))

    def reject(self, states: np.ndarray) -> np.ndarray:
        """`System.reject`, checked: bool `[K]`."""
        here = where(self.system, "reject")
        out = call(self.system, "reject", states)
        array = np.asarray(out) if isinstance(out, np.ndarray | list | tuple) else None
        if array is None or array.shape != (len(states),) or array.dtype.kind not in "biu":
            raise PluginError(f"{here} returned {described(out)}, expected bool "
                              f"[{len(states)}], one per trajectory")
        return array.astype(bool)


def _overrides(system: System, method: str) -> bool:
    """Whether `system`'s class defines its own `method` (not `System`'s default)."""
    from mpnode_cli.systems.base import System

    return getattr(type(system), method) is not getattr(System, method)
