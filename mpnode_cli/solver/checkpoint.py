"""Checkpointed backpropagation through a solver loop: each step is one autograd node that
keeps nothing, and the backward pass recomputes the step from a stored solver state.

Plain backpropagation through a solve keeps what autograd saves at every evaluation of f
in every step (f's activations) and the graph of every op, so its memory grows with the
number of steps. `solve(..., checkpoints=C)` runs each step of the loop
(`adaptive.loop_step`, `fixed.fixed_step`) through `Checkpointed`:

- **Forward.** A step runs as usual (grad enabled, the same ops as a plain solve, so the
  same numbers), under saved-tensor hooks that keep nothing, and its graph is dropped: to
  autograd the step is one node (`_Step`) from the differentiable part of the loop's carry
  before it (y, k₁) and the tensors f uses from outside the step (its parameters, found at
  the first step: `_outside`) to the carry after it. At most C solver states are kept: the
  whole carry (t, y, k₁, step size and controller history, counters, status), detached,
  and torch's random state, of every s-th step, s starting at 1 and doubling, dropping
  every other state, whenever C are held: a simple online scheme for a number of steps
  that is not known in advance (P. Stumm & A. Walther, "New algorithms for optimal online
  checkpointing", SIAM J. Sci. Comput. 32(2), 2010, place them optimally).
- **Backward.** Autograd runs the steps' nodes last to first. Node j reruns the steps from
  the nearest state at or before j up to j, keeping up to C more states on the way by the
  binomial rule of revolve (A. Griewank & A. Walther, "Algorithm 799: revolve", ACM TOMS
  26(1), 2000; `advance_length`), reruns step j with its graph and takes its
  vector-Jacobian product (`torch.autograd.grad`). The reruns run the forward's ops in the
  same order from the same values, so the step sizes and accept/reject decisions, which
  depend on forward values only, are the forward's, and each step's vector-Jacobian
  product is plain backprop's where f is deterministic: the gradient differs from plain
  backprop's only by the order in which the steps' parts of a parameter's gradient are
  summed (~1e-15 relative in float64). diffrax's `RecursiveCheckpointAdjoint` does the
  same in JAX (offline, for a known bound on the steps).

**Cost.** Memory: at most 2·C states, one step's graph and saved tensors (in the backward
pass), and per step one autograd node and its host-side arguments (a few hundred bytes).
Time: a step runs once in the forward pass, once more for its node's backward, and up to
r times in between, r the smallest with C(C + 1 + r, r) ≥ L, L ≤ 2·N/C the steps between
two kept states of a solve of N steps: 3 forward passes in all where L ≤ C + 2, 4 up to
(C + 2)(C + 3)/2, and so on.

**Guards.** A rerun that reaches a kept state (or the end) must arrive with the forward's
counters, statuses and flags, and give as many differentiable outputs: otherwise a
RuntimeError says that f is not deterministic. f must use the same tensors from outside
at every step (those of the first step get gradients), and pass those that need a gradient
to torch functions or tensor methods, which `torch.overrides.TorchFunctionMode` sees; one
it hides (in a custom autograd.Function, say) is refused at the first step.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import torch
from torch.overrides import TorchFunctionMode

# `step(carry, *args) -> (carry, info)`: one step of a loop. `carry` (tensors in tuples and
# NamedTuples) is all that a step reads of the previous ones; `args` are host-side values
# (kept per step, for the reruns); `info` is what the loop reads besides.
Step = Callable[..., tuple[Any, Any]]

_NOT_DETERMINISTIC = (
    "checkpointed solve: the recomputation of step {step} in the backward pass differs from "
    "the forward pass ({what}): the right-hand side must compute the same values from the "
    "same inputs (on CUDA, torch.use_deterministic_algorithms(True)); or solve without "
    "checkpoints")
_HIDDEN = (
    "checkpointed solve: the right-hand side uses a tensor made outside it that needs a "
    "gradient ({node}) without passing it to a torch function the solver can watch (a "
    "custom autograd.Function?): pass it through torch functions, or solve without "
    "checkpoints")


def _drop(x: torch.Tensor) -> None:
    """Keep nothing of a saved tensor: the step's graph is not differentiated."""


def _gone(_: None) -> torch.Tensor:
    raise RuntimeError("checkpointed solve: a dropped step graph was differentiated")


class _State(NamedTuple):
    """A kept solver state: the carry before a step, and torch's random state there."""

    carry: Any  # detached, each tensor requiring grad as the forward's did
    rng: tuple[torch.Tensor, ...]


class Checkpointed:
    """A loop's `step`, run as one autograd node per step that keeps nothing; see the
    module docstring.

    Args:
        step: `step(carry, *args) -> (carry, info)`, the loop's step.
        checkpoints: C ≥ 1, the solver states kept by the forward pass (and, at most,
            by the backward pass besides).
        replica: makes the step that the reruns run (None: `step` itself): the same
            computation, without side effects on the solve's result. Made anew for
            each backward pass.

    Attributes:
        reruns: steps rerun so far (by backward passes, and once to find f's tensors).
        outside: the tensors f uses from outside the steps, which get gradients.
    """

    def __init__(self, step: Step, checkpoints: int, replica: Callable[[], Step] | None = None):
        self.step, self.replica, self.capacity = step, replica, checkpoints
        self.stride = 1
        self.kept: dict[int, _State] = {}  # the forward pass's, every `stride`-th step
        self.extra: dict[int, _State] = {}  # the backward pass's
        self.args: list[tuple] = []  # per step: its host-side arguments
        self.final: tuple[torch.Tensor, ...] = ()  # the last step's decisions
        self.devices: list[int] = []  # CUDA devices whose random state is kept
        self.outside: list[torch.Tensor] | None = None
        self.reruns = 0
        self._rerun: Step | None = None
        self._last = math.inf  # the step whose node ran last (a new pass restarts high)
        self._rng_kept: tuple[torch.Tensor, ...] = ()

    def __call__(self, carry: Any, *args: Any) -> tuple[Any, Any]:
        """Run the next step as one node (keeping its state, if due)."""
        j = len(self.args)
        if j == 0:
            self.devices = sorted({x.device.index or 0 for x in _leaves(carry)
                                   if x.device.type == "cuda"})
        if j % self.stride == 0:
            self._keep(j, carry)
        self.args.append(args)
        if self.outside is None:
            self.outside = self._find_outside(carry, args)
        inputs = [x for x in _leaves(carry) if x.requires_grad]
        box: dict[str, Any] = {}
        outs = _Step.apply(self, j, carry, box, *inputs, *self.outside)
        carry = _replace_differentiable(box["carry"], outs)
        self.final = _decisions(carry)
        return carry, box["info"]

    def _keep(self, j: int, carry: Any) -> None:
        """Keep the state before step j; when C are held, keep every other one first."""
        if len(self.kept) >= self.capacity:
            self.stride *= 2
            self.kept = {p: s for p, s in self.kept.items() if p % self.stride == 0}
            if j % self.stride:
                return
        self.kept[j] = _State(_detached(carry), self._rng())

    def _rng(self) -> tuple[torch.Tensor, ...]:
        """Torch's random state now; the one kept last where it is the same (f draws no
        random numbers, the usual case: the states then share one copy, not 5 kB each)."""
        rng = (torch.get_rng_state(), *(torch.cuda.get_rng_state(d) for d in self.devices))
        if len(rng) == len(self._rng_kept) and all(map(torch.equal, rng, self._rng_kept)):
            return self._rng_kept
        self._rng_kept = rng
        return rng

    def _find_outside(self, carry: Any, args: tuple) -> list[torch.Tensor]:
        """The tensors outside the step that its graph reaches (parameters of f, tensors
        f closes over), from one extra run of the first step."""
        mark = _sequence_mark()
        start = _detached(carry)
        seen = _Outside(mark)
        with torch.random.fork_rng(devices=self.devices), torch.enable_grad(), \
                torch.autograd.graph.saved_tensors_hooks(_drop, _gone), seen:
            out, _ = (self.step if self.replica is None else self.replica())(start, *args)
        self.reruns += 1
        inside = {id(x) for x in _leaves(start)}
        outside: dict[int, torch.Tensor] = {}
        for node in _boundary(out, mark):
            x = getattr(node, "variable", None)  # a leaf's AccumulateGrad
            if x is None:
                x = next((t for t in seen.tensors.values() if t.grad_fn is node), None)
            if x is None:
                raise RuntimeError(_HIDDEN.format(node=type(node).__name__))
            if id(x) not in inside:
                outside[id(x)] = x
        return list(outside.values())

    def backward(self, j: int, grads: tuple[torch.Tensor, ...]) -> tuple:
        """Node j's backward: the gradients of its inputs (the carry's differentiable
        tensors before step j, then `outside`) from those of its outputs."""
        if j >= self._last or self._rerun is None:  # a new backward pass
            self._rerun = self.step if self.replica is None else self.replica()
            self.extra = {}
        self._last = j
        with torch.random.fork_rng(devices=self.devices):
            carry = self._state_before(j)
            with torch.enable_grad():
                out, _ = self._rerun(carry, *self.args[j])
        self.reruns += 1
        self._check(j, out)
        outputs = [x for x in _leaves(out) if x.requires_grad]
        if len(outputs) != len(grads):
            raise RuntimeError(_NOT_DETERMINISTIC.format(
                step=j, what=f"{len(outputs)} differentiable outputs against {len(grads)}"))
        inputs = [x for x in _leaves(carry) if x.requires_grad]
        return torch.autograd.grad(outputs, [*inputs, *self.outside], grads, allow_unused=True)

    def _state_before(self, j: int) -> Any:
        """The carry before step j (detached), rerun from the nearest kept state, keeping
        states on the way (revolve's binomial rule) where room is left; torch's random
        state set to step j's. The backward pass has left the steps after j: the states
        kept for them can go."""
        self.extra = {p: s for p, s in self.extra.items() if p <= j}
        at = max(p for p in itertools.chain(self.kept, self.extra) if p <= j)
        start = self.extra.get(at) or self.kept[at]
        _set_rng(start.rng, self.devices)
        carry = start.carry
        with torch.enable_grad(), torch.autograd.graph.saved_tensors_hooks(_drop, _gone):
            while at < j:
                free = self.capacity - len(self.extra)
                n = j - at if free <= 0 else advance_length(j + 1 - at, free + 1)
                for i in range(at, at + n):
                    carry = _detached(self._rerun(carry, *self.args[i])[0])
                self.reruns += n
                at += n
                if at < j:
                    self.extra[at] = _State(carry, self._rng())
        return carry

    def _check(self, j: int, carry: Any) -> None:
        """Where the rerun of step j ends on a kept state (or the last), its decisions
        (counters, statuses, flags) must be the forward's."""
        end = j + 1
        if end == len(self.args):
            want = self.final
        elif end in self.kept:
            want = _decisions(self.kept[end].carry)
        else:
            return
        got = _decisions(carry)
        if len(got) != len(want) or not all(map(torch.equal, got, want)):
            raise RuntimeError(_NOT_DETERMINISTIC.format(
                step=j, what="another step size or accept/reject decision"))


class _Step(torch.autograd.Function):
    """One step of a `Checkpointed` loop as one node: from the carry's differentiable
    tensors and the tensors f uses from outside (`inputs`) to the next carry's. The
    forward runs the step with its graph dropped; the backward reruns it
    (`Checkpointed.backward`)."""

    @staticmethod
    def forward(ctx, owner: Checkpointed, j: int, carry: Any, box: dict, *inputs):
        ctx.owner, ctx.j = owner, j
        with torch.enable_grad(), torch.autograd.graph.saved_tensors_hooks(_drop, _gone):
            out, box["info"] = owner.step(_detached(carry), *owner.args[j])
        box["carry"] = out
        return tuple(x.detach() for x in _leaves(out) if x.requires_grad)

    @staticmethod
    def backward(ctx, *grads):
        if torch.is_grad_enabled():
            raise RuntimeError("a checkpointed solve has a first-order backward only; for "
                               "higher derivatives (create_graph=True) solve without "
                               "checkpoints, fused=False")
        return (None, None, None, None, *ctx.owner.backward(ctx.j, grads))


class _Outside(TorchFunctionMode):
    """Collects the tensors needing a gradient that torch functions are given and that
    were made before the step (`_sequence_mark`): leaves, or with an older grad_fn."""

    def __init__(self, mark: int):
        super().__init__()
        self.mark, self.tensors = mark, {}

    def __torch_function__(self, func, types, args=(), kwargs=None):
        for a in itertools.chain(args, (kwargs or {}).values()):
            for x in (a if isinstance(a, list | tuple) else (a,)):
                if (isinstance(x, torch.Tensor) and x.requires_grad
                        and (x.grad_fn is None or x.grad_fn._sequence_nr() < self.mark)):
                    self.tensors[id(x)] = x
        return func(*args, **(kwargs or {}))


def _sequence_mark() -> int:
    """A number below every autograd node made after this call, and above those made
    before, on this thread (autograd numbers its nodes in creation order)."""
    with torch.enable_grad():
        return torch.zeros((), requires_grad=True).mul(1).grad_fn._sequence_nr() + 1


def _boundary(out: Any, mark: int) -> list:
    """The nodes outside a step's graph that it reaches: the AccumulateGrad nodes of leaves
    and nodes made before `mark`, walked back from `out`'s differentiable tensors."""
    stack = [x.grad_fn for x in _leaves(out) if x.grad_fn is not None]
    seen, found = set(), []
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        if hasattr(node, "variable") or node._sequence_nr() < mark:
            found.append(node)
        else:
            stack.extend(n for n, _ in node.next_functions)
    return found


def advance_length(steps: int, snapshots: int) -> int:
    """Revolve's first move: how many steps to advance before keeping a state.

    To reverse `steps` steps from a kept state with `snapshots` states in all (that one
    included, ≥ 2), each step run at most r times besides its last, r the smallest with
    β(snapshots, r) = C(snapshots + r, r) ≥ steps: advance m steps and keep a state,
    with the first m reversed later with all the states and r − 1 runs (β(snapshots,
    r − 1) ≥ m) and the rest now with one state fewer (β(snapshots − 1, r) ≥ steps − m),
    as β(s, r) = β(s, r − 1) + β(s − 1, r) allows (Griewank & Walther, ACM TOMS 26(1),
    2000).

    Returns:
        m, 1 ≤ m ≤ steps − 1 (for steps ≥ 2).
    """
    r = 1
    while math.comb(snapshots + r, r) < steps:
        r += 1
    return min(max(1, steps - math.comb(snapshots - 1 + r, r)), steps - 1)


def _leaves(x: Any) -> list[torch.Tensor]:
    """The tensors of a carry (tensors in tuples and NamedTuples), in order."""
    if isinstance(x, torch.Tensor):
        return [x]
    if isinstance(x, tuple):
        return [t for v in x for t in _leaves(v)]
    return []


def _rebuild(x: Any, leaf: Callable[[torch.Tensor], torch.Tensor]) -> Any:
    """The carry with each tensor replaced by `leaf(tensor)`, in `_leaves`' order."""
    if isinstance(x, torch.Tensor):
        return leaf(x)
    if isinstance(x, tuple):
        items = [_rebuild(v, leaf) for v in x]
        return type(x)(*items) if hasattr(x, "_fields") else tuple(items)
    return x


def _detached(x: Any) -> Any:
    """The carry with each tensor detached, requiring grad where it did: a run from it
    records what the forward pass did, without the forward's graph."""
    return _rebuild(x, lambda t: t.detach().requires_grad_() if t.requires_grad
                    else t.detach())


def _replace_differentiable(x: Any, outs: tuple[torch.Tensor, ...]) -> Any:
    """The carry with its differentiable tensors replaced by `outs`, in order."""
    it = iter(outs)
    return _rebuild(x, lambda t: next(it) if t.requires_grad else t)


def _decisions(carry: Any) -> tuple[torch.Tensor, ...]:
    """The integer and boolean tensors of a carry: counters, statuses, flags, indices."""
    return tuple(x for x in _leaves(carry) if not x.is_floating_point())


def _set_rng(states: tuple[torch.Tensor, ...], devices: list[int]) -> None:
    torch.set_rng_state(states[0])
    for device, state in zip(devices, states[1:], strict=True):
        torch.cuda.set_rng_state(state, device)
