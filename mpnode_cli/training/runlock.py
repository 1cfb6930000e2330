"""The run folder's lock: one training writes a run folder at a time.

A training (`train`, `finetune`, `train --resume`) holds an exclusive `flock(2)` on its run
folder from before its first write there until it returns, taken without waiting: a second
writer of the same folder is refused at once, in one line that names the holder's process.
The lock is taken on the folder itself (a descriptor of the directory, which Linux and the
BSDs lock as they lock a file), so it adds no file to the run and leaves nothing to clean
up; the operating system releases it when the process ends, however it ends (SIGKILL and
a crash included), so a dead training never leaves its run locked.

Under torchrun only rank 0, the process that writes the run folder, takes it; the other
ranks learn of a refusal from rank 0 (`mpnode_cli.training.distributed.World.from_main`).

Where `fcntl` is missing (Windows) or the filesystem cannot lock (some network mounts),
the run goes on unlocked, as before locks existed.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

try:
    import fcntl
except ImportError:  # Windows: no flock
    fcntl = None

# What a filesystem that cannot lock answers; the run then goes on unlocked.
_NO_LOCKS = {errno.ENOLCK, errno.EBADF, errno.EINVAL, errno.EOPNOTSUPP}


class RunLock:
    """The lock on a run folder, held until `release` (or the process's end)."""

    def __init__(self, path: Path, fd: int | None):
        self.path, self._fd = path, fd

    def release(self) -> None:
        """Unlock and close; again is a no-op. The unlock itself (not only the close)
        matters where a child process inherited the descriptor: the lock goes with it."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)


def lock_run(run_dir: str | Path) -> RunLock:
    """Lock the run folder `run_dir` (an existing folder) for this process, without waiting.

    Raises:
        ValueError: another process holds it ("run R is in use by another mpnode process
            (pid N)"), or the folder cannot be opened (one line).
    """
    path = Path(run_dir)
    if fcntl is None:
        return RunLock(path, None)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    except OSError as exc:
        raise ValueError(f"cannot open run folder {path}: {exc.strerror or exc}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        holder = _holder(path)
        who = f" (pid {holder})" if holder else ""
        raise ValueError(f"run {path} is in use by another mpnode process{who}: wait for it "
                         "to end, or stop it, then try again") from None
    except OSError as exc:
        if exc.errno not in _NO_LOCKS:
            os.close(fd)
            raise ValueError(f"cannot lock run folder {path}: {exc.strerror or exc}") from None
    return RunLock(path, fd)


def _holder(path: Path) -> int | None:
    """The process that holds a flock on `path`, from Linux's /proc/locks (None elsewhere,
    or when it cannot be told)."""
    try:
        st = os.stat(path)
        lines = Path("/proc/locks").read_text().splitlines()
    except OSError:
        return None
    # "1: FLOCK  ADVISORY  WRITE 4242 fe:00:2212305 0 EOF": pid, then major:minor:inode
    # (the device numbers in hex); see proc(5), /proc/locks.
    where = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    for line in lines:
        fields = line.split()
        if len(fields) >= 6 and fields[1] == "FLOCK" and fields[5] == where:
            return int(fields[4]) if fields[4].isdigit() else None
    return None
