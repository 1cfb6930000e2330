"""An HDF5 file that appears whole at its path or not at all.

The file is written under a temporary name (`.<name>.<pid>.<random>.tmp`) beside the
target, on the same filesystem so that the final rename is atomic, and renamed when the
block ends without an error. Any exception, an interrupt included, removes the temporary.
h5py would swallow an interrupt raised inside its C calls and finish the file, so SIGINT
and SIGTERM are held during the write (`mpnode_cli.signals.deferred_signals`) and taken
where the writer asks (`check()`), or when the block ends.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import h5py


@contextmanager
def atomic_h5(path: str | Path, *, overwrite: bool = False
              ) -> Iterator[tuple[h5py.File, Callable[[], None]]]:
    """Write an HDF5 file atomically: `with atomic_h5(path) as (f, check): ...`.

    Args:
        path: the target; its folder is created if missing.
        overwrite: replace an existing regular file (otherwise refuse).

    Yields:
        The open file (mode "x", under its temporary name) and `check()`, which raises
        `KeyboardInterrupt` if SIGINT or SIGTERM arrived; call it between steps of the write.

    Raises:
        FileExistsError, ValueError: as `mpnode_cli.paths.check_output_file`.
        KeyboardInterrupt: a signal during the write; nothing is left behind.
    """
    from mpnode_cli.paths import check_output_file
    from mpnode_cli.signals import deferred_signals

    path = Path(path)
    check_output_file(path, overwrite=overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    # Created by h5py itself so that the file gets the user's usual permissions.
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        with deferred_signals() as pending:
            with h5py.File(tmp, "x") as f:
                yield f, pending.check
            pending.check()
            os.replace(tmp, path)
    except BaseException:  # an interrupt too: never leave a half-written temp behind
        tmp.unlink(missing_ok=True)
        raise
