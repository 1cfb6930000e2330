"""The principal components of a trained model's messages over time (the paper's Fig. 12),
beside an untrained model's: what an experiment's evaluate step with `pca` reports.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from mpnode_cli.data.dataset import TrajectoryData
    from mpnode_cli.training.checkpoint import Checkpoint


def message_pca(ckpt: Checkpoint, data: TrajectoryData, *, split: str, components: int,
                trajectories: int, untrained: bool, path: Path | None = None,
                dpi: int = 80) -> dict[str, Any]:
    """PCA of all nodes' messages over time (the paper's Fig. 12), drawn at `path` (None:
    not drawn): each sample time of each trajectory is one point of N·M message values.

    Messages start at zero, so their spread from the start grows in any model whose
    messages move at all; with `untrained` the same statistic is taken of the same
    architecture with fresh weights (the training's seed) on the same trajectories, and
    `growth` (late spread ÷ early spread) of the trained model is judged against its.

    Args:
        ckpt: the trained model's checkpoint (one model: an ensemble's member alone).
        data: the dataset; `split` names its trajectories, of which the first
            `trajectories` are rolled out.
        components: how many principal components to draw and report.
        dpi: the figure's resolution.

    Returns:
        `trajectories`, `messages` (N·M), `explained` (each component's share of the
        variance), `spread_first`, `spread_last`, `growth`, and with `untrained` the same
        spread statistics of the fresh model under `untrained`.

    Raises:
        ValueError: a model without message states.
    """
    import torch

    from mpnode_cli.models.registry import build_model
    from mpnode_cli.report.plots import plot_components

    subset = data.subset(split)
    n = min(trajectories, len(subset))
    trained = ckpt.build_model()
    time, messages = _messages(ckpt, trained, subset, n)
    b, _, nodes, m = messages.shape
    scores, explained = _components(messages, components)
    if path is not None:
        plot_components(time, scores, path, dpi=dpi,
                        title=f"PCA of {nodes}×{m} messages, {b} trajectories")
    result = {"trajectories": b, "messages": nodes * m, "explained": explained,
              **_spread(scores)}
    if untrained:
        # The weights the training started from (it seeds, then builds), with the data
        # statistics it fitted (buffers such as PNA's degree scale), which are not weights.
        with torch.random.fork_rng():
            torch.manual_seed(int((ckpt.train_config or {}).get("seed", 0)))
            fresh = build_model(ckpt.model_kind, ckpt.model_config)
        fresh.to(dtype=next(trained.parameters()).dtype)  # a float64 training's, too
        state = fresh.state_dict()
        state.update({k: v for k, v in trained.named_buffers() if k in state})
        fresh.load_state_dict(state)
        _, fresh_messages = _messages(ckpt, fresh, subset, n)
        result["untrained"] = _spread(_components(fresh_messages, components)[0])
    return result


def _messages(ckpt, model, subset, n: int):
    """The sample times `[T]` and messages `[B, T, N, M]` of `model` on the first `n`
    trajectories of `subset`, with the checkpoint's normalization and training solver."""
    import torch

    from mpnode_cli.config.fields import train_solver
    from mpnode_cli.config.upgrade import stored_solver
    from mpnode_cli.training.evaluate import predict

    pred = predict(model, subset, ckpt.build_normalizer(), torch.arange(n),
                   solver=stored_solver(ckpt.train_config, train_solver))
    if pred.messages is None or pred.messages.shape[-1] == 0:
        raise ValueError(f"model '{ckpt.model_kind}' has no message states")
    return pred.time, pred.messages


def _components(messages, k: int):
    """The first `k` principal components' scores `[B, T, k]` of messages `[B, T, N, M]`
    (each sample time of each trajectory one point of N·M values), and the share of the
    variance each component explains."""
    import torch

    b, t, nodes, m = messages.shape
    flat = messages.double().reshape(b * t, nodes * m)  # (B·T, N·M)
    centred = flat - flat.mean(dim=0)
    _, s, v = torch.linalg.svd(centred, full_matrices=False)
    k = min(k, v.shape[0])
    scores = (centred @ v[:k].T).reshape(b, t, k)  # (B, T, k)
    total = float((s**2).sum())
    return scores, [float(x) / total if total > 0 else 0.0 for x in (s**2)[:k]]


def _spread(scores) -> dict[str, float | None]:
    """How far the components have moved from where each trajectory started, early and
    late in the horizon (the first and last quarter of the samples), and late over early:
    the paper reads growth as the messages countering drift."""
    t = scores.shape[1]
    moved = (scores - scores[:, :1]).abs().mean(dim=(0, 2))  # (T,)
    quarter = max(1, t // 4)
    first, last = float(moved[:quarter].mean()), float(moved[-quarter:].mean())
    return {"spread_first": first, "spread_last": last,
            "growth": last / first if first > 0 else None}
