"""mpnode: learn modular simulations of networked dynamical systems (MP-NODE).

The package is a library (solver, systems, models, training) under a thin typer CLI
(`mpnode_cli.cli`). Importing the package itself is cheap: nothing here imports torch.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("mpnode")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"
