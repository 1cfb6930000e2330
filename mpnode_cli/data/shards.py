"""Datasets written in shards (`mpnode generate --shard i/n`) and merged into one file.

A dataset too big to solve in one process, or in one memory, is generated as n shard files
that processes (or machines) write independently, then merged (`merge_shards`):

- **Which trajectories.** `generate` solves trajectories in chunks of `chunk_size`
  (`np.array_split` of 0 … K−1 into C = ⌈K / chunk_size⌉ nearly equal chunks). Shard i of n
  holds the contiguous chunks ⌊iC/n⌋ … ⌊(i+1)C/n⌋ − 1, so n ≤ C. Whole chunks, because
  the batched solver rounds a trajectory differently in different batches (by about 1e-13):
  solving the same batches as the single-file run gives the same bits.
- **The same draws.** Every shard builds all G graphs and draws all K initial states from
  the dataset's generator (cheap next to solving), then keeps its own; the split is drawn
  for all K and sliced. So a shard's trajectories, graphs, parameters and split labels are
  exactly those of the single file.
- **Redraws.** A trajectory that fails or is rejected is redrawn in the single file from
  the dataset's generator after all first draws, which a shard cannot replay (it does not
  know the other shards' failures). A shard redraws from its own generator,
  `default_rng([seed, REDRAW_STREAM, i, n])`, recorded in its `shard` attribute. Shards
  therefore equal the single file exactly when no trajectory needed a redraw, the usual
  case (`n_failed` and `n_rejected` say; the merged file sums them).
- **The file.** A shard is a complete dataset file of its K_i trajectories (all G graphs
  and parameters), whose `config` holds the shard spec and whose `shard` attribute
  (JSON) says where its trajectories lie in the whole: `index`, `count`, `start`, `stop`,
  `trajectories` (K) and `redraw_seed`.

The merged file equals the single-file generation apart from provenance (`created_utc`,
and a `merged` attribute naming the shards); `--virtual` writes an HDF5 virtual dataset
that maps the shards' per-trajectory arrays instead of copying them.
"""

from __future__ import annotations

import itertools
import json
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from mpnode_cli.progress import Progress

SHARD_ATTR = "shard"
MERGED_ATTR = "merged"
# `default_rng([seed, 1])` draws the split; a shard's redraws come from the next stream.
REDRAW_STREAM = 2
# Per-trajectory fields (leading axis K) that a merge concatenates; everything else in a
# shard (time, graphs, parameters) is the whole dataset's and must agree between shards.
_PER_TRAJECTORY = ("states", "controls", "graph_index", "split", "solver/", "hidden/")
# Values per read when copying: about 64 MiB of float64, whatever a trajectory's size.
_BLOCK_VALUES = 8 * 2**20


def chunk_starts(k: int, chunk_size: int) -> list[int]:
    """Where `generate`'s C + 1 solver chunks start (the last entry is K): the chunks of
    `np.array_split(arange(K), C)`, C = ⌈K / chunk_size⌉, the first K mod C one longer."""
    c = math.ceil(k / chunk_size)
    q, r = divmod(k, c)
    return [j * q + min(j, r) for j in range(c + 1)]


def shard_chunks(k: int, chunk_size: int, index: int, count: int) -> slice:
    """The solver chunks of shard `index` of `count` (contiguous, ⌊iC/n⌋ … ⌊(i+1)C/n⌋ − 1).

    Raises:
        ValueError: more shards than chunks (a shard would be empty).
    """
    c = math.ceil(k / chunk_size)
    if count > c:
        raise ValueError(
            f"{count} shards of {k} trajectories solved {chunk_size} at a time: a shard holds "
            f"whole solver chunks and there are only {c}; use at most {c} shards or a "
            f"--chunk-size of at most {k // count}")
    return slice(index * c // count, (index + 1) * c // count)


def shard_range(k: int, chunk_size: int, index: int, count: int) -> tuple[int, int]:
    """`(start, stop)`: the trajectories of shard `index` of `count` in the whole dataset."""
    chunks, starts = shard_chunks(k, chunk_size, index, count), chunk_starts(k, chunk_size)
    return starts[chunks.start], starts[chunks.stop]


def shard_path(out: str | Path, index: int, count: int) -> Path:
    """`datasets/x.h5` → `datasets/x.shard-0003-of-0008.h5` (shard 3 of 8)."""
    out = Path(out)
    suffix = out.suffix or ".h5"
    return out.with_name(f"{out.stem if out.suffix else out.name}.shard-{index:04d}-of-"
                         f"{count:04d}{suffix}")


def redraw_seed(seed: int, index: int, count: int) -> list[int]:
    """The seed sequence of shard `index`'s redraws: `[seed, REDRAW_STREAM, index, count]`."""
    return [seed, REDRAW_STREAM, index, count]


def shard_attribute(k: int, chunk_size: int, seed: int, index: int, count: int) -> str:
    """The `shard` root attribute (JSON) of shard `index` of `count`."""
    start, stop = shard_range(k, chunk_size, index, count)
    return json.dumps({"index": index, "count": count, "start": start, "stop": stop,
                       "trajectories": k, "redraw_seed": redraw_seed(seed, index, count)})


@dataclass(frozen=True)
class MergeSummary:
    """What `merge_shards` wrote.

    Attributes:
        path: the merged file. shards: n. trajectories: K. virtual: a virtual dataset
        (the shards stay in use). redrawn: trajectories the shards redrew (when > 0 the file
        differs from a single-file generation in those trajectories). bytes: the size of
        the per-trajectory arrays.
    """

    path: Path
    shards: int
    trajectories: int
    virtual: bool
    redrawn: int
    bytes: int


def merge_shards(paths: list[str | Path], out: str | Path, *, overwrite: bool = False,
                 virtual: bool = False, progress: Progress | None = None) -> MergeSummary:
    """Merge the shard files of one dataset into one dataset file, atomically.

    The per-trajectory arrays are copied a block of trajectories at a time (about 64 MiB),
    so memory stays bounded whatever the dataset's size; with `virtual` they are mapped
    instead (an HDF5 virtual dataset whose sources are the shard files, by their paths
    relative to the merged file's folder; every reader refuses the file, naming the shard,
    once a shard is moved or deleted: `mpnode_cli.data.virtual.virtual_source_problems`).

    Args:
        paths: every shard of the dataset, once each, in any order.
        out: the merged file.
        overwrite: replace an existing regular file at `out`.
        virtual: map instead of copying.
        progress: called as `progress(values done, values in all)` after each block.

    Raises:
        ValueError: files that are not shards of one dataset (one line saying why), or an
            output path that cannot be written or is one of the shards
            (`mpnode_cli.paths.reserve_output`).
        FileExistsError: `out` exists and `overwrite` is False.
        KeyboardInterrupt: SIGINT or SIGTERM; nothing is left at `out`.
    """
    import h5py

    from mpnode_cli.data.atomic import atomic_h5
    from mpnode_cli.paths import reserve_output

    out = Path(out)
    shards = _check_shards([Path(p) for p in paths])
    k = shards[0].info["trajectories"]
    with reserve_output(out, overwrite=overwrite, inputs=[s.path for s in shards]), \
            h5py.File(shards[0].path, "r") as first:
        per_trajectory = _per_trajectory_names(first)
        total = sum(int(np.prod(first[name].shape[1:])) * k for name in per_trajectory)
        nbytes = sum(int(np.prod(first[name].shape[1:])) * k * first[name].dtype.itemsize
                     for name in per_trajectory)
        with atomic_h5(out, overwrite=True) as (f, check):  # over the reservation
            f.attrs.update(_merged_attrs(shards, out, virtual))
            _copy_shared(first, f, shards, check)
            done = 0
            for name in per_trajectory:
                if virtual:
                    _map(f, name, first[name], shards, out)
                    done += int(np.prod(first[name].shape[1:])) * k
                    if progress is not None:
                        progress(done, total)
                    continue
                done = _copy(f, name, first[name], shards, check, progress, done, total)
                check()
    redrawn = sum(s.redrawn for s in shards)
    return MergeSummary(path=out, shards=len(shards), trajectories=k, virtual=virtual,
                        redrawn=redrawn, bytes=nbytes)


@dataclass(frozen=True)
class _Shard:
    path: Path
    info: dict[str, Any]  # the `shard` attribute
    attrs: dict[str, Any]  # every root attribute, as Python values
    config: dict[str, Any]  # the stored config, without `shard` and `out`
    redrawn: int


def _check_shards(paths: list[Path]) -> list[_Shard]:
    """The shards in order, after checking that they are all the shards of one dataset."""
    if not paths:
        raise ValueError("give the shard files to merge")
    shards = [_read_shard(path) for path in paths]
    first = shards[0]
    for s in shards[1:]:
        for key, what in (("format_version", "format version"),
                          ("mpnode_version", "mpnode version")):
            if s.attrs.get(key) != first.attrs.get(key):
                raise ValueError(f"{s.path.name} and {first.path.name} differ in {what} "
                                 f"({s.attrs.get(key)} and {first.attrs.get(key)}): "
                                 "regenerate the shards with one mpnode")
        if s.config != first.config:
            key = next(k for k in sorted(set(s.config) | set(first.config))
                       if s.config.get(k) != first.config.get(k))
            raise ValueError(f"{s.path.name} and {first.path.name} are shards of different "
                             f"datasets: their configs differ in '{key}' "
                             f"({s.config.get(key)!r} and {first.config.get(key)!r})")
    return _in_order(shards)


def _read_shard(path: Path) -> _Shard:
    """One shard file's attributes, shard record and config (less what may differ between
    shards), checked against its trajectory count, once the file passes the dataset check
    every reader runs (`mpnode_cli.data.validate.require_valid`)."""
    from mpnode_cli.data.hdf5 import open_dataset
    from mpnode_cli.data.validate import require_valid

    if not path.is_file():
        raise ValueError(f"no such shard file: {path}")
    require_valid(path)
    with open_dataset(path) as f:
        attrs = dict(f.attrs)  # as stored, to be written again as they are
        k = f["states"].shape[0]
    if SHARD_ATTR not in attrs:
        raise ValueError(f"{path} is not a shard (no '{SHARD_ATTR}' attribute): merge "
                         "takes the files that mpnode generate --shard i/n writes")
    info = json.loads(attrs[SHARD_ATTR])
    config = json.loads(attrs["config"])
    # Which shard, and where each was written (per machine, perhaps), may differ.
    config.pop(SHARD_ATTR, None)
    config.pop("out", None)
    if k != info["stop"] - info["start"]:
        raise ValueError(f"{path} holds {k} trajectories but its shard attribute says "
                         f"{info['stop'] - info['start']}")
    redrawn = int(attrs.get("n_failed", 0)) + int(attrs.get("n_rejected", 0))
    return _Shard(path, info, attrs, config, redrawn)


def _in_order(shards: list[_Shard]) -> list[_Shard]:
    """The shards of one dataset by index: each once, none missing, their trajectory
    ranges tiling the dataset."""
    first = shards[0]
    count = first.info["count"]
    by_index: dict[int, _Shard] = {}
    for s in shards:
        if s.info["count"] != count:
            raise ValueError(f"{s.path.name} is one of {s.info['count']} shards but "
                             f"{first.path.name} one of {count}")
        if s.info["index"] in by_index:
            raise ValueError(f"shard {s.info['index']} of {count} given twice: "
                             f"{by_index[s.info['index']].path} and {s.path}")
        by_index[s.info["index"]] = s
    missing = sorted(set(range(count)) - set(by_index))
    if missing:
        shown = ", ".join(str(i) for i in missing[:8]) + (" ..." if len(missing) > 8 else "")
        raise ValueError(f"{len(missing)} of {count} shards missing (index {shown}): merge "
                         "needs every shard of the dataset")
    ordered = [by_index[i] for i in range(count)]
    if ordered[0].info["start"] != 0 or ordered[-1].info["stop"] != first.info[
            "trajectories"] or any(a.info["stop"] != b.info["start"]
                                   for a, b in itertools.pairwise(ordered)):
        raise ValueError("the shards' trajectory ranges do not tile the dataset")
    return ordered


def _per_trajectory_names(f) -> list[str]:
    import h5py

    names: list[str] = []
    f.visititems(lambda name, obj: names.append(name) if isinstance(obj, h5py.Dataset)
                 and name.startswith(_PER_TRAJECTORY) else None)
    return names


def _merged_attrs(shards: list[_Shard], out: Path, virtual: bool) -> dict[str, Any]:
    """Root attributes of the merged file: the shards' own, as the single file has them;
    a virtual merge records each shard's checksum by the name it maps it by
    (`mpnode_cli.data.virtual`: a shard replaced since is refused)."""
    from mpnode_cli.data.integrity import CHECKSUM_ATTR

    attrs = {k: v for k, v in shards[0].attrs.items() if k != SHARD_ATTR}
    # Where the file lies, as `generate --out` records it; the rest is the shards' config.
    attrs["config"] = json.dumps({**shards[0].config, "out": str(out)}, sort_keys=True)
    attrs["created_utc"] = datetime.now(UTC).isoformat(timespec="seconds")
    for key in ("n_failed", "n_rejected"):
        if key in attrs:
            attrs[key] = sum(int(s.attrs[key]) for s in shards)
    attrs[MERGED_ATTR] = json.dumps({
        "shards": [s.path.name for s in shards],
        "created_utc": [s.attrs.get("created_utc") for s in shards],
        "redrawn": sum(s.redrawn for s in shards),
        **({"sources": {_source_name(s, out): s.attrs[CHECKSUM_ATTR] for s in shards
                        if CHECKSUM_ATTR in s.attrs}} if virtual else {})})
    return attrs


def _source_name(shard: _Shard, out: Path) -> str:
    """The name a virtual merge at `out` gives `shard` (relative to its folder)."""
    return os.path.relpath(shard.path.resolve(), out.resolve().parent)


def _copy_shared(first, f, shards: list[_Shard], check: Callable[[], None]) -> None:
    """Copy what every shard holds whole (time, graphs, parameters), after checking that
    the shards agree on it."""
    import h5py

    from mpnode_cli.data.hdf5 import open_dataset

    shared: list[str] = []
    first.visititems(lambda name, obj: shared.append(name) if isinstance(obj, h5py.Dataset)
                     and not name.startswith(_PER_TRAJECTORY) else None)
    for s in shards[1:]:
        with open_dataset(s.path) as other:
            for name in shared:
                if name not in other or not np.array_equal(other[name][()], first[name][()]):
                    raise ValueError(f"{s.path.name} and {shards[0].path.name} differ in "
                                     f"'{name}': they are not shards of one dataset")
    for name in shared:
        parent = name.rpartition("/")[0]
        first.copy(first[name], f.require_group(parent) if parent else f, name.split("/")[-1])
        check()
    for group in ("params", "graph", "solver", "hidden"):  # group attributes (scalar params)
        if group in first:
            f.require_group(group).attrs.update(dict(first[group].attrs))


def _copy(f, name: str, src, shards: list[_Shard], check, progress: Progress | None,
          done: int, total: int) -> int:
    """Concatenate the shards' `name` into `f`, a block of trajectories at a time."""
    from mpnode_cli.data.hdf5 import open_dataset
    from mpnode_cli.data.integrity import create_array

    k = shards[-1].info["stop"]
    row = int(np.prod(src.shape[1:]))
    dst = create_array(f, name, shape=(k, *src.shape[1:]), dtype=src.dtype, chunks=src.chunks,
                       compression=src.compression, compression_opts=src.compression_opts)
    dst.attrs.update(dict(src.attrs))
    rows = max(1, _BLOCK_VALUES // max(row, 1))
    for s in shards:
        with open_dataset(s.path) as shard:
            part = shard[name]
            for a in range(0, len(part), rows):
                b = min(a + rows, len(part))
                dst[s.info["start"] + a:s.info["start"] + b] = part[a:b]
                done += (b - a) * row
                check()
                if progress is not None:
                    progress(done, total)
    return done


def _map(f, name: str, src, shards: list[_Shard], out: Path) -> None:
    """`name` as a virtual dataset over the shards'. HDF5 reads a shard it cannot open as
    the fill value (NaN, or the largest integer); readers check the shards first
    (`mpnode_cli.data.virtual.virtual_source_problems`), so the fill value is a second line
    of defence."""
    import h5py

    k = shards[-1].info["stop"]
    layout = h5py.VirtualLayout(shape=(k, *src.shape[1:]), dtype=src.dtype)
    for s in shards:
        rows = s.info["stop"] - s.info["start"]
        layout[s.info["start"]:s.info["stop"]] = h5py.VirtualSource(
            _source_name(s, out), name, shape=(rows, *src.shape[1:]))
    fill = np.nan if src.dtype.kind == "f" else np.iinfo(src.dtype).max
    f.create_virtual_dataset(name, layout, fillvalue=fill)
    f[name].attrs.update(dict(src.attrs))
