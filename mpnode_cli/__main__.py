"""`python -m mpnode_cli ...` is `mpnode ...`; it lets `torchrun -m mpnode_cli train ...` start
training in several processes (docs/scale.md, "Several processes or machines").

`main` is the `mpnode` script's entry point too. It imports the CLI itself (typer, pydantic
and rich: most of a second), so that a Ctrl-C during that import, or while typer builds the
commands, ends in one line and exit 130 (as one during a verb does) rather than in a
traceback.
"""

import sys


def main() -> None:
    try:
        from mpnode_cli.cli.app import main as cli

        cli()
    except KeyboardInterrupt:  # before any verb ran: typer's own handling starts with it
        sys.stderr.write("Interrupted (SIGINT): nothing done\n")
        raise SystemExit(130) from None


if __name__ == "__main__":
    main()
