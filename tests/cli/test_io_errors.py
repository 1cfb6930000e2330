"""A disk that fails a read (EIO) and files this user may not read: one `Error:` line
naming the cause, never a traceback, and nothing changed.

Once, `train --resume` on a run whose `checkpoints/` folder could not be entered ended in a
PermissionError traceback, and an unreadable `last.pt` was called "not an mpnode
checkpoint (... is it a dataset or another file?)".
"""

from __future__ import annotations

import errno
import os
import pathlib

from conftest import invoke, one_line_error

from mpnode_cli.data import hdf5 as hdf5_module
from mpnode_cli.data import validate as validate_module
from mpnode_cli.training import checkpoint as checkpoint_module


def _files(folder) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*")
            if p.is_file()}


def _eio(path=None):
    def fail(*_args, **_kw):
        raise OSError(errno.EIO, os.strerror(errno.EIO), *([] if path is None else [path]))
    return fail


def test_a_disk_that_fails_a_read_is_one_line_with_the_cause(user_files, monkeypatch):
    data = user_files["data"]
    monkeypatch.setattr(validate_module, "check_dataset", _eio(str(data)))
    line = one_line_error(invoke("check", data), code=1)
    assert f"input/output error on {data} (errno 5" in line, line
    monkeypatch.undo()
    monkeypatch.setattr(hdf5_module, "read_header", _eio())  # a read that names no file
    line = one_line_error(invoke("info", data), code=1)
    assert line.startswith("Error: input/output error (errno 5"), line


def test_a_checkpoints_folder_that_cannot_be_entered_refuses_the_resume(own_user_files,
                                                                         monkeypatch):
    run = own_user_files["run"]
    before = _files(run)
    if os.geteuid() == 0:  # the superuser enters any folder: as the kernel refuses others
        is_file = pathlib.Path.is_file

        def refused(self):
            if self.parent.name == "checkpoints":
                raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(self))
            return is_file(self)

        monkeypatch.setattr(pathlib.Path, "is_file", refused)
    else:
        (run / "checkpoints").chmod(0o600)
    try:
        line = one_line_error(invoke("train", "--resume", run, "--epochs", 3))
    finally:
        monkeypatch.undo()
        (run / "checkpoints").chmod(0o755)
    assert f"cannot resume {run}: cannot read {run / 'checkpoints' / 'last.pt'}" in line, line
    assert "Permission denied" in line, line
    assert _files(run) == before


def test_an_unreadable_checkpoint_says_permission_denied(own_user_files, monkeypatch):
    last = own_user_files["run"] / "checkpoints" / "last.pt"
    monkeypatch.setattr(checkpoint_module.torch, "load", _denied(last))
    line = one_line_error(invoke("check", last))
    assert f"cannot read {last}: Permission denied" in line, line
    assert "is it a dataset" not in line


def _denied(path):
    def load(*_args, **_kw):
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
    return load
