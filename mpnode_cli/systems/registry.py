"""Systems by name: the one list that feeds the CLI's choices and config validation.

Adding a system is adding its module and one line here. Importing this module is cheap (no
torch, no networkx), so the CLI may use it for `--help` and completion.
"""

from __future__ import annotations

from mpnode_cli.systems.base import System
from mpnode_cli.systems.gene import Gene
from mpnode_cli.systems.kuramoto import Kuramoto
from mpnode_cli.systems.lorenz import Lorenz
from mpnode_cli.systems.pendulum import Pendulum
from mpnode_cli.systems.quadrotor import Quadrotor

SYSTEMS: dict[str, type[System]] = {
    cls.name: cls for cls in (Pendulum, Lorenz, Gene, Kuramoto, Quadrotor)
}


def get_system(name: str, **params: object) -> System:
    """Instantiate the system called `name` with its parameters and options.

    Raises:
        ValueError: an unknown name, or a parameter/option the system does not have.
    """
    if name not in SYSTEMS:
        raise ValueError(f"unknown system '{name}' (choose from: {', '.join(SYSTEMS)})")
    return SYSTEMS[name](**params)
