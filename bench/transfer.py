"""Transfer benchmark: a node model trained on small graphs, run zero-shot on larger ones.

For each system, one model is trained on small graphs with `mpnode train` (the defaults, or
the options a variant is about) and run with `mpnode zeroshot` on graphs about 2× and 4×
larger, with higher in-degrees, and on another topology. Every MSE (normalized, t₀
excluded) stands beside the two naive predictors on the same trajectories (hold x(0), the
train split's time mean) and the ratio to the model's own test error; each row is the mean
± std over `--seeds` training seeds (the data are fixed).

Systems:
- kuramoto: BA 10 → BA 20, BA 40, ER 20. Every dataset uses graph seed 0, so its natural
  frequencies ω (drawn per graph seed, docs/systems.md) are the same: ω is not part of a
  node's state, and a model can only carry it over if it is shared.
- gene: BA 9 → BA 18, BA 36, WS 18 (mean degree about N/2, so the in-degrees grow with N).
- pendulum: a chain of 3 → chains of 6 and 12. (From a chain of 2, where every node has one
  neighbour, no model can learn how the springs' pull grows with a second one.)
- lorenz: complete graphs of 3 → 6 and 12 nodes.
- fhn: FitzHugh–Nagumo as a plug-in (`examples/fitzhugh_nagumo.py`), BA 10 → 20, 40.
- grid: swing-equation power grids through `mpnode import` (`bench/power_grid.py`),
  BA 10 → 20, 40, with each node's constant power as a control.
(docs/own-systems.md describes the last two.)

Variants: `default` (no options: what a user gets); on the pendulum `mlp-sum` (the paper's
MLP update over the sum, its previous default); and on kuramoto and gene the choices the
default was picked against: `pna` (PNA with the paper's MLP update, the previous default), `mean`
(the paper's), and `l2s` (Learning to Simulate, CI-sized as in `bench/quality.py`, trained
for the wall time of the `default` run of the same seed).

Usage:
    .venv/bin/python bench/transfer.py --plan              # the time estimate only
    .venv/bin/python bench/transfer.py --only kuramoto,gene --variants default,pna
    .venv/bin/python bench/transfer.py --table-only        # rebuild the table from results
Cached results live in `--runs` (bench/.runs/transfer/<system>-<variant>-s<seed>/); the
table is rebuilt from every cached result and written to `bench/results/transfer.md`.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from quality import L2S_CI, ROOT, epochs_to_budget, git_commit, mpnode, schedule  # noqa: E402

RESULTS = HERE / "results" / "transfer.md"
FHN = ("--system-file", str(ROOT / "examples" / "fitzhugh_nagumo.py"), "--topology", "ba")
EVAL_SECONDS = 25.0  # a job's zero-shot runs and process starts, for the plan


@dataclass(frozen=True)
class Bench:
    """One system's datasets and budget.

    Attributes:
        datasets: name → `mpnode generate` arguments (or `("grid", N, K, seed,
            graph_seed, graphs)` for `bench/power_grid.py`), the training set first.
        targets: label ("x2", "x4", "other") → dataset name.
        epochs: the training budget. s_per_epoch: planning estimate (one core).
        variants: the variants run on this system.
    """

    name: str
    datasets: dict[str, tuple[Any, ...]]
    targets: dict[str, str]
    epochs: int
    s_per_epoch: float
    variants: tuple[str, ...] = ("default",)


def _gen(system: str, nodes: int, topology: str, k: int, graphs: int = 1,
         graph_seed: int = 0, seed: int = 0) -> tuple[str, ...]:
    return (system, "--nodes", str(nodes), "--topology", topology, "--trajectories", str(k),
            "--graphs", str(graphs), "--graph-seed", str(graph_seed), "--seed", str(seed))


COMPARED = ("default", "pna", "mean", "l2s")
ORDER = (*COMPARED, "mlp-sum")
BENCHES = {b.name: b for b in [
    Bench("kuramoto", {
        "kuramoto-ba10": _gen("kuramoto", 10, "ba", 500),
        "kuramoto-ba20": _gen("kuramoto", 20, "ba", 100, seed=1),
        "kuramoto-ba40": _gen("kuramoto", 40, "ba", 100, seed=2),
        "kuramoto-er20": _gen("kuramoto", 20, "er", 100, seed=3)},
        {"x2": "kuramoto-ba20", "x4": "kuramoto-ba40", "other": "kuramoto-er20"},
        150, 1.0, COMPARED),
    Bench("gene", {
        "gene-ba9": _gen("gene", 9, "ba", 300, graphs=10),
        "gene-ba18": _gen("gene", 18, "ba", 100, graphs=5, graph_seed=100, seed=1),
        "gene-ba36": _gen("gene", 36, "ba", 100, graphs=5, graph_seed=200, seed=2),
        "gene-ws18": _gen("gene", 18, "ws", 100, graphs=5, graph_seed=300, seed=3)},
        {"x2": "gene-ba18", "x4": "gene-ba36", "other": "gene-ws18"}, 100, 0.8, COMPARED),
    Bench("pendulum", {
        "pendulum-chain3": _gen("pendulum", 3, "chain", 500),
        "pendulum-chain6": _gen("pendulum", 6, "chain", 100, seed=1),
        "pendulum-chain12": _gen("pendulum", 12, "chain", 100, seed=2)},
        {"x2": "pendulum-chain6", "x4": "pendulum-chain12"}, 150, 4.0,
        ("default", "mlp-sum")),
    Bench("lorenz", {
        "lorenz-k3": _gen("lorenz", 3, "complete", 500),
        "lorenz-k6": _gen("lorenz", 6, "complete", 100, seed=1),
        "lorenz-k12": _gen("lorenz", 12, "complete", 100, seed=2)},
        {"x2": "lorenz-k6", "x4": "lorenz-k12"}, 100, 3.0),
    Bench("fhn", {
        "fhn-ba10": (*FHN, "--nodes", "10", "--graphs", "8", "--trajectories", "400"),
        "fhn-ba20": (*FHN, "--nodes", "20", "--graphs", "4", "--trajectories", "100",
                     "--seed", "1", "--graph-seed", "100"),
        "fhn-ba40": (*FHN, "--nodes", "40", "--graphs", "4", "--trajectories", "100",
                     "--seed", "2", "--graph-seed", "200")},
        {"x2": "fhn-ba20", "x4": "fhn-ba40"}, 100, 1.0),
    Bench("grid", {
        "grid-ba10": ("grid", 10, 400, 0, 0, 8),
        "grid-ba20": ("grid", 20, 100, 1, 100, 4),
        "grid-ba40": ("grid", 40, 100, 2, 200, 4)},
        {"x2": "grid-ba20", "x4": "grid-ba40"}, 100, 1.5),
]}
VARIANT_OPTIONS = {
    "default": (),
    "pna": ("--aggregate", "pna", "--update", "mlp", "--message-init", "zero"),
    "mean": ("--aggregate", "mean", "--update", "mlp", "--message-init", "zero"),
    "l2s": L2S_CI,
    "mlp-sum": ("--aggregate", "sum", "--update", "mlp", "--message-init", "zero"),
}


def data_path(args, name: str) -> Path:
    return args.data / f"{name}.h5"


def generate(args, bench: Bench) -> None:
    """Make the bench's datasets that are not there yet."""
    args.data.mkdir(parents=True, exist_ok=True)
    for name, spec in bench.datasets.items():
        path = data_path(args, name)
        if path.is_file():
            continue
        log = args.data / f"{name}.log"
        if spec[0] == "grid":
            from power_grid import make_dataset

            _, nodes, k, seed, graph_seed, graphs = spec
            make_dataset(path, nodes=nodes, trajectories=k, seed=seed, graph_seed=graph_seed,
                         graphs=graphs)
        else:
            mpnode("generate", *spec, "--out", path, "-y", log=log)


def in_degrees(path: Path) -> tuple[int, int]:
    """The smallest and largest in-degree over every node of every graph in a dataset."""
    import numpy as np

    from mpnode_cli.data.dataset import TrajectoryData

    degree = np.asarray(TrajectoryData.load(path).graphs.in_degree())  # (G, N)
    return int(degree.min()), int(degree.max())


def run_job(args, bench: Bench, variant: str, seed: int) -> dict[str, Any]:
    """Train one model and run it zero-shot on the bench's targets; write `result.json`."""
    folder = args.runs / f"{bench.name}-{variant}-s{seed}"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    log, run = folder / "log.txt", folder / "run"
    train = data_path(args, next(iter(bench.datasets)))
    common = (train, "--seed", seed, "--run-dir", run, "--no-plots", *VARIANT_OPTIONS[variant])
    clock: dict[str, float] = {}
    budget = None
    if variant == "l2s":  # the default run's wall time, in stages (bench/quality.py)
        ref = json.loads((args.runs / f"{bench.name}-default-s{seed}" / "result.json")
                         .read_text())
        budget = ref["train_seconds"]
        mpnode("train", *common, "--epochs", 2, log=log, clock=clock)
        for _ in range(16):
            more = epochs_to_budget(run, budget)
            if more < 1:
                break
            done = json.loads((run / "summary.json").read_text())["epochs"]
            mpnode("train", "--resume", run, "--epochs", done + more, log=log, clock=clock)
    else:
        mpnode("train", *common, "--epochs", bench.epochs * args.scale, log=log, clock=clock)
    summary = json.loads((run / "summary.json").read_text())
    targets = [data_path(args, name) for name in bench.targets.values()]
    report = json.loads(mpnode("zeroshot", run / "checkpoints" / "best.pt", *targets,
                               "--split", "all", "--json", log=log))
    rows = {"own": {"mse": summary["test"]["mse"], **(summary.get("baselines") or {}),
                    "degree": in_degrees(train)}}
    for label, name, row in zip(bench.targets, bench.targets.values(), report["datasets"],
                                strict=True):
        rows[label] = {"dataset": name, "mse": row["result"]["mse"],
                       "failed": row["result"]["failed"], **(row.get("baselines") or {}),
                       "degree": in_degrees(data_path(args, name)),
                       "states_outside": (row.get("extrapolation") or {}).get(
                           "states_outside_fraction")}
    metrics = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    result = {"system": bench.name, "variant": variant, "seed": seed,
              "epochs": summary["epochs"], "best_epoch": summary["best_epoch"],
              "train_seconds": sum(r["seconds"] for r in metrics),
              "budget_seconds": budget, "cpu_seconds": clock.get("cpu"),
              "process_seconds": clock.get("wall"), "model": summary["model"],
              "options": list(VARIANT_OPTIONS[variant]), "scale": args.scale,
              "date": datetime.now().isoformat(timespec="seconds"), "commit": git_commit(),
              "rows": rows}
    (folder / "result.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


# ------------------------------------------------------------------------------ the table


def _stat(values: list[float]) -> str:
    if not values:
        return "—"
    mean = statistics.fmean(values)
    std = statistics.stdev(values) if len(values) > 1 else 0.0
    return f"{mean:.3g} ± {std:.2g}"


def table(args) -> str:
    """The markdown table of every cached result, one row per system and variant."""
    results: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for path in sorted(args.runs.glob("*/result.json")):
        r = json.loads(path.read_text())
        results.setdefault((r["system"], r["variant"]), []).append(r)
    head = ("| system | variant | seeds | train in-degree | own test | ×2: MSE (÷ own) | "
            "×4: MSE (÷ own) | other: MSE (÷ own) | time mean own / ×2 / ×4 | "
            "hold x(0) own / ×2 / ×4 | ×4 states outside | train s |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for (system, variant), runs in sorted(results.items(), key=lambda kv: (
            list(BENCHES).index(kv[0][0]), ORDER.index(kv[0][1]))):
        own = [r["rows"]["own"]["mse"] for r in runs]
        cells = []
        for label in ("x2", "x4", "other"):
            present = [r for r in runs if label in r["rows"]]
            if not present:
                cells.append("—")
                continue
            row0 = present[0]["rows"][label]
            mses = [r["rows"][label]["mse"] for r in present]
            ratios = [r["rows"][label]["mse"] / r["rows"]["own"]["mse"] for r in present]
            lo, hi = row0["degree"]
            cells.append(f"{_stat(mses)} (×{statistics.fmean(ratios):.2f}); "
                         f"{row0['dataset']}, in-degree {lo}–{hi}")
        base = {key: " / ".join(f"{runs[0]['rows'][lab].get(key, float('nan')):.3g}"
                                for lab in ("own", "x2", "x4") if lab in runs[0]["rows"])
                for key in ("time_mean", "hold_x0")}
        outside = runs[0]["rows"].get("x4", {}).get("states_outside")
        lo, hi = runs[0]["rows"]["own"]["degree"]
        lines.append(
            f"| {system} | {variant} | {len(runs)} | {lo}–{hi} | {_stat(own)} | "
            + " | ".join(cells)
            + f" | {base['time_mean']} | {base['hold_x0']} | "
            + (f"{outside:.1%}" if outside is not None else "0%")
            + f" | {statistics.fmean(r['train_seconds'] for r in runs):.0f} |")
    return "\n".join(lines)


def write_table(args, quiet: bool = False) -> None:
    body = table(args)
    if not quiet:
        print(body)
    if args.out:
        text = (f"# Transfer: trained on small graphs, zero-shot on larger ones\n\n"
                f"Written by `bench/transfer.py` on {datetime.now():%Y-%m-%d}; each row is "
                f"mean ± std over its seeds (training seeds; the data are fixed). MSE in "
                f"normalized units, t₀ excluded; ÷ own is the mean over seeds of the "
                f"target's MSE over the model's own test MSE. Time mean and hold x(0) are "
                f"the naive predictors on the same trajectories (seed 0's run). "
                f"'×4 states outside' is the share of the ×4 target's state values outside "
                f"the training states' range. 'train s' is the seconds of training (the "
                f"sum of its epochs), which is also the budget each `l2s` row trains for "
                f"(the `default` run of the same seed). {args.note}\n\n{body}\n")
        args.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.out.with_suffix(".tmp")
        tmp.write_text(text)
        tmp.replace(args.out)


# ------------------------------------------------------------------------ out of range


def in_range_report(checkpoint: Path, dataset: Path) -> dict[str, Any]:
    """Split a zero-shot error by whether a node's true states stay in the training range.

    A node whose states leave the range its model was trained on asks the model for its
    own dynamics where it has none; its error says nothing about the coupling's transfer.
    Returns the share of state values outside, and the MSE (normalized, t₀ excluded) over
    the nodes that stay inside and over those that leave, with their counts.
    """
    import numpy as np

    from mpnode_cli.data.dataset import TrajectoryData
    from mpnode_cli.training.checkpoint import load_checkpoint
    from mpnode_cli.training.predict import roll_out

    ckpt, data = load_checkpoint(checkpoint), TrajectoryData.load(dataset)
    x = data.states.double().numpy()  # (K, T, N, D)
    pred = roll_out(ckpt, x[:, 0], data.time.numpy(), data.graphs, data.graph_index.numpy())
    std = ckpt.build_normalizer().x_std.double().numpy()  # (D,)
    err = ((pred.states[:, 1:] - x[:, 1:]) / std) ** 2  # (K, T-1, N, D)
    lo, hi = np.asarray(ckpt.dataset["train_range"]["states"]).T  # (D,), (D,)
    outside = (x < lo) | (x > hi)  # (K, T, N, D)
    node_out = outside.any(axis=(1, 3))  # (K, N): leaves the range at some time
    per_node = err.mean(axis=(1, 3))  # (K, N)
    degree = np.asarray(data.graphs.in_degree())[data.graph_index.numpy()]  # (K, N)
    return {"dataset": dataset.name, "states_outside": float(outside.mean()),
            "mse": float(per_node.mean()),
            "in_range_mse": float(per_node[~node_out].mean()) if (~node_out).any() else None,
            "in_range_nodes": int((~node_out).sum()),
            "out_of_range_mse": float(per_node[node_out].mean()) if node_out.any() else None,
            "out_of_range_nodes": int(node_out.sum()),
            "in_degree": [int(degree.min()), int(degree.max())],
            "train_in_degree": ckpt.dataset["train_range"]["in_degree"]}


# ------------------------------------------------------------------------------ main


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--only", help="systems, comma-separated (default: all)")
    p.add_argument("--variants", help="variants, comma-separated (default: each system's)")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--scale", type=int, default=1, help="multiply every epoch budget")
    p.add_argument("--data", type=Path, default=HERE / ".data" / "transfer")
    p.add_argument("--runs", type=Path, default=HERE / ".runs" / "transfer")
    p.add_argument("--out", type=Path, default=RESULTS)
    p.add_argument("--plan", action="store_true", help="print the estimate and stop")
    p.add_argument("--table-only", action="store_true", help="rebuild the table and stop")
    p.add_argument("--note", default="", help="a sentence for the table's header "
                   "(say how busy the machine was)")
    p.add_argument("--again", action="store_true",
                   help="rerun jobs that have a result already (default: keep them)")
    p.add_argument("--in-range", nargs=2, type=Path, metavar=("CHECKPOINT", "DATASET"),
                   help="print the zero-shot error split by nodes in and out of the "
                   "training states' range (JSON), and stop")
    args = p.parse_args(argv)
    if args.in_range:
        print(json.dumps(in_range_report(*args.in_range)))
        return 0
    benches = [BENCHES[n] for n in (args.only.split(",") if args.only else BENCHES)]
    wanted = set(args.variants.split(",")) if args.variants else None
    jobs = [(b, v, s) for b in benches for v in b.variants if wanted is None or v in wanted
            for s in range(args.seeds)
            if args.again or not (args.runs / f"{b.name}-{v}-s{s}" / "result.json").is_file()]
    estimate = {f"{b.name}-{v}-s{s}": (b.epochs * args.scale * b.s_per_epoch + EVAL_SECONDS,
                                       (f"{b.name}-default-s{s}",) if v == "l2s" else ())
                for b, v, s in jobs}
    print(f"{len(jobs)} trainings, about {schedule(estimate, args.workers) / 60:.0f} min on "
          f"{args.workers} cores (one thread each)")
    if args.plan:
        return 0
    if not args.table_only:
        for bench in benches:
            generate(args, bench)
        first = [j for j in jobs if j[1] != "l2s"]
        then = [j for j in jobs if j[1] == "l2s"]
        started = time.perf_counter()
        for batch in (first, then):
            with ThreadPoolExecutor(args.workers) as pool:
                for done in pool.map(lambda j: run_job(args, *j), batch):
                    print(f"{done['system']}-{done['variant']}-s{done['seed']}: own "
                          f"{done['rows']['own']['mse']:.4g} after "
                          f"{time.perf_counter() - started:.0f} s", flush=True)
                    write_table(args, quiet=True)  # what is done so far, as it lands
    write_table(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
