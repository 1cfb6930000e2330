"""`python -m mpnode_cli ...` is `mpnode ...`; it lets `torchrun -m mpnode_cli train ...` start
training in several processes (docs/scale.md, "Several processes or machines")."""

from mpnode_cli.cli.app import app

if __name__ == "__main__":
    app(prog_name="mpnode")
