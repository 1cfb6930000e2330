"""L2S training step: the edge MLP's first layer per node (ours) against per edge.

L2S's processor (`mpnode_cli.models.l2s`) computes a message f_e([h_i, h_j]) on every edge.
Its first layer is linear, W·[h_i, h_j] + b = W_r·h_i + W_s·h_j + b, so mpnode applies the
two halves to every node once and gathers them per edge (`_edge_messages`). The peer is
that layer applied to every edge's concatenation [h_i, h_j], as DeepMind's
`learning_to_simulate` does (deepmind-research `learning_to_simulate/graph_network.py`):
E rows instead of B·N, E / (B·N) being the mean in-degree.

Each case is one L2S training step (`one_step_loss` forward and backward, every window of
every trajectory) on random states of the case's sizes over one of its system's own graphs
(the step's cost does not depend on the values). Both variants run with the same weights,
in interleaved rounds; the reported time is the median over rounds, `× ours` the median of
the per-round ratios. `max rel. diff` compares the two variants' losses and gradients:
round-off only, since the function is the same.

Usage:
    .venv/bin/python bench/l2s_step.py                       # about 3 minutes, one thread
    .venv/bin/python bench/l2s_step.py --rounds 2 --out /tmp/l2s.md
Writes `bench/results/l2s-step.md`.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from datetime import datetime
from pathlib import Path

import torch

from mpnode_cli.data.atomic import atomic_text
from mpnode_cli.models import l2s
from mpnode_cli.models.registry import build_model
from mpnode_cli.systems.registry import get_system

# name, system, topology, nodes, D, trajectories, samples, L2S options
CASES = [
    ("gene 8×8, BA (m = 32), CI size", "gene", "ba", 64, 1, 8, 51,
     {"latent": 32, "hidden": 32, "steps": 5}),
    ("Kuramoto10, BA, paper size", "kuramoto", "ba", 10, 2, 32, 51, {}),
    ("quadrotor swarm of 6, complete, paper size", "quadrotor", "complete", 6, 12, 32, 51, {}),
]


def _per_edge(edge_fn, h, edges):
    """The peer: the first layer on every edge's concatenation [h_receiver, h_sender]."""
    return edge_fn(torch.cat([h[edges.receivers], h[edges.senders]], dim=-1))


def _step(net, x, adjacency, seed: int) -> tuple[float, torch.Tensor, float]:
    """One training step: seconds, the loss and the flattened gradient."""
    net.zero_grad(set_to_none=True)
    torch.manual_seed(seed)  # the same input noise for both variants
    start = time.perf_counter()
    loss = net.one_step_loss(x, adjacency)
    loss.backward()
    seconds = time.perf_counter() - start
    grad = torch.cat([p.grad.reshape(-1) for p in net.parameters()])
    return seconds, grad, loss.item()


def run_case(case, rounds: int) -> dict:
    name, system, topology, n, d, batch, samples, options = case
    graph = torch.as_tensor(get_system(system).graph(topology, n, 0), dtype=torch.float32)
    adjacency = graph.expand(batch, n, n)
    torch.manual_seed(0)
    net = build_model("l2s", {"node_dim": d} | options)
    x = torch.randn(batch, samples, n, d)
    own = l2s._edge_messages
    times: dict[str, list[float]] = {"ours": [], "per edge": []}
    results = {}
    for _ in range(rounds + 1):  # round 0 warms the allocator up and is not counted
        for variant, fn in (("ours", own), ("per edge", _per_edge)):
            l2s._edge_messages = fn
            try:
                seconds, grad, loss = _step(net, x, adjacency, seed=1)
            finally:
                l2s._edge_messages = own
            times[variant].append(seconds)
            results[variant] = (grad, loss)
    ratios = [b / a for a, b in zip(times["ours"][1:], times["per edge"][1:], strict=True)]
    (g0, l0), (g1, l1) = results["ours"], results["per edge"]
    diff = max(abs(l0 - l1) / abs(l1), float((g0 - g1).abs().max() / g1.abs().max()))
    edges = int(graph.count_nonzero())
    return {"case": name, "edges": edges, "degree": edges / n, "batch": batch,
            "windows": batch * (samples - 1),
            "ours": statistics.median(times["ours"][1:]),
            "per edge": statistics.median(times["per edge"][1:]),
            "ratio": statistics.median(ratios), "diff": diff}


def report(rows: list[dict], header: dict) -> str:
    lines = [
        "# L2S training step: the edge MLP's first layer per node (ours) against per edge",
        "",
        f"Command: `{header['command']}`. Machine: {header['machine']}, {header['cores']} "
        f"cores, {torch.get_num_threads()} torch thread(s), torch {torch.__version__}, "
        f"Python {platform.python_version()}, {header['date']}. Load average (1/5/15 min) "
        f"before {header['load_before']}, after {header['load_after']}.",
        "",
        "One step: `one_step_loss` forward and backward over every window of the batch's "
        "trajectories (51 samples, 50 windows each), random states, the system's own "
        "graph (seed 0) for every trajectory. Median of the rounds after a warm-up round; "
        "`× ours` = the peer's time / ours in the same round (median over rounds; higher: "
        "ours is faster). Paper size: latent and hidden 128, 10 message-passing steps; CI "
        "size: 32, 32, 5. max rel. diff: the largest difference of the two variants' loss "
        "or gradient, relative to the peer's largest.",
        "",
        "| case | directed edges | mean in-degree | trajectories | ours, s | per edge, s "
        "| × ours | max rel. diff |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(f"| {r['case']} | {r['edges']} | {r['degree']:.1f} | {r['batch']} | "
                     f"{r['ours']:.3f} | {r['per edge']:.3f} | {r['ratio']:.2f} | "
                     f"{r['diff']:.1e} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results"
                        / "l2s-step.md")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    load = "/".join(f"{v:.2f}" for v in os.getloadavg())
    rows = []
    for case in CASES:
        rows.append(run_case(case, args.rounds))
        r = rows[-1]
        print(f"{r['case']}: ours {r['ours']:.3f} s, per edge {r['per edge']:.3f} s, "
              f"× {r['ratio']:.2f}, max rel. diff {r['diff']:.1e}", flush=True)
    header = {"command": "bench/l2s_step.py " + " ".join(sys.argv[1:] if argv is None
                                                          else argv),
              "machine": platform.machine(), "cores": os.cpu_count(),
              "date": datetime.now().isoformat(timespec="minutes"), "load_before": load,
              "load_after": "/".join(f"{v:.2f}" for v in os.getloadavg())}
    text = report(rows, header)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_text(args.out, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
