"""Files that appear whole at their path or not at all: the one atomic write.

A file is written under a temporary name (`.<name>.<pid>.<random>.tmp`,
`mpnode_cli.path_limits.temp_beside`) beside its target, on the same filesystem so that the final
rename is atomic, and renamed when the block ends without an error. Any exception, an
interrupt included, removes the temporary. Libraries that write from C (h5py, torch.save)
would swallow an interrupt raised inside their calls and finish the file, so SIGINT and
SIGTERM are held during the write (`mpnode_cli.signals.deferred_signals`) and taken where
the writer asks (`check()`), or once the file is in place.

`atomic_path` is the write itself, for any writer that takes a path; `atomic_bytes` writes
bytes (a checkpoint, which torch serializes in memory first) and `atomic_text` a string;
`atomic_h5` writes a dataset file, which is a user's output: its target is reserved first
(`mpnode_cli.paths.reserve_output`: never an input, created exclusively, length checked),
and a signal during the write leaves nothing.

A full disk is one line (`mpnode_cli.paths.OutputError`) naming the file, what it needed and
what the disk had, and leaves nothing. torch.save and HDF5 must never meet it themselves:
torch then reports "unexpected pos", and HDF5 crashes the process as it closes the file
(a segfault), so the bytes reach the disk through Python's own writes (`_Sink`).
"""

from __future__ import annotations

import errno
import os
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # h5py is imported where an HDF5 file is written, not by every writer
    import io

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
    from mpnode_cli.path_limits import temp_beside
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
    """Write `text` to `path` atomically (`atomic_bytes`, UTF-8); returns the path."""
    return atomic_bytes(path, text.encode())


def atomic_bytes(path: str | Path, data: bytes | memoryview) -> Path:
    """Write `data` to `path` atomically (`atomic_path`); returns the path.

    Raises:
        mpnode_cli.paths.OutputError: no space left on the device (nothing is written).
    """
    path = Path(path)
    free = _free(path.parent)
    with atomic_path(path) as (tmp, _):
        try:
            with open(tmp, "xb") as f:
                f.write(data)
        except OSError as exc:
            raise _full(exc, path, memoryview(data).nbytes, free) from None
    return path


def _free(folder: Path) -> int | None:
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return None


def _full(exc: OSError, path: Path, need: int, free: int | None, more: bool = False
          ) -> OSError:
    """A failed write's error: one line (`OutputError`) for a full disk, else `exc`."""
    from mpnode_cli.memory import format_bytes
    from mpnode_cli.paths import OutputError

    if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
        return exc
    had = "" if free is None else f", the disk had {format_bytes(free)} free"
    return OutputError(f"no space left on device writing {path}: it needed "
                       f"{'more than ' * more}{format_bytes(need)}{had} (nothing was written)")


@contextmanager
def atomic_h5(path: str | Path, *, overwrite: bool = False
              ) -> Iterator[tuple[h5py.File, Callable[[], None]]]:
    """Write an HDF5 file atomically: `with atomic_h5(path) as (f, check): ...`; once the
    block ends, the file's `checksum` is its contents' (`mpnode_cli.data.integrity`).

    Args:
        path: the target; its folder is created if missing. Reserved while the file is
            written (`mpnode_cli.paths.reserve_output`): a writer that reserved it before
            its work passes `overwrite=True`.
        overwrite: replace an existing regular file (otherwise refuse).

    Yields:
        The open file (new, under its temporary name) and `check()`, which raises
        `KeyboardInterrupt` if SIGINT or SIGTERM arrived, or `OutputError` once the disk is
        full; call it between steps of the write.

    Raises:
        FileExistsError, ValueError: as `mpnode_cli.paths.reserve_output`.
        mpnode_cli.paths.OutputError: no space left on the device; nothing is left behind.
        KeyboardInterrupt: a signal during the write; nothing is left behind.
    """
    import h5py

    from mpnode_cli.data.integrity import CHECKSUM_ATTR, contents_sha256
    from mpnode_cli.paths import reserve_output

    with reserve_output(path, overwrite=overwrite), atomic_path(path) as (tmp, check):
        free = _free(Path(tmp).parent)
        # With the user's usual permissions (0666 less the umask), as HDF5 would create it.
        with open(tmp, "xb+", buffering=0) as raw:
            sink = _Sink(raw)

            def checked() -> None:  # a signal, or a full disk: stop the write there
                check()
                if sink.error is not None:
                    raise _full(sink.error, Path(path), sink.size, free, more=True)

            with h5py.File(sink, "w") as f:
                try:
                    yield f, checked
                    checked()
                    f.attrs[CHECKSUM_ATTR] = contents_sha256(f)
                except Exception:
                    checked()  # a full disk, if that is what failed: read back, it is zeros
                    raise
        checked()  # a signal during the write: no file rather than one the user stopped


class _Sink:
    """The temporary file as h5py's `fileobj` driver writes it, where a failed write never
    reaches HDF5 (which would crash on closing the file): the first error is kept for the
    writer to raise (`atomic_h5`'s check), and later writes are dropped."""

    def __init__(self, raw: io.FileIO):
        self.raw, self.error, self.size = raw, None, 0

    def seek(self, offset: int, whence: int = 0) -> int:
        return self.raw.seek(offset, whence)

    def tell(self) -> int:
        return self.raw.tell()

    def read(self, size: int) -> bytes:
        data = self.raw.read(size)  # past the end (a dropped write), zeros as HDF5's own
        return data + bytes(size - len(data))

    def write(self, data: Any) -> int:
        view = whole = memoryview(data).cast("B")
        self.size = max(self.size, self.raw.tell() + len(view))
        while len(view) and self.error is None:
            try:
                view = view[self.raw.write(view):]
            except OSError as exc:
                self.error = exc
        return len(whole)

    def truncate(self, size: int) -> None:
        if self.error is None:
            try:
                self.raw.truncate(size)
            except OSError as exc:
                self.error = exc

    def flush(self) -> None:
        """Nothing is buffered here (`raw` is unbuffered)."""
