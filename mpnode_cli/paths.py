"""Output locations, checked before any work starts.

A verb that writes a file or a folder checks first that it can: the folder exists or can
be made, a file can be created in it, and what sits at the target (if anything) is a
regular file that `--force` may replace. A symlink, a folder, a device or a pipe is never
replaced: the user meant something else, and replacing it would be hard to undo.
"""

from __future__ import annotations

import hashlib
import os
import stat
import tempfile
from pathlib import Path


def describe(path: Path) -> str | None:
    """What sits at `path` if it is not a regular file ("a symbolic link", "a folder",
    ...), None for a regular file or nothing."""
    try:
        mode = os.lstat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):  # nothing there (the folder says why)
        return None
    except OSError as exc:
        return f"unreadable ({exc.strerror})"
    if stat.S_ISREG(mode):
        return None
    kinds = ((stat.S_ISLNK, "a symbolic link"), (stat.S_ISDIR, "a folder"),
             (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
             (stat.S_ISFIFO, "a named pipe"), (stat.S_ISSOCK, "a socket"))
    return next((name for test, name in kinds if test(mode)), "not a regular file")


def check_output_file(path: str | Path, *, overwrite: bool) -> None:
    """Refuse an output file that could not be written, before the work that makes it.

    Args:
        path: the file to be written (atomically: a temporary beside it, then a rename).
        overwrite: whether an existing regular file may be replaced (`--force`).

    Raises:
        FileExistsError: a regular file exists there and `overwrite` is False.
        ValueError: something other than a regular file sits there, or its folder cannot
            be made or written in (one line saying which).
    """
    path = Path(path)
    other = describe(path)
    if other is not None:
        raise ValueError(f"{path} is {other}: mpnode only replaces regular files, even with "
                         "--force; choose another output path")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} already exists (use --force to overwrite)")
    check_writable_dir(path.parent)


def check_writable_dir(path: str | Path) -> None:
    """Refuse a folder that cannot be written in, or made (without making it).

    A missing folder is judged by its nearest existing ancestor, which must be a folder a
    file can be created in; a probe file proves it (permission bits alone do not tell:
    read-only mounts, immutable folders, and the superuser all defy them).

    Raises:
        ValueError: one line naming the folder and why.
    """
    path = Path(path)
    probe = path
    while not probe.exists() and not probe.is_symlink() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise ValueError(f"cannot write in {path}: {probe} is not a folder")
    try:
        fd, name = tempfile.mkstemp(dir=probe, prefix=".mpnode-probe-")
        os.close(fd)
        os.unlink(name)
    except OSError as exc:
        where = path if probe == path else f"{path} (its folder {probe})"
        raise ValueError(f"cannot write in {where}: {exc.strerror or exc}") from None


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file's bytes: a checkpoint's identity (recorded by finetunes and
    predictions), an imported input's."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
