"""`mpnode info FILE`: a dataset's summary, read from its header without loading states;
with `--plot`, one of its trajectories drawn (a prediction file's too: `mpnode simulate`'s
output has no ground truth to compare with, and is drawn as what it is)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from mpnode_cli.cli.common import FORCE, output_parser


def info_command(
    path: Path = typer.Argument(..., metavar="FILE", help="An mpnode dataset (.h5)."),
    json_out: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
    plot: bool = typer.Option(
        False, "--plot", help="Draw one trajectory's states per node (and its messages, "
        "for predictions that hold them)."),
    trajectory: int = typer.Option(0, help="The trajectory --plot draws."),
    plot_dir: Path | None = typer.Option(
        None, help="Where the plot goes (default plots/ beside FILE).",
        parser=output_parser("--plot-dir", folder=True)),
    force: bool = FORCE,
) -> None:
    """Print a dataset's summary (after checking the file, as `mpnode check` does).

    The in-degree range is over every node of every graph, not weighted by trajectories.
    """
    import json

    from mpnode_cli.cli.common import console, fail
    from mpnode_cli.data.hdf5 import DatasetFormatError, read_header
    from mpnode_cli.data.validate import require_valid
    from mpnode_cli.report.tables import titled

    try:
        require_valid(path)
        header = read_header(path)
    except (FileNotFoundError, DatasetFormatError) as exc:
        fail(str(exc))

    facts = _facts(header)
    plots = [str(_plot(path, header, trajectory, plot_dir, force))] if plot else []
    if json_out:
        typer.echo(json.dumps({"path": str(path), **facts, **({"plots": plots} if plot else {})}))
        return
    table = titled(str(path), show_header=False)
    table.add_column(style="bold")
    table.add_column()
    for name, value in _rows(facts):
        table.add_row(name, value)
    console().print(table)
    for written in plots:
        typer.echo(f"wrote {written}")


def _plot(path: Path, header: dict[str, Any], k: int, plot_dir: Path | None,
          force: bool) -> Path:
    """Draw trajectory `k` of the file as `<plot_dir>/<stem>-trajectory-<k>.png`."""
    from mpnode_cli.cli.common import fail
    from mpnode_cli.data.hdf5 import read_trajectory
    from mpnode_cli.paths import check_output_folder, reserve_output
    from mpnode_cli.report.plots import plot_rollout

    folder = plot_dir or path.parent / "plots"
    out = folder / f"{path.stem}-trajectory-{k}.png"
    try:
        check_output_folder(folder)
        with reserve_output(out, overwrite=force, inputs=(path,)):  # the plot replaces it
            one = read_trajectory(path, k)
            predicted = isinstance(header["attrs"].get("prediction"), str)
            what = "a model's predictions, not ground truth" if predicted else "data"
            return plot_rollout(one["time"], one["states"], None,
                                one["hidden"].get("messages"), header["attrs"]["state_names"],
                                out, title=f"{path.name}: trajectory {k} ({what})",
                                labels=("predicted" if predicted else "true", ""))
    except (FileExistsError, ValueError) as exc:  # FileExistsError is an OSError too
        fail(f"--plot: {exc}")
    except OSError as exc:
        fail(f"--plot: cannot write {exc.filename or 'the plot'}: {exc.strerror or exc}")


def _facts(header: dict[str, Any]) -> dict[str, Any]:
    """The summary as JSON-able facts (what `--json` prints and the table shows)."""
    import numpy as np

    from mpnode_cli.config.fields import generate_solver
    from mpnode_cli.config.upgrade import stored_solver
    from mpnode_cli.graphs.matrices import degree_range

    attrs, shapes, config = header["attrs"], header["shapes"], header["attrs"]["config"]
    (k, t, n, d), states_dtype = shapes["states"]
    graphs = header["graphs"]  # edge lists: no [N, N] matrix, whatever N
    train, val, test = (int(c) for c in np.bincount(header["split"], minlength=3)[:3])
    directed = not all(graphs.edges(g).symmetric() for g in range(len(graphs)))
    # An undirected edge is two messages (i → j and j → i); a directed one is one.
    edges = graphs.num_edges / (1 if directed else 2)
    facts = {
        "format": f"{attrs['format']} v{attrs['format_version']}",
        "system": attrs["system"], "num_nodes": n, "node_dim": d,
        "state_names": attrs["state_names"], "control_names": attrs["control_names"],
        "trajectories": k, "split": {"train": train, "validation": val, "test": test},
        "samples": t, "dt": attrs["dt"], "t_end": attrs["dt"] * (t - 1),
        "graphs": len(graphs), "topology": config.get("topology"),
        "hubs": config.get("hubs") or 0,
        "hub_multiplicity": config.get("hub_multiplicity") or 1,
        "directed": directed, "edges_mean": float(edges.mean()),
        # Over every node of every graph, not weighted by the trajectories on each graph.
        "in_degree": degree_range(graphs.in_degree()),
        "parameters": header["scalar_params"],
        "per_graph_parameters": {name.removeprefix("params/"): list(shape)
                                 for name, (shape, _) in shapes.items()
                                 if name.startswith("params/")},
        "states_dtype": states_dtype, "seed": attrs["seed"],
        "graph_seed": config.get("graph_seed"), "seeds": _seeds(config, attrs),
        # Imported and hand-written data were not solved by mpnode: no solver to show.
        "solver": (stored_solver(config, generate_solver).model_dump() if "solver" in config
                   else None),
        "origin": _origin(config, attrs),
        "unfinished": int(np.count_nonzero(header["solver_status"])),
        "hidden": [name.removeprefix("hidden/") for name in shapes
                   if name.startswith("hidden/")],
        "created_utc": attrs["created_utc"], "mpnode_version": attrs["mpnode_version"],
    }  # fmt: skip
    if "n_rejected" in attrs:
        facts["redrawn"] = {"failed": attrs.get("n_failed", 0), "rejected": attrs["n_rejected"]}
    return facts


def _rows(facts: dict[str, Any]) -> list[tuple[str, str]]:
    """(label, text) rows of the summary table."""
    solver = facts["solver"]
    if solver is None:
        solved = "none recorded (data mpnode did not solve)"
    else:
        steps = (f"fixed dt {solver['fixed_dt']:g}" if solver["fixed_dt"] is not None
                 else f"rtol {solver['rtol']:g}, atol {solver['atol']:g}")
        solved = f"{solver['method']}, {steps}, {facts['unfinished']} unfinished in the file"
    split = facts["split"]
    scalars = ", ".join(f"{key}={value:g}" for key, value in facts["parameters"].items())
    per_graph = ", ".join(f"{name} {shape}"
                          for name, shape in facts["per_graph_parameters"].items())
    kind = "directed" if facts["directed"] else "undirected"
    rows = [
        ("format", facts["format"]),
        ("system", facts["system"]),
        ("nodes × state", f"{facts['num_nodes']} × {facts['node_dim']} "
                          f"({', '.join(facts['state_names'])})"),
        ("controls", ", ".join(facts["control_names"]) or "none"),
        ("trajectories", f"{facts['trajectories']} ({split['train']} train / "
                         f"{split['validation']} val / {split['test']} test)"),
        ("samples", f"{facts['samples']} (dt {facts['dt']:g}, t_end {facts['t_end']:g})"),
        ("graphs", f"{facts['graphs']} × {facts['topology'] or '?'}"
                   + (f" + {facts['hubs']} hubs joined to all" if facts["hubs"] else "")
                   + (f" by up to {facts['hub_multiplicity']} parallel edges"
                      if facts["hub_multiplicity"] > 1 else "")
                   + f", {facts['edges_mean']:g} {kind} edges on average"),
        ("in-degree", "min {min}, median {median:g}, max {max}".format(**facts["in_degree"])
                      + (" (over every node of the graph)" if facts["graphs"] == 1 else
                         f" (over every node of the {facts['graphs']} graphs)")),
        ("parameters", scalars or "none"),
        ("per-graph parameters", per_graph or "none"),
        ("states dtype", facts["states_dtype"]),
        ("solver", solved),
    ]
    if facts["seeds"]:
        rows.insert(-1, ("seeds", ", ".join(f"{what} {seed}"
                                            for what, seed in facts["seeds"].items())))
    if facts["origin"]:
        rows.insert(2, ("origin", facts["origin"]))
    if "redrawn" in facts:
        rows.append(("redrawn", f"{facts['redrawn']['failed']} failed, "
                                f"{facts['redrawn']['rejected']} rejected"))
    if facts["hidden"]:
        rows.append(("hidden states", ", ".join(facts["hidden"])))
    version = facts["mpnode_version"]
    writer = f"mpnode {version}" if version else "?"
    rows.append(("written", f"{_known(facts['created_utc'])} by {writer}"))
    return rows


def _seeds(config: dict[str, Any], attrs: dict[str, Any]) -> dict[str, int]:
    """The seeds the file records, by what they drew: generated data's initial states and
    graphs; imported data's split alone (its trajectories and graph are the user's);
    none for a model's predictions."""
    if config.get("verb") == "import":
        return {"split": attrs["seed"]}
    seeds = {"trajectories": attrs["seed"], "graphs": config.get("graph_seed")}
    return {what: seed for what, seed in seeds.items() if seed is not None}


def _origin(config: dict[str, Any], attrs: dict[str, Any]) -> str | None:
    """Where the data came from, for files mpnode did not generate: imported arrays, or a
    model's predictions (`mpnode simulate`, `evaluate --save-predictions`)."""
    if config.get("verb") == "import":
        sources = config.get("sources") or {}
        files = ", ".join(f"{sources[name].get('path', '?')} ({name.replace('_', ' ')})"
                          for name in ("states", "adjacency", "edge_list", "controls")
                          if name in sources)
        return f"imported from {files or '?'}"
    prediction = attrs.get("prediction")
    if isinstance(prediction, str):
        import json

        try:
            facts = json.loads(prediction)
        except ValueError:
            facts = {}
        sha = str(facts.get("checkpoint_sha256"))[:12]
        member = f", member {facts['member']}" if "member" in facts else ""
        return (f"predictions of {facts.get('model_kind', '?')} checkpoint "
                f"{facts.get('checkpoint', '?')} (sha256 {sha}...{member}), not ground truth")
    return None


def _known(value: Any) -> str:
    return "?" if value is None else str(value)
