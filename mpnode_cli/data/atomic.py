"""An HDF5 file that appears whole at its path or not at all.

The target is reserved first (`mpnode_cli.paths.reserve_output`: never an input, created
exclusively, length checked). The file is written under a temporary name
(`.<name>.<pid>.<random>.tmp`, `mpnode_cli.paths.temp_beside`) beside the target, on the
same filesystem so that the final rename is atomic, and renamed when the block ends without
an error. Any exception, an interrupt included, removes the temporary and the reservation.
h5py would swallow an interrupt raised inside its C calls and finish the file, so SIGINT
and SIGTERM are held during the write (`mpnode_cli.signals.deferred_signals`) and taken
where the writer asks (`check()`), or when the block ends.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import h5py


@contextmanager
def atomic_h5(path: str | Path, *, overwrite: bool = False
              ) -> Iterator[tuple[h5py.File, Callable[[], None]]]:
    """Write an HDF5 file atomically: `with atomic_h5(path) as (f, check): ...`.

    Args:
        path: the target; its folder is created if missing. Reserved while the file is
            written (`mpnode_cli.paths.reserve_output`): a writer that reserved it before
            its work passes `overwrite=True`.
        overwrite: replace an existing regular file (otherwise refuse).

    Yields:
        The open file (mode "x", under its temporary name) and `check()`, which raises
        `KeyboardInterrupt` if SIGINT or SIGTERM arrived; call it between steps of the write.

    Raises:
        FileExistsError, ValueError: as `mpnode_cli.paths.reserve_output`.
        KeyboardInterrupt: a signal during the write; nothing is left behind.
    """
    from mpnode_cli.paths import reserve_output, temp_beside
    from mpnode_cli.signals import deferred_signals

    path = Path(path)
    # Created by h5py itself so that the file gets the user's usual permissions.
    tmp = temp_beside(path)
    with reserve_output(path, overwrite=overwrite):
        try:
            with deferred_signals() as pending:
                with h5py.File(tmp, "x") as f:
                    yield f, pending.check
                pending.check()
                os.replace(tmp, path)
        except BaseException:  # an interrupt too: never leave a half-written temp behind
            tmp.unlink(missing_ok=True)
            raise
