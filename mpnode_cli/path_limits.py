"""What the filesystem lets a writer do here: how long one name and a whole path may be
(`check_length`), a temporary's name beside a file that fits them (`temp_beside`,
`shorten`), and whether a folder can be written in (`check_writable_dir`).

The output guard (`mpnode_cli.paths`) runs these checks before the work.
"""

from __future__ import annotations

import os
import tempfile
import uuid
from pathlib import Path

# POSIX's limits where the filesystem does not say (`os.pathconf`): one name, one path.
NAME_MAX, PATH_MAX = 255, 4096


def check_length(path: str | Path, *, room: int = 0) -> None:
    """Refuse a path the filesystem cannot hold: a name longer than its limit for one name
    (usually 255 bytes), or a whole path (absolute, plus `room` bytes for what the writer
    adds: a temporary's suffix, the files inside a folder) longer than the system's.

    Raises:
        ValueError: one line saying which name, or how long, and the limit.
    """
    path = Path(path)
    name_max, path_max = _limits(path)
    for name in path.parts:
        size = len(os.fsencode(name))
        if size > name_max and name != path.anchor:
            where = f" in {_short(str(path))}" if name != str(path) else ""
            raise ValueError(f"the name '{_short(name)}'{where} is {size} bytes, longer than "
                             f"the {name_max} bytes a file or folder name may have here; "
                             "choose a shorter name")
    size = len(os.fsencode(os.path.abspath(path)))
    if size + room >= path_max:
        raise ValueError(f"cannot write {_short(str(path))}: its full path is {size} bytes, "
                         f"and mpnode needs it under {path_max - room} (the {path_max} bytes "
                         "a path may have here, less room for the files written there); "
                         "choose a shorter path")


def temp_beside(path: str | Path) -> Path:
    """A fresh temporary name beside `path` (same folder, hence same filesystem, so that a
    rename onto `path` is atomic): `.<name>.<pid>.<random>.tmp`, its name shortened to fit
    the limit on one name."""
    path = Path(path)
    tail = f".{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp"
    return path.with_name(f".{shorten(path.name, _limits(path)[0] - 1 - len(tail))}{tail}")


def shorten(name: str, size: int) -> str:
    """The longest start of `name`, in whole characters, that is at most `size` bytes on
    disk (for names mpnode makes from a user's: a temporary's, a run folder's)."""
    while len(os.fsencode(name)) > size:
        name = name[:-1]
    return name


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


def _limits(path: Path) -> tuple[int, int]:
    """The filesystem's limits on one name and on a whole path, in bytes, asked of the
    nearest existing folder above `path` (POSIX's where it does not say)."""
    probe = Path(os.path.abspath(path)).parent
    while not os.path.isdir(probe) and probe != probe.parent:  # isdir: False on any error
        probe = probe.parent
    limits = []
    for name, default in (("PC_NAME_MAX", NAME_MAX), ("PC_PATH_MAX", PATH_MAX)):
        try:
            limits.append(int(os.pathconf(probe, name)) or default)
        except (AttributeError, OSError, ValueError):  # no pathconf (Windows), or no answer
            limits.append(default)
    return limits[0], limits[1]


def _short(text: str, keep: int = 60) -> str:
    """`text` as it is, or its start and end around an ellipsis when over `keep` chars."""
    return text if len(text) <= keep else f"{text[:keep * 2 // 3]}…{text[-keep // 3:]}"
