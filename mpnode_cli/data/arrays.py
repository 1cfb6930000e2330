"""A user's arrays from files: `.npy`, `.npz` and CSV tables, read in one place.

Every reader of a user's array file (`mpnode import`'s states, adjacency and controls,
`mpnode simulate`'s initial states, graphs and controls) comes here, so that each way a
file can be unreadable is one `ValueError` naming it: a missing, empty or truncated file,
text or another format under a numpy suffix, arrays of Python objects, a table that is not
UTF-8 text or has rows of other lengths.

Nothing is unpickled (a pickle runs code as it loads), and no message passes on numpy's
advice to load one with `allow_pickle`. Each `.npy` header (numpy's format, NEP 1) is read
and checked before its data: the bytes it declares must be in the file, and fit this
machine's memory, so a forged or damaged header allocates nothing.
"""

from __future__ import annotations

import math
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from mpnode_cli.data.reads import block_rows

_NPY_MAGIC = b"\x93NUMPY"
_ZIP_MAGIC = b"PK"
# The longest line of a CSV table's header (a column per state: a few hundred characters).
_HEADER_CHARS = 2**20


def read_arrays(path: str | Path, *, mmap: bool = False) -> dict[str, np.ndarray]:
    """The arrays of a `.npy` file (one, named "") or a `.npz` file (by name), whichever the
    file's first bytes say it is.

    Args:
        path: the file.
        mmap: map a `.npy` read-only instead of reading it (`np.load`'s `mmap_mode="r"`),
            for a reader that goes through it a block at a time: it then need not fit in
            memory. A `.npz` is read whole all the same (its members are compressed, or
            may be).

    Raises:
        ValueError: a file that cannot be read as numpy data, holds Python objects, or
            would not fit in memory (one line naming it).
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(len(_NPY_MAGIC))
    except FileNotFoundError:
        raise ValueError(f"no such file: {path}") from None
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror or exc}") from None
    if head.startswith(_NPY_MAGIC):
        with open(path, "rb") as f:
            need = _checked_header(f, path.stat().st_size, str(path))
            if mmap:
                return {"": _mapped(path)}
            _check_memory(need, path)
            f.seek(0)
            return {"": _array(f, str(path))}
    if head.startswith(_ZIP_MAGIC):
        return _read_npz(path)
    what = "is empty" if not head else f"is not numpy data (it starts {head!r})"
    raise ValueError(f"{path} {what}: a .npy or .npz file is written by numpy.save or "
                     "numpy.savez")


def read_table(path: str | Path) -> tuple[list[str], np.ndarray]:
    """A CSV table of numbers under a header row: `(column names, float64 [R, C] rows)`.

    Returns no names for an empty file, and `[0, C]` rows for a header without rows.

    Raises:
        ValueError: a file that cannot be read or is not UTF-8 text, or a row that does
            not hold one number per column (one line naming the file).
    """
    import csv

    from mpnode_cli.textfiles import text_lines

    first = next(text_lines(path, "CSV file", _HEADER_CHARS), None)
    try:
        header = next(csv.reader([first[1]]), []) if first else []
    except csv.Error as exc:
        raise ValueError(f"{path}: the header row does not parse as CSV ({exc})") from None
    columns = [name.strip() for name in header]
    if not columns:
        return [], np.zeros((0, 0))
    if len(columns) == 1 and ";" in columns[0]:  # a spreadsheet's export in some locales
        raise ValueError(f"{path}: its columns are separated by ';', mpnode reads ',' (export "
                         "it as comma-separated CSV, with '.' for decimals)")
    try:
        with warnings.catch_warnings():
            # loadtxt warns of a table without rows, which the caller reports in its words.
            warnings.simplefilter("ignore", UserWarning)
            rows = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, dtype=np.float64,
                              encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise ValueError(f"CSV file {path} is not UTF-8 text (a binary file?)") from None
    except ValueError as exc:
        raise ValueError(f"{path}: every row must hold {len(columns)} numbers "
                         f"({str(exc).splitlines()[0]})") from None
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror or exc}") from None
    if rows.shape[0] == 0:
        rows = np.zeros((0, len(columns)))
    if rows.shape[1] != len(columns):
        raise ValueError(f"{path}: every row must hold {len(columns)} numbers, one per column "
                         f"of the header, but the rows hold {rows.shape[1]}")
    return columns, rows


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    """Every array of a `.npz` (a zip of `.npy` members), all headers checked first."""
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, EOFError):
        raise ValueError(f"{path} is not a readable .npz file (a damaged zip archive)") from None
    with archive:
        members = [info for info in archive.infolist() if not info.is_dir()]
        if not members:
            raise ValueError(f"{path} holds no arrays")
        strangers = [info.filename for info in members if not info.filename.endswith(".npy")]
        if strangers:
            raise ValueError(f"{path} holds {strangers[0]}, which is not an array (an .npz "
                             "written by numpy.savez holds only .npy arrays)")
        names = [info.filename.removesuffix(".npy") for info in members]
        wheres = [f"{path} (array '{name}')" for name in names]
        need = 0
        for info, where in zip(members, wheres, strict=True):
            with _member(archive, info, where) as f:
                need += _checked_header(f, info.file_size, where)
        _check_memory(need, path)
        arrays = {}
        for info, name, where in zip(members, names, wheres, strict=True):
            with _member(archive, info, where) as f:
                arrays[name] = _array(f, where)
        return arrays


def _member(archive: zipfile.ZipFile, info: zipfile.ZipInfo, where: str):
    """One member of an `.npz`, opened (a damaged or encrypted one: a `ValueError`)."""
    try:
        return archive.open(info)
    except Exception as exc:  # BadZipFile, and RuntimeError for encryption
        raise ValueError(f"cannot read {where}: {type(exc).__name__}") from None


def _array(f, where: str) -> np.ndarray:
    """The `.npy` array at the start of `f`, whose header `_checked_header` has passed."""
    try:
        return np.lib.format.read_array(f, allow_pickle=False)
    except MemoryError:
        raise ValueError(f"{where} does not fit in this machine's memory") from None
    except Exception as exc:  # zlib, zip CRC and short reads: the data are damaged
        raise ValueError(f"cannot read {where}: its data are damaged "
                         f"({type(exc).__name__})") from None


def _mapped(path: Path) -> np.ndarray:
    """The `.npy` at `path`, whose header `_checked_header` has passed, mapped read-only."""
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ValueError(f"cannot map {path}: {str(exc).splitlines()[0]}") from None


def _checked_header(f, size: int, where: str) -> int:
    """Read a `.npy` header from `f` and return the bytes of data it declares.

    Args:
        f: a binary file at the start of a `.npy`. size: the bytes of the whole `.npy`.
        where: the file (and array) as messages name it.

    Raises:
        ValueError: a header that does not parse, Python objects, or data that the file
            does not hold.
    """
    try:
        version = np.lib.format.read_magic(f)
        read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                else np.lib.format.read_array_header_2_0)
        shape, _, dtype = read(f)
    except Exception:  # numpy's own words here may advise allow_pickle: not passed on
        raise ValueError(f"{where}: not a .npy header that numpy.save writes (a damaged "
                         "or foreign file?)") from None
    if dtype.hasobject:
        raise ValueError(f"{where} holds Python objects (dtype {dtype}), not numbers; mpnode "
                         "loads no pickled data: save a numeric array")
    need = math.prod(shape) * dtype.itemsize
    have = size - f.tell()
    if need > have:
        raise ValueError(f"{where} is truncated: its header declares shape {list(shape)} "
                         f"of {dtype} ({need:,} bytes), but {max(have, 0):,} bytes follow")
    return need


def _check_memory(need: int, path: Path) -> None:
    """Refuse arrays that would not fit in memory as the float64 copies mpnode reads."""
    from mpnode_cli.memory import available_memory, format_bytes

    have = available_memory()
    if have is not None and need * 3 > have:  # the file's arrays, their float64 copy
        raise ValueError(f"{path} holds {format_bytes(need)} of arrays, more than the "
                         f"memory this machine has available ({format_bytes(have)}) takes "
                         "as float64")


# Values read at a time when scanning for non-finite numbers (float64: 512 MiB).
BLOCK_VALUES = 1 << 26


def nonfinite(array: Any, axes: tuple[str, ...], *, values: int = BLOCK_VALUES,
              progress: Callable[[int, int], None] | None = None) -> str | None:
    """Look for NaN and inf a block of rows (first axis) at a time, so that an array larger
    than memory (an h5py dataset, a memory-mapped `.npy`) can be scanned.

    Args:
        array: `[K, ...]` numbers.
        axes: the name of each axis, for the message.
        values: values per block.
        progress: called after each block with (rows done, K).

    Returns:
        None when every value is finite, else "holds C non-finite value(s) (NaN or inf;
        the first at trajectory k, sample t, ...)".
    """
    k = len(array)
    rows = block_rows(array, values)
    bad, first = 0, None
    for start in range(0, k, rows):
        mask = ~np.isfinite(array[start:start + rows])
        count = int(mask.sum())
        if count and first is None:
            first = tuple(int(i) for i in np.argwhere(mask)[0])
            first = (first[0] + start, *first[1:])
        bad += count
        if progress is not None:
            progress(min(start + rows, k), k)
    if not bad:
        return None
    where = ", ".join(f"{axis} {i}" for axis, i in zip(axes, first, strict=False))
    return (f"holds {bad} non-finite value{'s' * (bad > 1)} (NaN or inf; the first at "
            f"{where})")
