"""A dataset file's own checksums, and what a damaged one reads as.

The one HDF5 writer (`mpnode_cli.data.atomic.atomic_h5`) puts HDF5's Fletcher-32 filter on
every chunk of every array (`create_array`: a changed byte fails its chunk's read, by any
reader) and stores `checksum`, the sha256 of the file as it reads (`contents_sha256`), which
covers what Fletcher-32 does not: the attributes, and HDF5's bookkeeping of where chunks
lie. `mpnode check --deep` verifies both (`deep_problems`); older files read as before.

HDF5 reports damage as `HDF5_ERRORS`, which `damage` makes one line of. Two kinds it does
not report: a zeroed object in a global heap collection (h5py's string attributes) loops it
for ever, and a chunk listed shorter than its Fletcher-32 checksum crashes it; `preflight`,
which every reader runs first, finds them (`Damaged`).
"""

from __future__ import annotations

import hashlib
import io
import os
from collections.abc import Iterator
from typing import Any

import h5py
import numpy as np
from h5py import h5z

from mpnode_cli.data.reads import block_rows, unwritten

CHECKSUM_ATTR = "checksum"
HDF5_ERRORS = (OSError, RuntimeError, KeyError)
# Values per read in a pass over a whole array: memory stays bounded whatever its size.
_BLOCK_VALUES = 4 * 2**20


def create_array(group: h5py.Group, name: str, data: Any = None, **kwargs: Any
                 ) -> h5py.Dataset:
    """`group.create_dataset` with Fletcher-32 on every chunk (h5py chunks the array for
    the filter, which needs chunks); an empty array, with no bytes to damage, has none."""
    shape = np.shape(data) if data is not None else kwargs["shape"]
    filtered = len(shape) > 0 and int(np.prod(shape)) > 0
    return group.create_dataset(name, data=data, fletcher32=filtered, **kwargs)


def blocks(array: h5py.Dataset) -> Iterator[np.ndarray]:
    """The whole of `array`, a block of rows (its first axis) at a time."""
    if array.ndim == 0 or array.size == 0:
        yield array[()]
        return
    rows = block_rows(array, _BLOCK_VALUES)
    for start in range(0, array.shape[0], rows):
        yield array[start:start + rows]


def contents_sha256(f: h5py.File, damaged: list[str] | None = None) -> str:
    """sha256 of everything the file holds as it reads, but its own `checksum` attribute.

    Args:
        f: the open file.
        damaged: when given, every array is read, virtual ones too (so their shards'
            checksums are verified), and each that cannot be read adds its line here
            instead of raising.
    """
    digest = hashlib.sha256()

    def add(name: str, obj: Any) -> None:
        digest.update(_bytes(name) + b"\0")
        for key in sorted(obj.attrs, key=_bytes):  # a damaged name may read as bytes
            if obj.name != "/" or key != CHECKSUM_ATTR:
                digest.update(_bytes(key) + b"\0" + _bytes(obj.attrs[key]) + b"\0")
        if not isinstance(obj, h5py.Dataset):
            return
        digest.update(f"{obj.dtype.str}{obj.shape}".encode())
        if obj.is_virtual:
            digest.update(repr([(m.file_name, m.dset_name, m.vspace.get_select_bounds())
                                for m in obj.virtual_sources()]).encode())
            if damaged is None:
                return
        try:
            for block in blocks(obj):
                if not obj.is_virtual:
                    digest.update(_bytes(block))
        except HDF5_ERRORS as exc:
            if damaged is None:
                raise
            damaged.append(damage(exc, name))

    add("/", f)
    f.visititems(add)
    return digest.hexdigest()


def deep_problems(f: h5py.File) -> list[str]:
    """Read every byte of the file: one line per array that fails (a Fletcher-32 checksum
    or HDF5's bookkeeping), else one if the file's `checksum` is not its contents'."""
    damaged: list[str] = []
    have = contents_sha256(f, damaged)
    stored = f.attrs.get(CHECKSUM_ATTR)
    if damaged or stored is None:
        return damaged
    if stored != have:
        return [f"the file is damaged: its contents are not those written (their sha256 "
                f"{have[:12]}... is not the recorded {str(stored)[:12]}...); restore it from "
                "a copy or write it again"]
    return []


def checksum_summary(f: h5py.File, verified: bool) -> str:
    """What `mpnode check` says of the file's checksums."""
    if CHECKSUM_ATTR not in f.attrs:
        return "none (written before mpnode recorded them)"
    how = "verified" if verified else "recorded (mpnode check --deep verifies every byte)"
    return f"{how}: Fletcher-32 on each array, sha256 of the contents"


class Damaged(OSError):
    """Damage found before HDF5 meets it (`preflight`); its text is the whole line."""


def damage(exc: BaseException, name: str | None = None) -> str:
    """One line for HDF5's error on reading a damaged file, naming the array if known."""
    if isinstance(exc, Damaged):
        return str(exc)
    said = (str(exc).splitlines() or [type(exc).__name__])[0].strip()
    what = f"array {name}" if name else "the file"
    return (f"{what} is damaged: HDF5 cannot read it ({said}); restore the file from a copy "
            "or write it again")


def name_damage(f: h5py.File, exc: BaseException) -> str:
    """`damage` for an error met while reading `f`, naming the first array that fails to
    read where one does (found by reading them all again: this runs only on damage)."""
    damaged: list[str] = []
    try:
        preflight(f.filename)  # reading on through `f` must not meet what hangs HDF5
        contents_sha256(f, damaged)
    except Exception:  # the damage may be where the arrays are listed: unnamed then
        pass
    return damaged[0] if damaged else damage(exc)


def preflight(path: Any) -> None:
    """Read every attribute of the file at `path` through `_Guard` (a global heap that
    would hang HDF5 raises instead), every array's declared size against the file's
    (`reads.unwritten`) and every chunk index (`_chunks`), before any reader reads through
    HDF5 alone: what is left for HDF5 to meet, it reports.

    Raises:
        Damaged, OSError, RuntimeError, KeyError: a damaged file (`HDF5_ERRORS`).
    """
    with _Guard(path) as raw, h5py.File(raw, "r") as f:
        end = os.fstat(raw.fileno()).st_size

        def visit(name: str | bytes, obj: Any) -> None:
            if isinstance(name, bytes):  # h5py's name for one that is not UTF-8 text
                raise Damaged(f"the file is damaged: it holds an object named {name!r}, "
                              "not text; restore the file from a copy or write it again")
            for key in obj.attrs:
                try:
                    obj.attrs[key]
                except (TypeError, ValueError):  # a type h5py does not read: no heap read
                    pass
            if isinstance(obj, h5py.Dataset) and not obj.is_virtual:
                if (line := unwritten(name, obj, end)) is not None:
                    raise Damaged(line)
                if obj.chunks:
                    _chunks(name, obj, end)

        visit("/", f)
        f.visititems(visit)


def _chunks(name: str, array: h5py.Dataset, end: int) -> None:
    """Every chunk the index lists lies in the file, at the size it is written at (its
    values and, with Fletcher-32 alone, 4 bytes of checksum; more than the checksum under
    other filters)."""
    plist = array.id.get_create_plist()
    filters = {plist.get_filter(i)[0] for i in range(plist.get_nfilters())}
    fletcher = 4 * (h5z.FILTER_FLETCHER32 in filters)
    whole = int(np.prod(array.chunks)) * array.dtype.itemsize + fletcher
    exact = filters <= {h5z.FILTER_FLETCHER32}

    def check(info: Any) -> None:
        if (info.size != whole if exact else info.size <= fletcher) or (
                info.byte_offset + info.size > end):
            raise Damaged(f"array {name} is damaged: its index of chunks is broken (it lists "
                          f"{info.size} bytes at byte {info.byte_offset}); restore the file "
                          "from a copy or write it again")

    if hasattr(array.id, "chunk_iter"):  # h5py 3.8 on HDF5 1.14
        array.id.chunk_iter(check)


class _Guard(io.FileIO):
    """A file as h5py's `fileobj` driver reads it, where a global heap collection ("GCOL")
    holding an object of index 0 and size 0 reads without its signature: HDF5 would step
    over that object by its size, 0, for ever (`H5HG__cache_heap_deserialize`)."""

    def readinto(self, buffer: Any) -> int:
        n = super().readinto(buffer)
        view = memoryview(buffer).cast("B")
        if n and n >= 16 and bytes(view[:4]) == b"GCOL" and _endless(bytes(view[:n])):
            view[:4] = b"\0\0\0\0"
        return n


def _endless(chunk: bytes) -> bool:
    """Whether HDF5 would loop decoding this global heap collection (as far as it is read)."""
    end, p = min(int.from_bytes(chunk[8:16], "little"), len(chunk)), 16
    while p + 16 <= end:
        index, size = int.from_bytes(chunk[p:p + 2], "little"), int.from_bytes(
            chunk[p + 8:p + 16], "little")
        step = 16 + (size + 7) // 8 * 8 if index else size
        if step == 0:
            return True
        p += step
    return False


def _bytes(value: Any) -> bytes:
    """An attribute or a block of an array as bytes, the same in every numpy."""
    if isinstance(value, str):
        return value.encode(errors="surrogatepass")
    if isinstance(value, bytes):
        return value
    array = np.asarray(value)
    if array.dtype.kind == "O":  # strings, as h5py reads variable-length ones
        return repr(array.tolist()).encode(errors="surrogatepass")
    return array.dtype.str.encode() + np.ascontiguousarray(array).tobytes()
