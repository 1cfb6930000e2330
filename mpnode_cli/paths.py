"""Output locations: the one guard every writer uses, before the work that fills them.

A verb that writes a file or a folder checks first that it can (`check_output_file`,
`check_output_folder`), then takes the path for itself (`reserve_output`, `reserve_folder`):

- **Never an input.** An output that is the same file as one of the verb's inputs (by
  `os.path.samefile`: through symbolic links and hard links) is refused, even with
  `--force`: replacing it would destroy the data the output is made from.
- **Created exclusively.** A new output file is reserved by creating an empty placeholder
  with `O_CREAT | O_EXCL` before any work; the finished file is written beside it under a
  temporary name and renamed over it (`mpnode_cli.data.atomic`). Of two runs writing one
  new path without `--force`, the second is refused at once instead of replacing the first
  run's file when it finishes. A run that fails removes its placeholder. A folder is
  reserved by making its first entry with `mkdir`, which is exclusive too.
- **Length checked.** Each name in the path fits the filesystem's limit (usually 255
  bytes) and the whole path the system's (usually 4096, with room for the temporary and
  the files a folder will hold), so a long name is refused up front, as what it is.
- **Only regular files replaced.** What sits at the target (if anything) must be a
  regular file that `--force` may replace. A symlink, a folder, a device or a pipe is
  never replaced: the user meant something else, and replacing it would be hard to undo.
  A file the verb wrote itself (an index it rebuilds: `mine`, its first bytes) is
  replaced without `--force`; anyone else's is the user's, and refused.
- **Replaceable, checked up front.** A file that `--force` will replace must be one the
  final rename can replace: not immutable or append-only (`chattr +i`, `+a`), not another
  user's in a sticky folder. This is checked before the work, and a rename that fails
  anyway is one line (`OutputError`), with the temporary removed.
- **Named as a path.** An output given as an empty string, or (for a file) ending in `/`,
  is refused (`output_arg`): "" would mean the current folder, and `newdir/` a folder, not
  the file the verb writes.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterable
from pathlib import Path

from mpnode_cli.path_limits import NAME_MAX, check_length, check_writable_dir

# Inode flags that forbid replacing a file by a rename (linux/fs.h: FS_IMMUTABLE_FL,
# FS_APPEND_FL), read with the FS_IOC_GETFLAGS ioctl (`_IOR('f', 1, long)` on 64 bits).
_IMMUTABLE, _APPEND_ONLY, _GETFLAGS = 0x10, 0x20, 0x80086601


class OutputError(ValueError):
    """An output that cannot be written where it was asked (one line for the user)."""

# Bytes a temporary beside a file may add to its name: `.` + `.<pid>.<8 hex>.tmp`.
_TEMP_ROOM = 32
# Room left in a folder's path for what its writer puts inside (a name's worth).
_FOLDER_ROOM = NAME_MAX + 1


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


def check_output_file(path: str | Path, *, overwrite: bool,
                      inputs: Iterable[str | Path | None] = (), mine: bytes | None = None
                      ) -> None:
    """Refuse an output file that could not be written, before the work that makes it.

    Args:
        path: the file to be written (atomically: a temporary beside it, then a rename).
        overwrite: whether an existing regular file may be replaced (`--force`).
        inputs: the files the verb reads (None entries are skipped); the output may be
            none of them.
        mine: how a file this verb wrote begins (an index it rebuilds); an existing file
            that begins so is replaced without `overwrite`.

    Raises:
        FileExistsError: a regular file exists there, `overwrite` is False, and it is not
            the verb's own (`mine`).
        ValueError: a name or path too long, one of `inputs`, something other than a
            regular file there, a file the rename could not replace, or a folder that
            cannot be made or written in (one line saying which).
    """
    path = Path(path)
    check_length(path, room=_TEMP_ROOM)
    other = describe(path)
    if other is not None:
        raise ValueError(f"{path} is {other}: mpnode only replaces regular files, even with "
                         "--force; choose another output path")
    check_not_input(path, inputs)
    if path.exists():
        if not (overwrite or (mine is not None and begins(path, mine))):
            raise FileExistsError(_exists(path, mine is not None))
        check_replaceable(path)
    check_writable_dir(path.parent)


def check_replaceable(path: str | Path) -> None:
    """Refuse an existing file that a rename could not replace: immutable or append-only
    (`chattr +i`, `chattr +a`), or another user's in a sticky folder (as /tmp) — what the
    kernel's rename refuses beyond the folder's own permission (which
    `check_writable_dir` proves).

    Raises:
        OutputError: one line naming the file and why.
    """
    path = Path(path)
    flags = _inode_flags(path)
    if flags & (_IMMUTABLE | _APPEND_ONLY):
        how = "immutable" if flags & _IMMUTABLE else "append-only"
        raise OutputError(f"cannot replace {path}: it is {how} (lsattr shows it; chattr "
                          f"-{'i' if flags & _IMMUTABLE else 'a'} lifts it); choose another "
                          "output path")
    try:
        own, folder = os.lstat(path), os.stat(path.parent)
    except OSError:
        return
    uid = os.geteuid() if hasattr(os, "geteuid") else 0
    if folder.st_mode & stat.S_ISVTX and uid not in (0, own.st_uid, folder.st_uid):
        raise OutputError(f"cannot replace {path}: it is another user's, in a folder where "
                          "only a file's owner may replace it; choose another output path")


def output_arg(text: str | Path | None, option: str, *, folder: bool = False
               ) -> Path | None:
    """A path given on the command line for an output, as the verb takes it.

    Args:
        text: what was typed (None: not given).
        option: its name, for the message (`--out`).
        folder: whether it names a folder (a trailing `/` is then just a folder).

    Raises:
        OutputError: an empty path (it would be the current folder), or a file's path
            that ends in `/` (a folder, where the verb writes a file).
    """
    if text is None:
        return None
    raw = os.fspath(text)
    if not raw.strip():
        raise OutputError(f"{option} is empty: give a path (. for the current folder)"
                          if folder else f"{option} is empty: give the file's path")
    if not folder and raw.endswith(("/", os.sep)):
        raise OutputError(f"{option} {raw} ends in '/', a folder: give the file's name "
                          f"too, e.g. {raw}data.h5")
    parts = Path(raw).parts
    if any(part == ".." and i and not Path(*parts[:i]).exists()
           for i, part in enumerate(parts)):  # `x/..` of no x: made, it would be left behind
        return Path(os.path.normpath(raw))
    return Path(raw)


class Reservation:
    """An output file taken for one writer (`reserve_output`); as a context manager, it
    removes its placeholder when the block ends without having filled it."""

    def __init__(self, path: Path, placeholder: os.stat_result | None,
                 folders: list[Path] | None = None):
        self.path = path
        self._placeholder = placeholder  # the empty file made, None where one existed
        self._folders = folders or []  # the folders made for it, outermost first

    def release(self) -> None:
        """Remove the placeholder if it is still there, empty (nothing was written), and
        the folders made for it if they are empty."""
        placeholder, self._placeholder = self._placeholder, None
        try:
            now = os.lstat(self.path)
        except OSError:
            return
        if placeholder is None or (now.st_dev, now.st_ino, now.st_size) != (
                placeholder.st_dev, placeholder.st_ino, 0):
            return
        self.path.unlink(missing_ok=True)
        for folder in reversed(self._folders):
            try:
                folder.rmdir()
            except OSError:  # not empty: someone else's now
                break

    def __enter__(self) -> Reservation:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def reserve_output(path: str | Path, *, overwrite: bool,
                   inputs: Iterable[str | Path | None] = ()) -> Reservation:
    """Check an output file (`check_output_file`) and take it for this writer.

    A new file is created empty and exclusively (`O_CREAT | O_EXCL`), so a second writer
    of the same path is refused until this one is done; an existing file (`overwrite`)
    stays as it is until the finished file replaces it. Use it as `with
    reserve_output(...):` around the work and the write; inside, write the file with
    `overwrite=True`, since the path is now the block's own.

    Raises:
        FileExistsError, ValueError: as `check_output_file`; FileExistsError too when
            another writer created the file since the check.
    """
    path = Path(path)
    check_output_file(path, overwrite=overwrite, inputs=inputs)
    folders = [p for p in reversed(path.parents) if not os.path.lexists(p)]
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    except FileExistsError:
        if not overwrite:  # another writer took it between the check and now
            raise FileExistsError(_exists(path)) from None
        check_output_file(path, overwrite=True)  # still a regular file, and writable
        return Reservation(path, None)
    try:
        placeholder = os.fstat(fd)
    finally:
        os.close(fd)
    return Reservation(path, placeholder, folders)


def check_output_folder(path: str | Path) -> None:
    """Refuse an output folder that could not be made or written in (without making it):
    names too long, something other than a folder there, no permission.

    Raises:
        ValueError: one line naming the folder and why.
    """
    path = Path(path)
    check_length(path, room=_FOLDER_ROOM)
    if os.path.lexists(path) and not path.is_dir():
        raise ValueError(f"{path} is {describe(path) or 'a file'}, not a folder: choose "
                         "another path")
    check_writable_dir(path)


def reserve_folder(path: str | Path, first: str) -> bool:
    """Check an output folder (`check_output_folder`) and take it for this writer: make
    it (or take it as it is, if it exists empty), then make `first` inside it, exclusively,
    so that of two writers of the same folder one is refused.

    Args:
        path: the folder.
        first: the entry this writer makes first inside it (a folder).

    Returns:
        Whether `path` itself was made.

    Raises:
        FileExistsError: the folder holds something already (another writer's `first`,
            perhaps made since the check).
        ValueError: as `check_output_folder`.
    """
    path = Path(path)
    check_output_folder(path)
    try:
        path.mkdir(parents=True)
        made = True
    except FileExistsError:
        made = False
        if any(path.iterdir()):
            raise FileExistsError(f"{path} already exists and is not empty") from None
    try:
        (path / first).mkdir()
    except FileExistsError:
        raise FileExistsError(f"{path} was just taken by another run") from None
    return made


def check_not_input(path: str | Path, inputs: Iterable[str | Path | None]) -> None:
    """Refuse an output that is one of `inputs` (the same file, through links or not).

    Raises:
        ValueError: one line naming the input.
    """
    for each in inputs:
        if each is not None and _same_file(Path(path), Path(each)):
            alias = "" if str(each) == str(path) else f" ({each})"
            raise ValueError(f"{path} is one of the inputs{alias}: mpnode never writes over "
                             "its inputs, even with --force; choose another output path")


def _exists(path: Path, foreign: bool = False) -> str:
    """Why an existing output is refused without `--force`: an empty file is most likely
    another run's reservation, and saying so beats a bare "exists"; a `foreign` one is a
    file the verb would have written itself, but did not."""
    try:
        empty = path.stat().st_size == 0
    except OSError:
        empty = False
    if foreign:
        return (f"{path} already exists and mpnode did not write it: move it away, or choose "
                "another output folder")
    if empty:
        return (f"{path} already exists and is empty: another mpnode run may be writing it "
                "(or one was killed before it finished); wait for it, or use --force to "
                "replace it")
    return f"{path} already exists (use --force to overwrite)"


def begins(path: Path, start: bytes) -> bool:
    """Whether the file at `path` begins with `start` (False if it cannot be read)."""
    try:
        with open(path, "rb") as f:
            return f.read(len(start)) == start
    except OSError:
        return False


def _inode_flags(path: Path) -> int:
    """The file's inode flags (`lsattr`), 0 where the system or filesystem has none."""
    try:
        import array
        import fcntl
    except ImportError:  # not POSIX
        return 0
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | os.O_NONBLOCK)
    except OSError:
        return 0
    try:
        buf = array.array("l", [0])
        fcntl.ioctl(fd, _GETFLAGS, buf, True)
        return int(buf[0])
    except OSError:  # a filesystem without flags (tmpfs on old kernels, NFS, ...)
        return 0
    finally:
        os.close(fd)


def _same_file(a: Path, b: Path) -> bool:
    """Whether `a` and `b` name one file: the same inode where both exist, else the same
    path once symbolic links are resolved."""
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them is missing (or unreadable)
        return os.path.realpath(a) == os.path.realpath(b)
