"""Names a package re-exports from its modules, imported on first use (PEP 562's module
`__getattr__`, as scientific-python's `lazy_loader.attach` does it), so that importing a
light module of the package does not import the heavy ones (torch, h5py)."""

from __future__ import annotations

from collections.abc import Callable
from importlib import import_module
from typing import Any


def lazy_exports(package: str, exports: dict[str, list[str]], namespace: dict[str, Any]
                 ) -> tuple[Callable[[str], Any], list[str]]:
    """The `__getattr__` and `__all__` of `package`, whose `namespace` (its `globals()`)
    re-exports the names `exports` lists under each of its modules.

    A name asked for imports its module and binds every name exported from it in the
    package, so later look-ups are plain attributes. Importing a submodule binds its own
    name in the package (`mpnode_cli.solver.solve`, the module, over the function); the
    names bound here afterwards take it back. (Code that imports such a submodule before
    anything asks the package for the name would leave the module there: import the names
    from the package.)
    """
    where = {name: module for module, names in exports.items() for name in names}

    def __getattr__(name: str) -> Any:
        if name not in where:
            raise AttributeError(f"module '{package}' has no attribute '{name}'")
        module = import_module(f"{package}.{where[name]}")
        namespace.update({key: getattr(module, key) for key in exports[where[name]]})
        return namespace[name]

    return __getattr__, sorted(where)
