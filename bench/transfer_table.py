"""Records and tables of `bench/transfer.py`: every job's record JSON, the committed copy
(`bench/results/transfer.json`) and the markdown table, rebuilt from records alone.
"""

from __future__ import annotations

import json
import os
import statistics
from collections.abc import Iterable
from datetime import datetime
from pathlib import Path
from typing import Any

from transfer_specs import SETS, SYSTEMS, per_degree, set_of

LABELS = ("own", "x2", "x4", "other", "n256", "n512", "n1024", "n2048", "n4096", "n8192")


def write_atomic(path: Path, text: str) -> None:
    """Write `text` to a temporary file beside `path`, then rename it over `path`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    tmp.replace(path)


def write_json(path: Path, value: Any) -> None:
    write_atomic(path, json.dumps(value, indent=1) + "\n")


def local_records(runs: Path) -> dict[str, dict[str, Any]]:
    """Every job's record in the engine's work folder `runs` (`step.json`), by job."""
    from mpnode_cli.experiments.jobs import records

    return {r["job"]: r for r in records(runs) if "job" in r}


def merged_records(runs: Path, committed: Path) -> dict[str, dict[str, Any]]:
    """The committed copy's records, overridden by the local ones of the same job."""
    saved = json.loads(committed.read_text()) if committed.is_file() else []
    return {**{r["job"]: r for r in saved}, **local_records(runs)}


def stripped(record: dict[str, Any]) -> dict[str, Any]:
    """A record without its per-node arrays (the committed copy keeps the bins only)."""
    if "score" not in record:
        return record
    return {**record, "score": {k: v for k, v in record["score"].items() if k != "per_node"}}


def save_committed(records: dict[str, dict[str, Any]], path: Path) -> None:
    write_json(path, [stripped(records[job]) for job in sorted(records)])


# ------------------------------------------------------------------------------ grouping


def _group_key(r: dict[str, Any]) -> tuple:
    return (r["protocol"], r["system"], r.get("gamma"), r["variant"], r["label"])


def _order(key: tuple) -> tuple:
    protocol, system, gamma, variant, label = key
    first = SETS["selection"]
    return (system not in first, SYSTEMS.index(system) if system in SYSTEMS else 99,
            protocol != "size", gamma or 0.0, variant,
            LABELS.index(label) if label in LABELS else 99, label)


def grouped(records: Iterable[dict[str, Any]]) -> dict[tuple, dict[str, dict[int, dict]]]:
    """(protocol, system, γ, variant, label) → kind → seed → record; a source's own
    record goes under every label of its bench as "source"."""
    groups: dict[tuple, dict[str, dict[int, dict]]] = {}
    sources = {}
    for r in records:
        if r["kind"] == "source":
            sources[(r["protocol"], r["system"], r.get("gamma"), r["variant"], r["seed"])] = r
            continue
        groups.setdefault(_group_key(r), {}).setdefault(r["kind"], {})[r["seed"]] = r
    for key, kinds in groups.items():
        for seed in {*kinds.get("zeroshot", {}), *kinds.get("oracle", {})}:
            src = sources.get((*key[:4], seed))
            if src:
                kinds.setdefault("source", {})[seed] = src
    for key, kinds in groups.items():  # a variant run with --no-oracles: its base's,
        # where both measure in the same units (angles wrapped or not)
        base = "periodic-off" if key[3].endswith("periodic-off") else "default"
        default = groups.get((*key[:3], base, key[4]), {}).get("oracle")
        if (key[3] != base and "oracle" not in kinds and default
                and _wrapped(kinds.get("zeroshot", {})) == _wrapped(default)):
            kinds["oracle"], kinds["borrowed"] = default, {}
    return dict(sorted(groups.items(), key=lambda kv: _order(kv[0])))


def _wrapped(records: dict[int, dict]) -> bool:
    """Whether scored records took angles mod 2π (`transfer_score.score`'s `wrapped`)."""
    return any((r.get("score") or {}).get("wrapped") for r in records.values())


# ------------------------------------------------------------------------------ cells


def _fmt(value: float | None, spec: str = ".3g") -> str:
    return "—" if value is None else f"{value:{spec}}"


def _pm(values: list[float | None], spec: str = ".3g") -> str:
    values = [v for v in values if v is not None]
    if not values:
        return "—"
    if len(values) == 1:
        return f"{values[0]:{spec}}"
    return f"{statistics.fmean(values):{spec}} ± {statistics.stdev(values):.2g}"


def ratio_cell(zs: dict[int, dict], oracle: dict[int, dict]) -> str:
    """Zero-shot ÷ oracle MSE: the ratio of the seed means, and in brackets the range of
    the ratios of seeds paired by number."""
    a = [r["score"]["mse"] for r in zs.values() if r["score"]["mse"] is not None]
    b = [r["score"]["mse"] for r in oracle.values() if r["score"]["mse"] is not None]
    if not a or not b or not statistics.fmean(b) > 0:
        return "—"
    pairs = [zs[s]["score"]["mse"] / oracle[s]["score"]["mse"] for s in zs
             if s in oracle and zs[s]["score"]["mse"] and oracle[s]["score"]["mse"]]
    spread = f" [{min(pairs):.2g}–{max(pairs):.2g}]" if len(pairs) > 1 else ""
    return f"**{statistics.fmean(a) / statistics.fmean(b):.3g}**{spread}"


def oracle_cell(oracle: dict[int, dict]) -> str:
    """Mean epochs (mean best epoch), and how many seeds stopped by patience."""
    if not oracle:
        return "—"
    rs = list(oracle.values())
    converged = sum(r["stopped_by"] == "patience" for r in rs)
    return (f"{statistics.fmean(r['epochs'] for r in rs):.0f} "
            f"({statistics.fmean(r['best_epoch'] for r in rs):.0f}), "
            f"{statistics.fmean(r['train_seconds'] for r in rs):.0f} s; "
            f"{converged}/{len(rs)} converged")


def source_cell(source: dict[int, dict]) -> str:
    if not source:
        return "—"
    rs = list(source.values())
    return (f"{statistics.fmean(r['epochs'] for r in rs):.0f} "
            f"({statistics.fmean(r['best_epoch'] for r in rs):.0f}), "
            f"{statistics.fmean(r['train_seconds'] for r in rs):.0f} s")


def _scores(kind: dict[int, dict]) -> list[dict[str, Any]]:
    return [r["score"] for _, r in sorted(kind.items())]


def headline_row(key: tuple, kinds: dict[str, dict[int, dict]]) -> str:
    protocol, system, gamma, variant, label = key
    zs, oracle, source = (kinds.get(k, {}) for k in ("zeroshot", "oracle", "source"))
    any_r = next(iter({**zs, **oracle}.values()))
    z, o = _scores(zs), _scores(oracle)
    base = z or o
    src = next(iter(source.values()), None)
    where = (f"{src['nodes']} → " if src else "") + f"{any_r['nodes']} ({any_r['dataset']})"
    failed = sum(s["failed"] for s in z + o)
    lo = min(s["in_degree"][0] for s in base)
    hi = max(s["in_degree"][1] for s in base)
    trained = (z[0] if z else {}).get("train_in_degree")
    cells = [
        set_of(system), system, protocol + (f" γ={gamma:g}" if gamma else ""),
        variant + ("‡" if _dirty(zs, oracle, source) else ""), label, where,
        str(len(zs) or len(oracle)),
        (ratio_cell(zs, oracle) + ("†" if "borrowed" in kinds else "")) if label != "own"
        else "—",
        _pm([s["mse"] for s in z]), _pm([s["skill"] for s in z]),
        _pm([s["mse"] for s in o]), _pm([s["skill"] for s in o]),
        _pm([s["hold_x0"] / s["time_mean"] if s["time_mean"] else None for s in base]),
        _pm([s["time_mean"] for s in base]), _pm([s["states_outside"] for s in z], ".2%"),
        f"{_fmt_range(trained)} → {lo}–{hi}",
        oracle_cell(oracle), source_cell(source), str(failed)]
    return "| " + " | ".join(cells) + " |"


def _dirty(*kinds: dict[int, dict]) -> bool:
    """Whether a row rests on a record made from a tree with uncommitted changes."""
    return any(str(r.get("commit", "")).endswith("+dirty") for k in kinds for r in k.values())


def _fmt_range(pair: list[int] | None) -> str:
    return "—" if not pair else f"{pair[0]}–{pair[1]}"


HEAD = ("| set | system | protocol | variant | target | N: source → target (dataset) | seeds | "
        "**zero-shot ÷ oracle** | zero-shot MSE | zero-shot skill | oracle MSE | "
        "oracle skill | hold x(0) skill | time-mean MSE | states outside | in-degree: "
        "train → target | oracle epochs (best), s; converged | source epochs (best), s | "
        "failed |")


# ------------------------------------------------------------------------------ per degree


def bins_of(record: dict[str, Any]) -> list[dict[str, Any]]:
    """A score's in-degree bins as stored when it was scored, from the full-precision
    per-node values. Not from the record's packed per-node arrays: those are rounded
    (`PER_NODE`'s dtypes: the share outside as float16), and a table taken from them
    would differ in the third or fourth digit from the one a fresh clone rebuilds."""
    return record["score"]["by_degree"]


def degree_table(key: tuple, kinds: dict[str, dict[int, dict]]) -> list[str]:
    """One target's errors by in-degree bin, each bin's value the mean over seeds."""
    protocol, system, gamma, variant, label = key
    per_bin: dict[tuple[int, int], dict[str, list]] = {}
    for kind in ("zeroshot", "oracle"):
        for record in kinds.get(kind, {}).values():
            for row in bins_of(record):
                cell = per_bin.setdefault((row["lo"], row["hi"]), {})
                cell.setdefault(f"{kind}_mse", []).append(row.get("mse"))
                cell.setdefault(f"{kind}_nodes", []).append(row["nodes"])
                if kind == "zeroshot":
                    cell.setdefault("time_mean", []).append(row.get("time_mean"))
                    cell.setdefault("outside", []).append(row.get("outside"))
    gamma_text = f", γ = {gamma:g}" if gamma else ""
    lines = [f"### {system} ({protocol}{gamma_text}, {variant}): {label}", "",
             "| in-degree | node-trajectories per seed | zero-shot MSE | oracle MSE | "
             "zero-shot ÷ oracle | time-mean MSE | states outside |",
             "|---|---|---|---|---|---|---|"]
    for (lo, hi), cell in sorted(per_bin.items()):
        zs = [v for v in cell.get("zeroshot_mse", []) if v is not None]
        orc = [v for v in cell.get("oracle_mse", []) if v is not None]
        ratio = (statistics.fmean(zs) / statistics.fmean(orc)
                 if zs and orc and statistics.fmean(orc) > 0 else None)
        nodes = cell.get("zeroshot_nodes") or cell.get("oracle_nodes")
        lines.append(f"| {lo}–{hi - 1} | {statistics.fmean(nodes):.0f} | {_pm(zs)} | "
                     f"{_pm(orc)} | {_fmt(ratio)} | {_pm(cell.get('time_mean', []))} | "
                     f"{_pm(cell.get('outside', []), '.2%')} |")
    return [*lines, ""]


# ------------------------------------------------------------------------------ the page


INTRO = """\
Written by `bench/transfer.py` from its job records ({count} records; {when}). The protocol
and the metrics are in [docs/transfer.md](../../docs/transfer.md). In short: each row is one
target of one source model; MSE in the target's physical units over its test split (t₀
excluded); **skill** = MSE ÷ the MSE of the target's own time-mean predictor (the mean of
the target's train split at each time) on the same trajectories; the **oracle** is the same
recipe trained on the target's own distribution (as many node-trajectories as the source),
until its validation stopped improving for `--oracle-patience` epochs and for at least the
source's wall time, and is scored on the same test trajectories; **zero-shot ÷ oracle** is
the ratio of the seed means of the MSE (in brackets the range of the ratios paired by seed).
Mean ± std over seeds (training seeds). size: data fixed across seeds; s1: graphs and
initial states drawn anew for each seed. 'own' rows: the source on its own test split.
States outside: the share of the target's test values outside the source's training range.
{note}"""


def page(records: dict[str, dict[str, Any]], note: str = "") -> str:
    """The markdown page: the headline table, then every per-degree table."""
    groups = grouped(records.values())
    lines = ["# Transfer: zero-shot on larger graphs against an oracle trained there", "",
             INTRO.format(count=len(records), when=_dates(records.values()), note=note), "",
             HEAD, "|" + "---|" * (HEAD.count("|") - 1)]
    lines += [headline_row(key, kinds) for key, kinds in groups.items()]
    if any("borrowed" in kinds for kinds in groups.values()):
        lines += ["", "† A variant trained without oracles (`--no-oracles`): its oracle columns "
                  "are the default variant's oracles of the same target (`periodic-off`'s for "
                  "`hub-coverage-periodic-off`)."]
    dirty = sum(str(r.get("commit", "")).endswith("+dirty") for r in records.values())
    if dirty:
        lines += ["", f"‡ A row resting on records made from a tree with uncommitted changes "
                  f"({dirty} of the {len(records)} records): not quoted as results."]
    scales = sorted({r.get("scale", "?") for r in records.values()})
    if scales != ["full"]:
        lines += ["", f"Scales present: {', '.join(scales)} (smoke rows are not results)."]
    lines += ["", "## By in-degree (×4 and S¹ targets)", "",
              "Bins of in-degree [2^k, 2^(k+1)); each value the mean over seeds of the bin's "
              "mean over its node-trajectories of the test split.", ""]
    for key, kinds in groups.items():
        if per_degree(key[4]) and kinds.get("zeroshot"):
            lines += degree_table(key, kinds)
    return "\n".join(lines).rstrip() + "\n"


def _dates(records: Iterable[dict[str, Any]]) -> str:
    dates = sorted({r.get("date", "")[:10] for r in records} - {""})
    if not dates:
        return "no runs yet"
    return f"runs of {dates[0]}" + (f" to {dates[-1]}" if len(dates) > 1 else "")


def rebuild(runs: Path, committed: Path, out: Path, note: str = "",
            save: bool = True) -> str:
    """Merge the committed copy with the local records, write the page (and, with `save`,
    the committed copy again); return the page."""
    records = merged_records(runs, committed)
    text = page(records, note)
    write_atomic(out, text)
    if save:
        save_committed(records, committed)
    return f"{out}: {len(records)} records, {datetime.now():%H:%M:%S}"
