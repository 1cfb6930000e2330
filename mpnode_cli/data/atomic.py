"""Files that appear whole at their path or not at all: the one atomic write.

A file is written under a temporary name (`.<name>.<pid>.<random>.tmp`,
`mpnode_cli.paths.temp_beside`) beside its target, on the same filesystem so that the final
rename is atomic, and renamed when the block ends without an error. Any exception, an
interrupt included, removes the temporary. Libraries that write from C (h5py, torch.save)
would swallow an interrupt raised inside their calls and finish the file, so SIGINT and
SIGTERM are held during the write (`mpnode_cli.signals.deferred_signals`) and taken where
the writer asks (`check()`), or once the file is in place.

`atomic_path` is the write itself, for any writer that takes a path (torch.save, a JSON
summary); `atomic_text` writes a string; `atomic_h5` writes a dataset file, which is a
user's output: its target is reserved first (`mpnode_cli.paths.reserve_output`: never an
input, created exclusively, length checked), and a signal during the write leaves nothing.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # h5py is imported where an HDF5 file is written, not by every writer
    import h5py


@contextmanager
def atomic_path(path: str | Path) -> Iterator[tuple[Path, Callable[[], None]]]:
    """Write a file atomically through a temporary: `with atomic_path(p) as (tmp, check)`.

    The block writes `tmp`; when it ends without an error, `tmp` replaces `path`. A signal
    that arrived during the block and was not raised by `check()` is raised once the file
    is in place (it is whole: stopping it halfway would gain nothing).

    Args:
        path: the target; its folder must exist. An existing file there is replaced.

    Yields:
        The temporary's path (nothing there yet) and `check()`, which raises
        `KeyboardInterrupt` if SIGINT or SIGTERM arrived; call it between steps of a write
        that should stop early, or last in the block for nothing to be left on a signal.

    Raises:
        KeyboardInterrupt: a signal during the write (after the rename unless `check()`
            raised it first).
        mpnode_cli.paths.OutputError: the rename was refused (the temporary is removed).
    """
    from mpnode_cli.paths import temp_beside
    from mpnode_cli.signals import deferred_signals

    path = Path(path)
    tmp = temp_beside(path)
    try:
        with deferred_signals() as pending:
            yield tmp, pending.check
            _rename(tmp, path)
    except BaseException:  # an interrupt too: never leave a half-written temp behind
        tmp.unlink(missing_ok=True)
        raise


def _rename(tmp: Path, path: Path) -> None:
    """`tmp` onto `path`; a refusal (a file made immutable since the writer checked it, a
    folder gone read-only) is one line, `mpnode_cli.paths.OutputError`."""
    from mpnode_cli.paths import OutputError

    try:
        os.replace(tmp, path)
    except OSError as exc:
        raise OutputError(f"cannot write {path}: {exc.strerror or exc} (nothing was "
                          "written)") from None


def atomic_text(path: str | Path, text: str) -> Path:
    """Write `text` to `path` atomically (`atomic_path`); returns the path."""
    with atomic_path(path) as (tmp, _):
        tmp.write_text(text)
    return Path(path)


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
    import h5py

    from mpnode_cli.paths import reserve_output

    with reserve_output(path, overwrite=overwrite), atomic_path(path) as (tmp, check):
        # Created by h5py itself so that the file gets the user's usual permissions.
        with h5py.File(tmp, "x") as f:
            yield f, check
        check()  # a signal during the write: no file rather than one the user stopped
