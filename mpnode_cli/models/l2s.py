"""L2S: Learning to Simulate (Sanchez-Gonzalez et al. 2020) without edge features.

The paper's Fig. 1 (right): encode → process → decode, one step ahead.
- Encoder: MLP on a node's input — its current normalized state, the last C − 1 state
  differences (`history` C, default 1 so that every model starts from x(t₀) alone) and its
  control — to a latent of size 128, then LayerNorm.
- Processor: `steps` (10) message-passing steps with **unshared** weights: edge MLP on
  [h_receiver, h_sender], sum over incoming edges, node MLP on [h_i, Σ_j e_ij], residual
  h_i ← h_i + node(...); MLPs are 2×128 ReLU followed by LayerNorm.
- Decoder: MLP (no LayerNorm) → the normalized next-step state difference Δ.
Trained one step ahead with random-walk input noise (`one_step_loss`), or, with `unroll` > 1,
on short rollouts of its own predictions from noisy data states (`unrolled_loss`, a mpnode
option, not in the paper), from every step of each trajectory in a batch or, with `windows`
k > 0, from k of them drawn at random (DeepMind's simulator draws its training windows at
random; an epoch's training then costs about k / T of a full one); evaluated by
autoregressive rollout over the whole horizon, x_{t+1} = x_t + Δ̂. Departures from
DeepMind's simulator (deepmind-research `learning_to_simulate/`; docs/authors-code.md): no
positions, so no edge features and no connectivity radius; a first-order Δ instead of an
acceleration with semi-implicit Euler.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import torch
from torch import nn

from mpnode_cli.graphs.matrices import EdgeBatch
from mpnode_cli.models.aggregate import full_graph
from mpnode_cli.models.backend import EdgeIndex, Graph, as_graph
from mpnode_cli.models.base import BatchLoss, NeuralModel, Rollout, mlp
from mpnode_cli.models.options import L2SOptions
from mpnode_cli.models.stacked import LayerNorm


def _mlp_ln(in_dim: int, hidden: int, layers: int, out_dim: int) -> nn.Sequential:
    return nn.Sequential(*mlp(in_dim, hidden, layers, out_dim, "relu"), LayerNorm(out_dim))


def _windows(x: torch.Tensor, span: int, starts: int) -> torch.Tensor:
    """The `starts` windows of `span` samples of `x` `[B, T, ...]`, each trajectory's from
    sample 0 on, all at once: `[B·starts, span, ...]` (trajectory-major)."""
    out = x.unfold(1, span, 1)[:, :starts].movedim(-1, 2)
    return out.reshape(x.shape[0] * starts, span, *x.shape[2:])


def _draw(starts: int, batch: int, k: int, generator: torch.Generator | None,
          device: torch.device) -> torch.Tensor | None:
    """`k` of each trajectory's `starts` windows at random, without repeats, as rows of
    `_windows`' output (trajectory-major, in the order drawn); None: all of them (`k` 0 or
    at least `starts`)."""
    if k <= 0 or k >= starts:
        return None
    pick = torch.rand(batch, starts, generator=generator, device=device).argsort(dim=1)
    first = torch.arange(batch, device=device).unsqueeze(1) * starts
    return (pick[:, :k] + first).reshape(-1)


def _take(rows: torch.Tensor | None, *tensors: torch.Tensor | None) -> tuple:
    """Each of `tensors` (None stays None) at `rows` of its leading axis; all of it when
    `rows` is None (`_draw`'s "every window")."""
    if rows is None:
        return tensors
    return tuple(None if t is None else t[rows] for t in tensors)


def _per_window(adjacency: Graph, batch: int, starts: int) -> Graph:
    """Each trajectory's graph repeated for its `starts` windows (as `_windows` orders them)."""
    repeat = torch.arange(batch, device=adjacency.device).repeat_interleave(starts)
    return adjacency.take(repeat) if isinstance(adjacency, EdgeBatch) else adjacency[repeat]


def _edge_messages(edge_fn: nn.Sequential, h: torch.Tensor, edges: EdgeIndex) -> torch.Tensor:
    """`edge_fn([h_receiver, h_sender])` on every edge `[E, L]`, from node latents `h` `[M, L]`.

    The MLP's first layer is linear: W·[h_r, h_s] + b = W_r·h_r + W_s·h_s + b. So each half
    is applied to every node once and gathered per edge, rather than the whole layer to
    every edge's concatenation: M rows instead of E (E / M is the mean in-degree, 32 on the
    paper's 8×8 gene graphs). The same function, up to round-off.
    """
    first, latent = edge_fn[0], h.shape[-1]
    to_receiver = nn.functional.linear(h, first.weight[:, :latent])
    to_sender = nn.functional.linear(h, first.weight[:, latent:], first.bias)
    return edge_fn[1:](to_receiver[edges.receivers] + to_sender[edges.senders])


class L2S(NeuralModel):
    """Encode–process–decode GNN simulator, one step of the dataset's dt at a time.

    Args:
        node_dim: D. control_dim: U. num_nodes: unused (the model runs on any graph).
        options: `L2SOptions` — latent, the node/edge latent size; hidden, layers of the
            MLPs (128, 2); steps, message-passing steps (unshared weights); history, C
            states in the input window (C − 1 differences are fed); graph ("sys" or
            "full", complete with self-loops); step_noise, the training input noise;
            unroll, the steps of each training rollout (1: one step ahead); windows,
            the training windows drawn from each trajectory per batch (0: all).
    """

    kind: ClassVar[str] = "l2s"
    transferable: ClassVar[bool] = True
    statistics_need_states: ClassVar[bool] = True  # the one-step differences' moments
    Options: ClassVar[type[L2SOptions]] = L2SOptions

    def __init__(self, node_dim: int, control_dim: int = 0, num_nodes: int | None = None,
                 options: L2SOptions | None = None):
        super().__init__(node_dim, control_dim, num_nodes, options)
        o = self.options
        self.history, self.graph = o.history, o.graph
        latent, hidden, layers = o.latent, o.hidden, o.layers
        in_dim = node_dim * o.history + control_dim
        self.encoder = _mlp_ln(in_dim, hidden, layers, latent)
        self.edge_fns = nn.ModuleList(
            _mlp_ln(2 * latent, hidden, layers, latent) for _ in range(o.steps))
        self.node_fns = nn.ModuleList(
            _mlp_ln(2 * latent, hidden, layers, latent) for _ in range(o.steps))
        self.decoder = mlp(latent, hidden, layers, node_dim, "relu")
        # Statistics of the normalized one-step differences, set by `fit_statistics`.
        self.register_buffer("delta_mean", torch.zeros(node_dim))
        self.register_buffer("delta_std", torch.ones(node_dim))
        self.register_buffer("step_dt", torch.zeros((), dtype=torch.float64))

    @property
    def initial_states(self) -> int:
        """C = `history`: a rollout starts from the data's first C states."""
        return self.history

    # -------------------------------------------------------------- one step
    def edge_index(self, adjacency: Graph) -> EdgeIndex:
        """`[B, N, N]` or an `EdgeBatch` → the edges messages pass over."""
        if self.graph == "full":
            adjacency = full_graph(adjacency)
        return EdgeIndex.from_adjacency(adjacency)

    def delta(self, window: torch.Tensor, edges: EdgeIndex, u: torch.Tensor | None):
        """Normalized Δ̂ for one step.

        Args:
            window: `[B, C, N, D]` the last C normalized states (oldest first).
            edges: the batch's graph. u: `[B, N, U]` or None.

        Returns:
            `[B, N, D]` in the units of the fitted Δ statistics (zero mean, unit std).
        """
        current = window[:, -1]  # (B, N, D)
        feats = [current, *(window[:, k + 1] - window[:, k]
                             for k in range(window.shape[1] - 1))]
        if u is not None:
            feats.append(u.to(current.dtype))
        h = self.encoder(torch.cat(feats, dim=-1))  # (B, N, L)
        flat_size = h.shape[0] * h.shape[1]
        for edge_fn, node_fn in zip(self.edge_fns, self.node_fns, strict=True):
            hf = h.reshape(flat_size, -1)
            e = _edge_messages(edge_fn, hf, edges)  # (E, L)
            summed = torch.zeros_like(hf).index_add_(0, edges.receivers, e).view_as(h)
            h = h + node_fn(torch.cat([h, summed], dim=-1))
        return self.decoder(h)

    @torch.no_grad()
    def fit_statistics(self, states: torch.Tensor | Sequence[torch.Tensor], dt: float,
                       adjacency: torch.Tensor | None = None) -> None:
        """Fit the Δ normalization on normalized training states `[K, T, N, D]`, or on a
        list of them (several datasets of one dt: pooled over their steps)."""
        if isinstance(states, torch.Tensor):
            diff = (states[:, 1:] - states[:, :-1]).reshape(-1, self.node_dim).double()
        else:  # (Σ K·(T−1)·N, D)
            diff = torch.cat([(s[:, 1:] - s[:, :-1]).reshape(-1, self.node_dim).double()
                              for s in states])
        std = diff.std(dim=0, correction=0)
        self.delta_mean.copy_(diff.mean(dim=0).float())
        self.delta_std.copy_(torch.where(std > 1e-8, std, torch.ones_like(std)).float())
        self.step_dt.fill_(dt)

    def one_step_loss(self, states: torch.Tensor, adjacency: torch.Tensor,
                      controls: torch.Tensor | None = None, *, noise_std: float = 3e-3,
                      generator: torch.Generator | None = None, windows: int = 0
                      ) -> torch.Tensor:
        """MSE of the normalized Δ over every step of every trajectory, with input noise.

        A random walk of total std `noise_std` (in normalized state units) is added along
        each input window, as L2S does; the target Δ leads from the *noisy* current state to
        the true next one, so the model learns to correct its own drift.

        Args:
            states: `[B, T, N, D]` normalized; adjacency: `[B, N, N]`; controls `[B, T, N, U]`.
            windows: > 0, only that many of each trajectory's steps, drawn at random
                (`generator`), as L2S samples its training windows; 0 every step.
        """
        c = self.history
        batch, steps = states.shape[0], states.shape[1] - c
        inputs = _windows(states, c, steps)
        nexts = states[:, c:].reshape(batch * steps, *states.shape[2:])
        u = None
        if self.control_dim:
            u = controls[:, c - 1 : c - 1 + steps].reshape(batch * steps, *controls.shape[2:])
        rows = _draw(steps, batch, windows, generator, states.device)
        inputs, nexts, u = _take(rows, inputs, nexts, u)
        inputs = self._noisy(inputs, noise_std, generator)
        target = nexts - inputs[:, -1]
        graph = _per_window(adjacency, batch, inputs.shape[0] // batch)
        pred = self.delta(inputs, self.edge_index(graph), u)
        return ((pred - (target - self.delta_mean) / self.delta_std) ** 2).mean()

    def _noisy(self, windows: torch.Tensor, noise_std: float,
               generator: torch.Generator | None = None) -> torch.Tensor:
        """`windows` `[W, C, N, D]` with a random walk of total std `noise_std` along C."""
        if noise_std <= 0:
            return windows
        c = windows.shape[1]
        eps = torch.randn(windows.shape, generator=generator, dtype=windows.dtype,
                          device=windows.device) * (noise_std / c**0.5)
        return windows + eps.cumsum(dim=1)

    def _advance(self, window: torch.Tensor, edges: EdgeIndex,
                 u: torch.Tensor | None) -> torch.Tensor:
        """The state after `window`'s last: x + Δ̂ in the units of the states."""
        d = self.delta(window, edges, u) * self.delta_std + self.delta_mean
        return window[:, -1] + d

    def unrolled_loss(self, states: torch.Tensor, adjacency: torch.Tensor,
                      controls: torch.Tensor | None = None, *, steps: int,
                      noise_std: float = 3e-3, windows: int = 0) -> torch.Tensor:
        """MSE of `steps`-step rollouts from every start of every trajectory, in the units
        of the fitted Δ statistics (so that `steps` = 1 is `one_step_loss` with its
        target and units).

        Each rollout starts from a data window with the random walk of `one_step_loss` on
        it and feeds the model its own predictions; the error of the state reached after
        each step, over Δ's std, is averaged over the steps. Backpropagating through the
        steps (unrolled, or multi-step, training) trains the model against the drift its
        own errors cause, which one step ahead sees only through the input noise.

        Args:
            states: `[B, T, N, D]` normalized, T > C + `steps` − 1; adjacency: `[B, N, N]`;
                controls `[B, T, N, U]`. windows: as `one_step_loss`'s, of the starts.
        """
        c = self.history
        batch, starts = states.shape[0], states.shape[1] - c - steps + 1
        if starts < 1:
            raise ValueError(f"an unrolled L2S loss of {steps} steps needs more than "
                             f"{c + steps - 1} samples per trajectory, not {states.shape[1]}")
        runs = _windows(states, c + steps, starts)  # (B·starts, C + steps, N, D)
        u_all = _windows(controls, c + steps, starts) if self.control_dim else None
        runs, u_all = _take(_draw(starts, batch, windows, None, states.device), runs, u_all)
        window = self._noisy(runs[:, :c], noise_std)
        edges = self.edge_index(_per_window(adjacency, batch, runs.shape[0] // batch))
        loss = states.new_zeros(())
        for k in range(steps):
            nxt = self._advance(window, edges, u_all[:, c - 1 + k] if self.control_dim else None)
            loss = loss + (((nxt - runs[:, c + k]) / self.delta_std) ** 2).mean()
            window = torch.cat([window[:, 1:], nxt.unsqueeze(1)], dim=1)
        return loss / steps

    def training_loss(self, x: torch.Tensor, ts: torch.Tensor, adjacency: torch.Tensor,
                      controls: torch.Tensor | None,
                      loss_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                      **solver: Any) -> BatchLoss:
        """One step ahead: `one_step_loss` with `step_noise`, or with `unroll` > 1 the
        rollouts of `unrolled_loss` (at most the batch's samples allow, so a horizon
        curriculum's first short prefixes train fewer steps), on `windows` random windows
        of each trajectory (0: all); `loss_fn` and the solver options are unused."""
        o = self.options
        steps = min(o.unroll, x.shape[1] - self.history)
        if steps > 1:
            loss = self.unrolled_loss(x, adjacency, controls, steps=steps,
                                      noise_std=o.step_noise, windows=o.windows)
        else:
            loss = self.one_step_loss(x, adjacency, controls, noise_std=o.step_noise,
                                      windows=o.windows)
        return BatchLoss(loss, torch.zeros(x.shape[0], dtype=torch.long, device=x.device), 0)

    # -------------------------------------------------------------- rollout
    def rollout(self, x0: torch.Tensor, ts: torch.Tensor, adjacency: torch.Tensor,
                controls: torch.Tensor | None = None, *, history: torch.Tensor | None = None,
                **_solver_options) -> Rollout:
        """Autoregressive rollout, one dataset step at a time.

        Args:
            x0: `[B, N, D]` normalized start; ts: `[T]` sample times (spacing must be the
                training dt); adjacency: `[B, N, N]`; controls: `[B, T, N, U]` or None.
            history: `[B, C, N, D]` the first C states (needed when C > 1; then the rollout
                starts from the data's first C states).
            Solver options are accepted and ignored: this model takes discrete steps.
        """
        self.check_states(x0)
        ts = ts.to(torch.float64)
        spacing = ts[1:] - ts[:-1]
        if float(self.step_dt) > 0 and spacing.numel() and not torch.allclose(
                spacing, torch.full_like(spacing, float(self.step_dt)), rtol=1e-6):
            raise ValueError(f"L2S steps by the training dt {float(self.step_dt):g}; these "
                             "samples are spaced differently")
        c = self.history
        if c > 1 and history is None:
            raise ValueError(f"this L2S model needs the first {c} states (history={c})")
        window = history if c > 1 else x0.unsqueeze(1)
        edges = self.edge_index(as_graph(adjacency, x0))
        states = list(window.unbind(1))
        for k in range(c - 1, ts.numel() - 1):
            nxt = self._advance(window, edges, controls[:, k] if self.control_dim else None)
            states.append(nxt)
            window = torch.cat([window[:, 1:], nxt.unsqueeze(1)], dim=1)
        out = torch.stack(states, dim=1)  # (B, T, N, D)
        return Rollout(states=out, messages=None,
                       status=torch.zeros(x0.shape[0], dtype=torch.long, device=x0.device),
                       n_f_evals=0)
