"""mpnode: learn modular simulations of networked dynamical systems (MP-NODE).

The package is a library (solver, systems, models, training) under a thin typer CLI
(`mpnode_cli.cli`). Importing the package itself is cheap: nothing here imports torch, and
`__version__` is read from the installed metadata when first asked for (importlib.metadata
would be most of the package's own import, before `mpnode_cli.__main__` guards Ctrl-C).
"""


def __getattr__(name: str) -> str:
    if name != "__version__":
        raise AttributeError(f"module 'mpnode_cli' has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("mpnode")
    except PackageNotFoundError:  # running from a source tree that was never installed
        return "0.0.0+unknown"
