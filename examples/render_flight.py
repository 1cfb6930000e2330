"""Render one quadrotor-swarm flight of a dataset in 3-D (quads, cables, load, doorway).

Usage:
    .venv/bin/python examples/render_flight.py datasets/quadrotor-n3-complete-s0.h5 \
        --trajectory 0 --out docs/quad3-flight.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

from mpnode_cli.data.hdf5 import read_dataset
from mpnode_cli.report.flight import plot_flight


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path, help="an mpnode quadrotor dataset (.h5)")
    parser.add_argument("--trajectory", type=int, default=0, help="which flight (default 0)")
    parser.add_argument("--out", type=Path, default=Path("flight.png"), help="PNG to write")
    args = parser.parse_args()

    ds = read_dataset(args.dataset)
    if "load" not in ds.hidden:
        parser.error(f"{args.dataset} has no hidden/load: not a quadrotor dataset")
    if not 0 <= args.trajectory < ds.num_trajectories:
        parser.error(f"--trajectory must be in [0, {ds.num_trajectories}), got {args.trajectory}")
    k = args.trajectory
    reference = ds.hidden.get("load_reference")
    path = plot_flight(
        ds.states[k], ds.hidden["load"][k], args.out,
        reference=None if reference is None else reference[k], time=ds.time,
        title=f"{args.dataset.name}: flight {k} of {ds.num_trajectories} ({ds.num_nodes} quads)",
    )  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
