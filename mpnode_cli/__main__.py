"""`python -m mpnode_cli ...` is `mpnode ...`; it lets `torchrun -m mpnode_cli train ...` start
training in several processes (docs/scale.md, "Several processes or machines")."""

from mpnode_cli.cli.app import app
from mpnode_cli.cli.common import ascii_fallback

if __name__ == "__main__":
    ascii_fallback()  # help and usage errors print before any verb runs
    app(prog_name="mpnode")
