"""A fixed-seed contract of mpnode's numbers: a guard for refactors that must change none.

`record OUT.json` runs the CLI in this process on tiny problems (a few generated datasets,
every registered model, an ensemble, a resumed run, a finetune, an evaluation) and writes
what they produced: per-epoch train and validation losses, gradient norms and RHS
evaluation counts (the run's `metrics.jsonl`), the run's summary numbers, a SHA-256 of
every weight tensor's bytes, and a SHA-256 of every array of every dataset written.
`compare OUT.json` records again and compares: the float64 section must be identical to
the bit (exit 1 otherwise); the float32 section lists what moved and by how much (relative
difference) without failing. tools/README.md says how a refactor uses it.

It is a guard, not a test of correctness: a number that is wrong today is recorded as it
is, and the suite lives outside `tests/`.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import json
import math
import os
import platform
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

FORMAT = "mpnode-contract"
VERSION = 1
SECTIONS = ("float64", "float32")
# Wall times change from run to run, and so does a hash of a file that holds the paths of
# the temporary folder (a finetune's parent checkpoint); they are not part of the contract.
_VOLATILE = {"parent_sha256", "created_utc"}
_WORK = "<work>"  # what the temporary folder's path reads as in the record
_TINY = 1e-300

# Model kinds and the options that keep them tiny. The registry's every kind must appear
# here (`_check_registry` refuses a record that would leave one out).
MODELS: dict[str, list[str]] = {
    "mpnode-default": ["--model", "mpnode", "--hidden", "8"],
    "mpnode-paper": ["--model", "mpnode", "--hidden", "8", "--update", "mlp",
                     "--aggregate", "mean", "--periodic", "off"],
    "mpnode-options": ["--model", "mpnode", "--hidden", "8", "--aggregate", "pna",
                       "--periodic", "embed", "--backend", "scatter", "--message-init", "zero"],
    "node": ["--model", "node", "--hidden", "8"],
    "gnode": ["--model", "gnode", "--hidden", "8"],
    "l2s": ["--model", "l2s", "--hidden", "8", "--latent", "8", "--steps", "2"],
}
DATASETS: dict[str, list[str]] = {
    "pendulum-chain": ["pendulum", "--nodes", "3", "--topology", "chain", "--trajectories",
                       "10", "--t-end", "1", "--dt", "0.1", "--seed", "0"],
    "pendulum-chain5": ["pendulum", "--nodes", "5", "--topology", "chain",
                          "--trajectories", "8", "--t-end", "1", "--dt", "0.1", "--seed", "1"],
    "kuramoto-ba": ["kuramoto", "--nodes", "6", "--topology", "ba", "--graphs", "2", "--split",
                    "0.5,0.25,0.25",
                    "--trajectories", "4", "--t-end", "1", "--dt", "0.1", "--seed", "2"],
    "lorenz-complete": ["lorenz", "--nodes", "3", "--topology", "complete", "--trajectories",
                        "4", "--t-end", "0.5", "--dt", "0.05", "--seed", "3", "--method",
                        "dopri5", "--split", "0.5,0.25,0.25"],
    "gene-grid": ["gene", "--grid", "3", "--trajectories", "6", "--t-end", "1", "--dt", "0.1",
                  "--seed", "4"],
    "sis-s1": ["sis", "--nodes", "12", "-p", "mean_degree=3", "--trajectories", "6",
               "--t-end", "1", "--dt", "0.1", "--seed", "5", "--fixed-dt", "0.05",
               "--method", "rk4"],
}
TRAIN = ["--batch-size", "4", "--stop-patience", "1000", "--no-plots", "--threads", "1",
         "--seed", "0"]
EPOCHS = 3


def cli(args: list[str]) -> str:
    """Run `mpnode ARGS` in this process and return its stdout.

    Raises:
        RuntimeError: the command exited with a non-zero code.
    """
    from mpnode_cli.cli.app import app

    out, err = io.StringIO(), io.StringIO()
    code: Any = 0
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            # Without standalone mode, click returns an `Exit`'s code instead of exiting.
            code = app([str(a) for a in args], prog_name="mpnode", standalone_mode=False)
        except SystemExit as exc:
            code = exc.code
    if code not in (0, None):
        raise RuntimeError(f"mpnode {' '.join(map(str, args))} exited {code}:\n"
                           f"{err.getvalue()[-2000:]}")
    return out.getvalue()


def _clean(value: Any, work: Path) -> Any:
    """`value` without wall times (keys named `*seconds*` or in `_VOLATILE`), the temporary
    folder `work` in its strings replaced by `_WORK`."""
    if isinstance(value, dict):
        return {k: _clean(v, work) for k, v in value.items()
                if "seconds" not in k and k not in _VOLATILE}
    if isinstance(value, list):
        return [_clean(v, work) for v in value]
    if isinstance(value, str):
        return value.replace(str(work), _WORK)
    return value


def _tensor_record(tensor: Any) -> dict[str, Any]:
    import torch

    t = tensor.detach().cpu().contiguous()
    norm = float(torch.linalg.vector_norm(t.to(torch.float64))) if t.is_floating_point() \
        else float(t.to(torch.float64).abs().sum())
    return {"sha256": hashlib.sha256(t.numpy().tobytes()).hexdigest(),
            "dtype": str(t.dtype), "shape": list(t.shape), "norm": norm}


def weights(checkpoint: Path) -> dict[str, Any]:
    """SHA-256 (and norm, shape, dtype) of every tensor of a checkpoint's `state_dict`."""
    import torch

    state = torch.load(checkpoint, map_location="cpu", weights_only=False)["state_dict"]
    return {name: _tensor_record(t) for name, t in sorted(state.items())}


def dataset_arrays(path: Path) -> dict[str, Any]:
    """SHA-256 (and shape, dtype, sum) of every array in an HDF5 dataset file."""
    import h5py
    import numpy as np

    found: dict[str, Any] = {}

    def visit(name: str, obj: Any) -> None:
        if isinstance(obj, h5py.Dataset):
            a = np.ascontiguousarray(obj[()])
            total = float(np.sum(a, dtype=np.float64)) if a.dtype.kind in "fiub" else None
            found[name] = {"sha256": hashlib.sha256(a.tobytes()).hexdigest(),
                           "dtype": str(a.dtype), "shape": list(a.shape), "sum": total}

    with h5py.File(path, "r") as f:
        f.visititems(visit)
    return dict(sorted(found.items()))


def run_record(run: Path, work: Path) -> dict[str, Any]:
    """A run folder's per-epoch metrics, summary and final (last) and best weights."""
    lines = (run / "metrics.jsonl").read_text().splitlines()
    summary = json.loads((run / "summary.json").read_text())
    return {"epochs": [_clean(json.loads(line), work) for line in lines if line.strip()],
            "summary": _clean(summary, work),
            "weights_last": weights(run / "checkpoints" / "last.pt"),
            "weights_best": weights(run / "checkpoints" / "best.pt")}


def _generate(work: Path, progress: Any) -> dict[str, Any]:
    """Generate every dataset of `DATASETS` (float64 storage) into `work`."""
    record = {}
    for name, args in DATASETS.items():
        progress(f"generate {name}")
        out = work / f"{name}.h5"
        summary = json.loads(cli(["generate", *args, "--dtype", "float64", "-o", out,
                                  "--threads", "1", "--json"]))
        record[name] = {"summary": _clean(summary, work), "arrays": dataset_arrays(out)}
    return record


def _train_section(work: Path, dtype: str, progress: Any) -> dict[str, Any]:
    """One precision's runs: every model, an ensemble, a resume, a finetune, an evaluate."""
    data = work / "pendulum-chain.h5"
    other = work / "pendulum-chain5.h5"
    base = [*TRAIN, "--dtype", dtype]
    section: dict[str, Any] = {}
    for name, opts in MODELS.items():
        progress(f"{dtype} train {name}")
        run = work / dtype / name
        cli(["train", data, *opts, *base, "--epochs", EPOCHS, "--run-dir", run])
        section[f"train/{name}"] = run_record(run, work)
    default = MODELS["mpnode-default"]
    progress(f"{dtype} ensemble")
    run = work / dtype / "ensemble"
    cli(["train", data, *default, *base, "--epochs", 2, "--seeds", 2, "--run-dir", run])
    section["ensemble/mpnode-default-seeds2"] = run_record(run, work)
    section.update(_resume(work / dtype, data, [*default, *base], progress))
    progress(f"{dtype} finetune")
    parent, run = work / dtype / "mpnode-default", work / dtype / "finetune"
    cli(["finetune", parent, other, *base, "--epochs", 2, "--run-dir", run])
    section["finetune/mpnode-default-on-chain5"] = run_record(run, work)
    section.update(_evaluate(work / dtype, data, progress))
    return section


def _resume(folder: Path, data: Path, args: list[str], progress: Any) -> dict[str, Any]:
    """Train 2 epochs, resume to `EPOCHS`; recorded beside the uninterrupted run's match."""
    progress(f"{folder.name} resume")
    run = folder / "resumed"
    cli(["train", data, *args, "--epochs", 2, "--run-dir", run])
    cli(["train", "--resume", run, "--epochs", EPOCHS, "--threads", "1", "--no-plots"])
    record = run_record(run, folder.parent)
    whole = run_record(folder / "mpnode-default", folder.parent)
    same = {key: record[key] == whole[key] for key in ("epochs", "weights_last")}
    return {"resume/mpnode-default-2-to-3": record,
            "resume/equals-uninterrupted": same}


def _evaluate(folder: Path, data: Path, progress: Any) -> dict[str, Any]:
    """Evaluate every trained model on all of its dataset, the predictions hashed."""
    record = {}
    for name in [*MODELS, "ensemble"]:
        progress(f"{folder.name} evaluate {name}")
        out = folder / f"predictions-{name}.h5"
        result = json.loads(cli(["evaluate", folder / name, data, "--split", "all", "--json",
                                 "--save-predictions", out, "--threads", "1"]))
        record[f"evaluate/{name}"] = {"result": _clean(result, folder.parent),
                                                  "predictions": dataset_arrays(out)}
    return record


def _check_registry() -> None:
    from mpnode_cli.models.registry import OPTIONS

    covered = {opts[opts.index("--model") + 1] for opts in MODELS.values()}
    missing = sorted(set(OPTIONS) - covered)
    if missing:
        raise SystemExit(f"contract.py: model kinds not covered: {', '.join(missing)}; "
                         "add them to MODELS")


def record(progress: Any) -> dict[str, Any]:
    """Run every case in a temporary folder and return the contract record."""
    import numpy as np
    import torch

    torch.set_num_threads(1)
    with contextlib.suppress(RuntimeError):  # refused once torch has run parallel work
        torch.set_num_interop_threads(1)
    _check_registry()
    with tempfile.TemporaryDirectory(prefix="mpnode-contract-") as tmp:
        work = Path(tmp)
        result: dict[str, Any] = {
            "format": FORMAT, "version": VERSION,
            "meta": {"torch": torch.__version__, "numpy": np.__version__,
                     "python": platform.python_version(), "machine": platform.machine()},
            "datasets": _generate(work, progress),
        }
        for dtype in SECTIONS:
            result[dtype] = _train_section(work, dtype, progress)
    return result


def dump(value: dict[str, Any]) -> str:
    """The record as JSON text (float repr round-trips exactly)."""
    return json.dumps(value, indent=1, sort_keys=True) + "\n"


def flatten(value: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """(path, leaf) pairs of a nested record, e.g. `float64/train/node/epochs/1/val_loss`."""
    if isinstance(value, dict):
        for key, item in value.items():
            yield from flatten(item, f"{prefix}/{key}" if prefix else str(key))
    elif isinstance(value, list) and value and all(
            isinstance(v, dict | list) for v in value):
        for i, item in enumerate(value):
            yield from flatten(item, f"{prefix}/{i}")
    else:
        yield prefix, value


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return type(a) is type(b) and a == b


def _relative(a: Any, b: Any) -> float | None:
    """|a − b| / max(|a|, |b|) of two numbers (or equal-length lists: the largest), else None."""
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        parts = [_relative(x, y) for x, y in zip(a, b, strict=True)]
        return None if any(p is None for p in parts) else max(parts, default=0.0)
    numbers = (int, float)
    if isinstance(a, numbers) and isinstance(b, numbers) and not isinstance(a, bool) \
            and not isinstance(b, bool):
        if _same(float(a), float(b)):
            return 0.0
        return abs(a - b) / max(abs(a), abs(b), _TINY)
    return None


def differences(old: dict[str, Any], new: dict[str, Any]) -> list[tuple[str, Any, Any, Any]]:
    """(path, recorded, now, relative difference or None) of every leaf that differs."""
    a = dict(flatten({k: v for k, v in old.items() if k != "meta"}))
    b = dict(flatten({k: v for k, v in new.items() if k != "meta"}))
    rows = []
    for path in sorted(a.keys() | b.keys()):
        x, y = a.get(path, "<missing>"), b.get(path, "<missing>")
        if not _same(x, y):
            rows.append((path, x, y, _relative(x, y)))
    return rows


def _short(value: Any, width: int = 22) -> str:
    text = repr(value) if isinstance(value, float) else json.dumps(value)
    return text if len(text) <= width else text[: width - 1] + "…"


def report(old: dict[str, Any], new: dict[str, Any], limit: int) -> bool:
    """Print the comparison; True where the float64 section and datasets are identical."""
    rows = differences(old, new)
    if old.get("meta") != new.get("meta"):
        print(f"note: recorded on {old.get('meta')}, now {new.get('meta')}: "
              "bytes may differ across torch or numpy versions")
    total = dict(flatten({k: v for k, v in old.items() if k != "meta"}))
    print(f"{'section':<10} {'numbers':>8} {'moved':>6} {'max rel diff':>13}")
    for section in ("datasets", *SECTIONS):
        moved = [r for r in rows if r[0].split("/")[0] == section]
        rel = [r[3] for r in moved if r[3] is not None]
        count = sum(1 for p in total if p.split("/")[0] == section)
        print(f"{section:<10} {count:>8} {len(moved):>6} "
              f"{(f'{max(rel):.3g}' if rel else '—'):>13}")
    if rows:
        print(f"\n{'what moved':<72} {'recorded':>22} {'now':>22} {'rel diff':>9}")
        for path, x, y, rel in rows[:limit]:
            print(f"{path:<72} {_short(x):>22} {_short(y):>22} "
                  f"{(f'{rel:.2e}' if rel is not None else '—'):>9}")
        if len(rows) > limit:
            print(f"(+{len(rows) - limit} more; --limit to see them)")
    strict = [r for r in rows if r[0].split("/")[0] != "float32"]
    print("\nfloat64 and datasets: " + ("identical" if not strict else
                                        f"{len(strict)} numbers differ — FAIL"))
    return not strict


def main(argv: list[str] | None = None) -> int:
    """`contract.py record OUT.json` or `contract.py compare OUT.json`."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record", help="run the cases and write the record to OUT.json")
    rec.add_argument("out", type=Path)
    cmp = sub.add_parser("compare", help="run the cases and compare with a record (exit 1 "
                                         "where float64 or the datasets differ)")
    cmp.add_argument("record", type=Path)
    cmp.add_argument("--limit", type=int, default=60, help="rows of moved numbers shown")
    cmp.add_argument("--save", type=Path, help="also write this run's record here")
    args = parser.parse_args(argv)
    # One thread everywhere, set before torch (imported by the commands) starts its pools.
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                "MPNODE_THREADS"):
        os.environ[var] = "1"

    def progress(text: str) -> None:
        print(f"  {text}", file=sys.stderr, flush=True)

    if args.command == "compare":
        try:
            old = json.loads(args.record.read_text())
        except (OSError, ValueError) as exc:
            print(f"contract.py: cannot read {args.record}: {exc}", file=sys.stderr)
            return 2
        if old.get("format") != FORMAT:
            print(f"contract.py: {args.record} is not a {FORMAT} record", file=sys.stderr)
            return 2
    new = record(progress)
    text = dump(new)
    target = args.out if args.command == "record" else args.save
    if target is not None:
        tmp = target.with_name(target.name + ".tmp")
        tmp.write_text(text)
        tmp.replace(target)
    if args.command == "record":
        print(f"wrote {target} (sha256 {hashlib.sha256(text.encode()).hexdigest()[:16]})")
        return 0
    return 0 if report(old, json.loads(text), args.limit) else 1


if __name__ == "__main__":
    sys.exit(main())
