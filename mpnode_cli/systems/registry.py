"""Systems by name: the built-in ones, and your own.

`SYSTEMS` lists the built-in systems (adding one is adding its module and one line here);
importing this module is cheap (no torch, no networkx), so the CLI may use it for `--help`
and completion. Systems of your own join in two ways (docs/custom-systems.md):

- a Python file, `mpnode generate --system-file my_system.py`: `load_system_file` imports
  it and registers the one `System` subclass it defines;
- a package's entry point in the group `mpnode.systems` (`name = "package.module:Class"`),
  found by `entry_point_systems` the first time a name is not built in.

Either kind then runs through the same solver, writer, presets and checks as the
built-in ones. A plug-in cannot take a built-in system's name.
"""

from __future__ import annotations

import functools
import importlib.util
import inspect
import json
import math
import sys
from pathlib import Path

from mpnode_cli.systems.barzel_barabasi import BD, MAK, MM, ND, SIS
from mpnode_cli.systems.base import Option, System
from mpnode_cli.systems.gene import Gene
from mpnode_cli.systems.kuramoto import Kuramoto
from mpnode_cli.systems.lorenz import Lorenz
from mpnode_cli.systems.pendulum import Pendulum
from mpnode_cli.systems.plugin_calls import HardExit as _HardExit
from mpnode_cli.systems.plugin_calls import no_hard_exit as _no_hard_exit
from mpnode_cli.systems.quadrotor import Quadrotor

ENTRY_POINT_GROUP = "mpnode.systems"

SYSTEMS: dict[str, type[System]] = {
    cls.name: cls for cls in (Pendulum, Lorenz, Gene, Kuramoto, Quadrotor, SIS, MAK, MM, BD, ND)
}
# Systems registered from files in this process (`load_system_file`).
_FILES: dict[str, type[System]] = {}


def get_system(name: str, **params: object) -> System:
    """Instantiate the system called `name` with its parameters and options.

    Raises:
        ValueError: an unknown name, or a parameter/option the system does not have.
    """
    return system_class(name)(**params)


def system_class(name: str) -> type[System]:
    """The class of the system called `name`: built in, loaded from a file, or an entry point.

    Raises:
        ValueError: an unknown name (the message lists the known ones), or a plug-in that
            cannot be loaded.
    """
    if name in SYSTEMS:
        return SYSTEMS[name]
    if name in _FILES:
        return _FILES[name]
    plugins = entry_point_systems()
    if name in plugins:
        return plugins[name]
    known = [*SYSTEMS, *_FILES, *plugins]
    raise ValueError(f"unknown system '{name}' (choose from: {', '.join(known)}; or your own "
                     "with --system-file FILE, docs/custom-systems.md)")


def sparse_systems() -> list[str]:
    """The built-in systems that run on edge lists (`System.sparse`), hence on graphs of
    any size."""
    return [name for name, cls in SYSTEMS.items() if cls.sparse]


def grid_systems() -> list[str]:
    """The built-in systems whose nodes sit on a grid (`System.grid_layout`): those that
    take `grid`."""
    return [name for name, cls in SYSTEMS.items() if cls.grid_layout]


def all_systems() -> dict[str, type[System]]:
    """Every system known to this process: built in, from files, from entry points."""
    return {**entry_point_systems(), **_FILES, **SYSTEMS}


@functools.cache
def entry_point_systems() -> dict[str, type[System]]:
    """The systems that installed packages declare in the entry point group
    `mpnode.systems` (loaded once per process).

    Raises:
        ValueError: an entry point that does not load, or is not a `System` subclass of
            the name it is registered under.
    """
    from importlib.metadata import entry_points

    found: dict[str, type[System]] = {}
    for point in entry_points(group=ENTRY_POINT_GROUP):
        try:
            cls = point.load()
        except KeyboardInterrupt:
            raise
        except BaseException as exc:  # the user's code: any error, or exit, is "cannot load"
            raise ValueError(f"the {ENTRY_POINT_GROUP} entry point '{point.name}' "
                             f"({point.value}) does not load: {_failure(exc)}") from None
        _check_class(cls, f"entry point '{point.name}' ({point.value})")
        if cls.name != point.name:
            raise ValueError(f"entry point '{point.name}' ({point.value}) names a system "
                             f"called '{cls.name}': register it under its own name")
        found[cls.name] = cls
    return found



def load_system_file(path: str | Path) -> type[System]:
    """Import a Python file and register the one `System` subclass it defines.

    The module is imported under a name derived from the file's path, so two files of the
    same name do not collide; loading the same file again returns its registered class,
    and a file that defines a name already loaded from another file takes it over.

    Raises:
        ValueError: a missing file, one that does not import, or one that defines no
            `System` subclass or several.
    """
    path = Path(path).resolve()
    if not path.is_file():
        raise ValueError(f"--system-file {path}: no such file")
    module_name = f"mpnode_system_{abs(hash(str(path))):x}"
    module = sys.modules.get(module_name)
    if module is None:
        spec = importlib.util.spec_from_file_location(module_name, path)
        if spec is None or spec.loader is None:
            raise ValueError(f"--system-file {path}: not a Python file")
        module = importlib.util.module_from_spec(spec)
        sys.modules[module_name] = module
        try:
            with _no_hard_exit():
                spec.loader.exec_module(module)
        except BaseException as exc:  # the user's code: any error, or exit, is "cannot load"
            del sys.modules[module_name]
            if isinstance(exc, KeyboardInterrupt):
                raise
            raise ValueError(f"--system-file {path} does not import: {_failure(exc)}") from None
    classes = [cls for _, cls in inspect.getmembers(module, inspect.isclass)
               if issubclass(cls, System) and cls.__module__ == module_name]
    concrete = [cls for cls in classes if not inspect.isabstract(cls)]
    if not concrete and classes:  # a class that misses a method: say which
        missing = ", ".join(sorted(classes[0].__abstractmethods__))
        raise ValueError(f"--system-file {path}: the system {classes[0].__name__} does not "
                         f"declare {missing} (docs/custom-systems.md)")
    if len(concrete) != 1:
        names = ", ".join(cls.__name__ for cls in concrete) or "none"
        raise ValueError(f"--system-file {path} must define exactly one System subclass, "
                         f"found {names}")
    cls = concrete[0]
    _check_class(cls, f"--system-file {path}")
    _FILES[cls.name] = cls  # the file named last defines the name
    return cls


def _failure(exc: BaseException) -> str:
    """Why importing a plug-in failed, in a few words (`sys.exit` said as such)."""
    if isinstance(exc, _HardExit):
        return str(exc)
    if isinstance(exc, SystemExit):
        return f"it called sys.exit({exc.code!r}) as it was imported"
    return f"{type(exc).__name__}: {exc}"


def _check_class(cls: object, where: str) -> None:
    """A plug-in must be a concrete `System` with the declarations generate needs."""
    if not (inspect.isclass(cls) and issubclass(cls, System)):
        raise ValueError(f"{where} is not a subclass of mpnode_cli.systems.System")
    missing = [attr for attr in ("name", "state_names", "topologies", "default_topology",
                                 "default_nodes", "defaults") if not hasattr(cls, attr)]
    if missing or inspect.isabstract(cls):
        what = ", ".join(missing) or "sample_initial or rhs"
        raise ValueError(f"{where}: the system {cls.__name__} does not declare {what} "
                         "(docs/custom-systems.md)")
    wrong = _wrong_declaration(cls)
    if wrong:
        raise ValueError(f"{where}: the system {cls.__name__} declares {wrong} "
                         "(docs/custom-systems.md)")
    if cls.name in SYSTEMS and SYSTEMS[cls.name] is not cls:
        raise ValueError(f"{where}: '{cls.name}' is a built-in system; give yours another "
                         "name")
    if cls.name == "custom":  # what a dataset of `mpnode import` says its system is
        raise ValueError(f"{where}: 'custom' names the data mpnode import makes (of no "
                         "known system); give yours another name")
    if cls.default_topology not in cls.topologies:
        raise ValueError(f"{where}: default_topology '{cls.default_topology}' is not among "
                         f"its topologies ({', '.join(cls.topologies)})")


def _wrong_declaration(cls: type[System]) -> str | None:
    """The first class attribute of a plug-in that is not what `System` documents (as
    `name = 3, not a non-empty string`), or None: read at generate time, a wrong one would
    fail far from the class."""

    def names(value: object, least: int = 0) -> bool:  # distinct, as they name columns
        return (isinstance(value, tuple | list) and len(value) >= least
                and all(isinstance(v, str) and v for v in value) and len(set(value)) == len(value))

    def number(value: object, low: float = -math.inf) -> bool:
        return (isinstance(value, int | float) and not isinstance(value, bool)
                and math.isfinite(value) and value > low)

    def table(value: object, keys: object, values) -> bool:
        return isinstance(value, dict) and all(
            isinstance(k, str) and (keys is None or k in keys) and values(v)
            for k, v in value.items())

    def recipe() -> bool:
        try:
            json.dumps(cls.recipe())
        except (TypeError, ValueError):
            return False
        return True

    checks = [
        # The name becomes part of paths (datasets/<name>-n8-ring-s0.h5): no '/' or '..'.
        ("name", lambda v: isinstance(v, str) and v.isidentifier(),
         "an identifier (letters, digits and _, as a Python name; it names the dataset file)"),
        ("state_names", lambda v: names(v, 1), "a tuple of at least one name, each once"),
        ("control_names", names, "a tuple of names, each once"),
        ("topologies", lambda v: names(v, 1), "a tuple of at least one topology, each once"),
        ("default_nodes", lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 1,
         "a whole number ≥ 1"),
        ("defaults", lambda v: table(v, None, number), "a dict of names to finite numbers"),
        ("options", lambda v: table(v, None, lambda o: isinstance(o, Option)),
         "a dict of names to Option"),
        ("data_defaults", lambda v: table(v, ("trajectories", "t_end", "dt"),
                                          lambda x: number(x, 0)),
         "a dict of trajectories, t_end and dt to positive numbers"),
        ("presets", lambda v: table(v, None, lambda p: isinstance(p, dict)),
         "a dict of preset names to dicts of generate fields"),
        ("recommended", lambda v: isinstance(v, dict) and recipe(),
         "a dict of train-config fields that JSON can hold"),
        ("sparse", lambda v: isinstance(v, bool), "True or False"),
    ]
    checks.append(("periodic_states", lambda v: names(v) and set(v) <= set(cls.state_names),
                   "a tuple of distinct names among its state_names"))
    for attr, ok, what in checks:
        value = getattr(cls, attr)
        if not ok(value):
            shown = repr(value)
            return f"{attr} = {shown if len(shown) <= 40 else shown[:37] + '...'}, not {what}"
    return None
