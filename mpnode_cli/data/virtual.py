"""The source files of a virtual merge (`mpnode merge --virtual`): whether they are still
where the merged file reads them from, still hold what it maps, and are still the files it
merged: the merge records each shard's `checksum` (`mpnode_cli.data.integrity`, the sha256
of its contents) in its `merged` attribute, which a shard replaced by another no longer
carries, while a copy of the folder still does.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import h5py


def virtual_source_problems(f: h5py.File) -> list[str]:
    """What is wrong with the source files of the file's virtual datasets (`mpnode merge
    --virtual`'s shards): one line naming those HDF5 cannot open and where they belong, and
    one per file that no longer holds the arrays mapped from it.

    HDF5 reads a source it cannot open as the fill value, without a word (its VDS
    documentation: "If a source file is missing the fill value will be displayed"), so a
    moved or deleted shard would read as NaN and out-of-range indices; every reader asks
    here first. A source is looked for as HDF5 does (`H5F_prefix_open_file`): an absolute
    name as given, then the file name under `HDF5_VDS_PREFIX`, in the virtual file's
    folder, and relative to the working directory.
    """
    # file → (dataset, the block's shape); the block is read from the virtual side's
    # selection, since HDF5 hands back a source selection of "all" without its extent.
    sources: dict[str, list[tuple[str, tuple[int, ...]]]] = {}

    def visit(name: str, obj: Any) -> None:
        if isinstance(obj, h5py.Dataset) and obj.is_virtual:
            for m in obj.virtual_sources():
                if m.file_name != ".":  # "." maps the virtual file itself
                    lo, hi = m.vspace.get_select_bounds()
                    block = tuple(b - a + 1 for a, b in zip(lo, hi, strict=True))
                    sources.setdefault(m.file_name, []).append((m.dset_name, block))

    f.visititems(visit)
    problems, missing, recorded = [], [], _recorded(f)
    for file_name, mapped in sources.items():
        candidates = _source_candidates(file_name, Path(f.filename))
        found = next((c for c in candidates if _readable_hdf5(c)), None)
        if found is None:
            missing.append(candidates[0])
            continue
        with h5py.File(found, "r") as source:
            if recorded.get(file_name, source.attrs.get("checksum")) != source.attrs.get(
                    "checksum"):
                problems.append(f"its shard {found} is not the file it merged (its checksum "
                                "differs: replaced or rewritten since); merge the shards again")
                continue
            for dset, shape in mapped:
                have = source[dset].shape if isinstance(source.get(dset), h5py.Dataset) else None
                if have is None or len(have) != len(shape) or any(
                        h < w for h, w in zip(have, shape, strict=True)):
                    problems.append(f"its shard {found} does not hold the {dset} {list(shape)} "
                                    f"this virtual merge reads from it (it holds {have}): "
                                    "the shard was replaced after the merge; merge again")
                    break
    if missing:  # one line, however many: a folder moved loses every shard at once
        shown = ", ".join(str(p) for p in missing[:3]) + (" ..." if len(missing) > 3 else "")
        what = (f"its shard {shown} is" if len(missing) == 1 else
                f"{len(missing)} of its {len(sources)} shards ({shown}) are")
        them = "it" if len(missing) == 1 else "them"
        problems.insert(0, f"{what} missing or unreadable: this file is a virtual merge (mpnode "
                           "merge --virtual) that reads its trajectories from the shards where "
                           f"they were; put {them} back there, or merge the shards again")
    return problems


def _recorded(f: h5py.File) -> dict[str, str]:
    """Each shard's checksum at the merge, by its name (none in a merge before they were)."""
    try:
        sources = json.loads(f.attrs.get("merged", "{}")).get("sources", {})
    except (ValueError, TypeError, AttributeError):
        return {}
    return sources if isinstance(sources, dict) else {}


def _source_candidates(name: str, virtual_file: Path) -> list[Path]:
    """Where HDF5 looks for the virtual source file `name`, in its order."""
    path = Path(name)
    relative = Path(path.name) if path.is_absolute() else path
    origin = str(virtual_file.resolve().parent)
    prefixes = [p.replace("${ORIGIN}", origin)
                for p in os.environ.get("HDF5_VDS_PREFIX", "").split(os.pathsep) if p]
    return [*([path] if path.is_absolute() else []),
            *(Path(p) / relative for p in prefixes), Path(origin) / relative, relative]


def _readable_hdf5(path: Path) -> bool:
    if not path.is_file():
        return False
    from mpnode_cli.data.integrity import HDF5_ERRORS, preflight

    try:
        with h5py.File(path, "r"):
            preflight(path)
            return True
    except HDF5_ERRORS:
        return False
