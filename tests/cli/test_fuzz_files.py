"""Damaged files, at random: zeroed blocks and flipped bytes over a small dataset and a
small checkpoint (fixed seeds). `mpnode check --deep` must answer each in one line or pass
it, never with a traceback (nor a hang or a crash: HDF5 loops for ever on a zeroed global
heap object and crashes on a chunk shorter than its checksum), and a file that passes must
read exactly as the undamaged one: a changed value is always caught (the dataset's
Fletcher-32 and contents checksum, the checkpoint's digest), while damage to space the file
does not use may pass.

The cases run in one child process, so that a crash fails this test instead of the run.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import child_env

CASES = 50  # of each kind, for each file
SEEDS = {"dataset": 11, "checkpoint": 12}


def damaged(original: bytes, kind: str, rng: np.random.Generator) -> bytes:
    """`original` with 512 bytes zeroed, or one byte changed, at a random place."""
    data = bytearray(original)
    at = int(rng.integers(0, len(data)))
    if kind == "zero":
        data[at:at + 512] = bytes(len(data[at:at + 512]))
    else:
        data[at] ^= int(rng.integers(1, 256))
    return bytes(data)


def dataset_contents(path: Path) -> dict:
    """Every attribute and array of an HDF5 file, as h5py reads them."""
    import h5py

    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            out[f"{name}@"] = {k: np.asarray(v).tobytes() if not isinstance(v, str) else v
                               for k, v in obj.attrs.items()}
            if isinstance(obj, h5py.Dataset):
                out[name] = (obj.dtype.str, obj.shape, obj[()].tobytes())

        visit("/", f)
        f.visititems(visit)
    return out


def checkpoint_contents(path: Path):
    import torch

    return torch.load(path, map_location="cpu", weights_only=True)


def same(a, b) -> bool:
    import torch

    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b)
    if isinstance(a, dict):
        return (isinstance(b, dict) and list(a) == list(b)
                and all(same(a[k], b[k]) for k in a))
    if isinstance(a, list | tuple):
        return type(a) is type(b) and len(a) == len(b) and all(map(same, a, b))
    return type(a) is type(b) and a == b


def run_cases(file: str, what: str, work: str) -> dict:
    """Damage `file` CASES times each way and `mpnode check --deep` each copy, in this
    process: the counts of each outcome, and what went wrong."""
    from typer.testing import CliRunner

    from mpnode_cli.cli.app import app

    path, work = Path(file), Path(work)
    original = path.read_bytes()
    contents = dataset_contents if what == "dataset" else checkpoint_contents
    want = contents(path)
    rng = np.random.default_rng(SEEDS[what])
    counts, wrong = {"refused": 0, "passed": 0}, []
    cases = [(kind, i) for kind in ("zero", "flip") for i in range(CASES)]
    for kind, i in cases:
        data = original
        while data == original:  # zeros over zeros damage nothing: draw again
            data = damaged(original, kind, rng)
        case = work / f"{kind}{i}{path.suffix}"
        case.write_bytes(data)
        result = CliRunner().invoke(app, ["check", "--deep", str(case)])
        errors = [line for line in result.output.splitlines() if line.startswith("Error:")]
        if result.exit_code == 2 and errors and "Traceback" not in result.output:
            counts["refused"] += 1
        elif result.exit_code == 0 and not errors:
            counts["passed"] += 1
            try:
                intact = same(contents(case), want)
            except Exception as exc:  # passed check, yet does not read
                intact = exc
            if intact is not True:
                wrong.append(f"{case.name} passed check but reads otherwise ({intact!r})")
        else:
            wrong.append(f"{case.name}: exit {result.exit_code}: {result.output[-600:]}"
                         f" {result.exception!r}")
    return {"counts": counts, "wrong": wrong}


_CHILD = """
import json, sys
sys.path[:0] = [sys.argv[1], sys.argv[1].rsplit("/", 1)[0]]  # this file, conftest
from test_fuzz_files import run_cases
print(json.dumps(run_cases(*sys.argv[2:])))
"""


@pytest.fixture(scope="module")
def files(tiny_checkpoint) -> dict[str, Path]:
    """A small dataset (8 Lorenz trajectories of 3 nodes, 44 KB) and the checkpoint of a
    model trained on it for one epoch (38 KB)."""
    return {"dataset": tiny_checkpoint.parents[2] / "l3.h5", "checkpoint": tiny_checkpoint}


@pytest.mark.parametrize("what", ["dataset", "checkpoint"])
def test_damaged_files_are_refused_in_one_line_or_read_as_written(files, what, tmp_path):
    proc = subprocess.run(
        [sys.executable, "-c", _CHILD, str(Path(__file__).resolve().parent), str(files[what]), what,
         str(tmp_path)], capture_output=True, text=True, timeout=120, env=child_env())
    assert proc.returncode == 0, proc.stderr[-3000:]  # no crash, no traceback
    found = json.loads(proc.stdout.splitlines()[-1])
    counts = found["counts"]
    assert not found["wrong"], found["wrong"]
    assert sum(counts.values()) == 2 * CASES
    # Most damage lands in values (the dataset's arrays, the checkpoint's tensors): refused.
    assert counts["refused"] >= CASES // 2, counts
    print(what, counts)
