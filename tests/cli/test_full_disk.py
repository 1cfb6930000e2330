"""A full disk: one line naming the file, the space the write needed and the space the disk
had, exit 2, and nothing left behind.

Once, `generate` onto a full disk crashed (a segfault: HDF5 fails as it closes a file whose
write failed), and `train`, `import`, `simulate`, `merge` and `check --member --out` ended
in tracebacks, torch's saying "unexpected pos 128 vs 0". Now HDF5 and torch never meet
the full disk themselves (`mpnode_cli.data.atomic`), and `generate` compares its file's
estimated size with the free space before it solves anything.

Where a small tmpfs can be mounted (root), the verbs run against a real full disk; the
rest simulate one with a file that refuses bytes past a limit.
"""

from __future__ import annotations

import errno
import io
import os
import shutil
import subprocess

import pytest
from conftest import invoke, one_line_error

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data import atomic
from mpnode_cli.data import generate as generate_module
from mpnode_cli.data import size as size_module
from mpnode_cli.data.generate import generate
from mpnode_cli.data.hdf5 import read_dataset
from mpnode_cli.data.hdf5_write import write_dataset
from mpnode_cli.paths import OutputError
from mpnode_cli.training import run as run_module
from mpnode_cli.training.checkpoint import load_checkpoint, save_checkpoint


@pytest.fixture
def full(tmp_path):
    """A 1 MiB tmpfs for this test, to fill (skipped where it cannot be mounted)."""
    mount = tmp_path / "full"
    mount.mkdir()
    try:
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mount)],
                              capture_output=True).returncode == 0
    except OSError:
        done = False
    if not done:
        pytest.skip("a tmpfs cannot be mounted here (it needs root)")
    yield mount
    subprocess.run(["umount", str(mount)], check=False)


def fill(folder) -> None:
    with open(folder / "fill", "wb", buffering=0) as f:
        try:
            while True:
                f.write(bytes(65536))
        except OSError as exc:
            assert exc.errno == errno.ENOSPC


def test_a_generate_too_big_for_the_disk_is_refused_before_solving(full):
    line = one_line_error(invoke("generate", "lorenz", "--nodes", 5, "--trajectories", 400,
                                 "--t-end", 2, "--dt", 0.01, "--out", full / "big.h5"))
    assert "needs about 4.6 MiB on disk" in line and "1 MiB free" in line, line
    assert not list(full.iterdir())


def test_writers_on_a_full_disk_say_so_in_one_line(full, user_files):
    fill(full)
    files = user_files
    for out, args in (
            ("i.h5", ["import", "--states", files["states"], "--adjacency", files["adjacency"],
                      "--dt", 0.1]),
            ("s.h5", ["simulate", files["checkpoint"], "--x0", files["x0"], "--edge-list",
                      files["edges"], "--t-end", 0.5, "--dt", 0.1]),
            ("p.h5", ["evaluate", files["checkpoint"], files["data"], "--save-predictions"]),
            ("run", ["train", files["data"], "--epochs", 1, "--no-plots", "--run-dir"])):
        flag = [] if args[-1] in ("--save-predictions", "--run-dir") else ["--out"]
        line = one_line_error(invoke(*args, *flag, full / out))
        assert f"no space left on device writing {full / out}" in line, line
        assert "(nothing was written)" in line and "the disk had 0 B free" in line, line
        assert [p.name for p in full.iterdir()] == ["fill"]


class _FullAfter(io.FileIO):
    """A file on a disk with `room` bytes free."""

    room = 3000

    def write(self, data) -> int:
        room = self.room - self.tell()
        if room <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return super().write(memoryview(data).cast("B")[:room])


def full_open(file, mode="r", buffering=-1, **_):
    raw = _FullAfter(file, mode.replace("b", ""))
    if buffering == 0:
        return raw
    return (io.BufferedRandom if "+" in mode else io.BufferedWriter)(raw)


def test_a_dataset_or_checkpoint_the_disk_cannot_take_leaves_nothing(user_files, tmp_path,
                                                                     monkeypatch):
    ds, ckpt = read_dataset(user_files["data"]), load_checkpoint(user_files["checkpoint"])
    monkeypatch.setattr(atomic, "open", full_open, raising=False)
    with pytest.raises(OutputError, match=r"no space left on device writing .*d\.h5: it "
                                          r"needed more than [0-9.]+ KiB, the disk had"):
        write_dataset(tmp_path / "d.h5", ds)
    with pytest.raises(OutputError, match=r"writing .*c\.pt: it needed [0-9.]+ KiB, the disk"):
        save_checkpoint(tmp_path / "c.pt", ckpt)
    assert not list(tmp_path.iterdir())


def test_generate_compares_its_file_with_the_free_space_first(tmp_path, monkeypatch):
    monkeypatch.setattr(size_module.shutil, "disk_usage",
                        lambda _: shutil._ntuple_diskusage(10**9, 10**9 - 1000, 1000))

    def solve(*_):
        raise AssertionError("solved before the disk was checked")

    monkeypatch.setattr(generate_module, "solve_and_redraw", solve)
    with pytest.raises(ValueError, match=r"needs about .* on disk, more than the 1000 B free"):
        generate(GenerateConfig(system="lorenz", nodes=3, trajectories=8, t_end=0.2, dt=0.05,
                                out=tmp_path / "d.h5"))
    assert not list(tmp_path.iterdir())


def test_a_metrics_row_cut_short_by_a_full_disk_is_taken_back(tmp_path, monkeypatch):
    path = tmp_path / "metrics.jsonl"
    path.write_text('{"epoch": 0}\n' * 200)  # 2600 bytes: room for a part of the next row
    monkeypatch.setattr(run_module, "open", full_open, raising=False)
    with pytest.raises(OSError) as caught:
        run_module.append_metrics(tmp_path, {"epoch": 1, "train_loss": 0.5, "note": "x" * 600})
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(path)
    assert path.read_text() == '{"epoch": 0}\n' * 200
