"""Rich tables of results. They are built here and printed by `cli/` (the library never prints).

Every function takes plain dicts (`EvalResult.to_dict()`, `summary.json`), so tables can be
drawn from files as well as from live results. Every MSE is shown beside the two naive
predictors of `mpnode_cli.training.evaluate.baseline_mse` (hold x(0), time mean), each with
its ratio to the model's MSE: "×20" means the baseline's error is 20 times the model's.

An ensemble's result (`train --seeds S`) is its members' mean prediction's, and its tables
add the members' own MSE as mean ± std over the members, the spread (the members' std,
normalized, averaged over every predicted value) and the spread-error correlation (over
trajectories: how well the spread ranks where the mean prediction is wrong). A single
model's tables have none of these rows or columns.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rich import box
from rich.table import Table
from rich.text import Text

# Columns a table may take where it is not shown on a terminal (a pipe, a file, a log),
# whose console is otherwise unbounded so that plain lines are never wrapped.
PIPE_WIDTH = 100


class FittedTable(Table):
    """A rich table that fits `PIPE_WIDTH` columns when not written to a terminal (on one,
    rich fits it to the terminal's width itself); cells then fold rather than lose their
    ends, so a path in one is whole."""

    def add_column(self, *args: Any, **options: Any) -> None:
        options.setdefault("overflow", "fold")
        super().add_column(*args, **options)

    def __rich_console__(self, console, options):
        yield from super().__rich_console__(console, _fitted(console, options))

    def __rich_measure__(self, console, options):
        return super().__rich_measure__(console, _fitted(console, options))


def _fitted(console, options):
    """`options` narrowed to `PIPE_WIDTH` off a terminal."""
    if console.is_terminal or options.max_width <= PIPE_WIDTH:
        return options
    return options.update(width=PIPE_WIDTH)


def titled(title: str, **options: Any) -> Table:
    """A table (`FittedTable`) under a title that is never wrapped: rich wraps a title to
    the table's width, and a narrow table would break a path in it mid-name.

    Args:
        title: the title (a path, a command, what the table is).
        **options: rich's `Table` options.
    """
    text = Text(title, style="table.title", no_wrap=True, overflow="ignore")
    return FittedTable(title=text, title_justify="left", **options)


def fmt(value: Any, digits: int = 4) -> str:
    """Numbers for a table: 4 significant digits, '—' for missing or non-finite."""
    if value is None or (isinstance(value, float) and value != value):
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return str(value)


def versus(baseline: Any, mse: Any) -> str:
    """A baseline's MSE and its ratio to the model's: `0.1234 (×20.5)`."""
    if not isinstance(baseline, float) or not isinstance(mse, float) or not mse > 0:
        return fmt(baseline)
    return f"{fmt(baseline)} (×{fmt(baseline / mse, 3)})"


def format_mean_std(mean: Any, std: Any) -> str:
    """`1.234 ± 0.05`; '—' when the mean is missing."""
    if fmt(mean) == "—":
        return "—"
    return f"{fmt(mean)} ± {fmt(std)}"


def members_mse(result: dict[str, Any] | None) -> str:
    """An ensemble result's members' MSE as mean ± std (`member_stats`), '—' for a single
    model's."""
    if not (result or {}).get("members"):
        return "—"
    return format_mean_std((result.get("members_mean") or {}).get("mse"),
                           (result.get("members_std") or {}).get("mse"))


def _ensemble_rows(result: dict[str, Any], prefix: str = "") -> list[tuple[str, str]]:
    """An ensemble result's rows: the members' MSE, the spread, the spread-error
    correlation (none for a single model's result)."""
    members = result.get("members")
    if not members:
        return []
    return [(f"{prefix}members' MSE (mean ± std of {len(members)})", members_mse(result)),
            (f"{prefix}spread (members' std, normalized)", fmt(result.get("spread"))),
            (f"{prefix}spread-error correlation", fmt(result.get("spread_error_corr"), 3))]


def _dataset_test_row(name: str, record: dict[str, Any]) -> tuple[str, str]:
    """One dataset's test MSE beside its time-mean baseline (a run on several datasets)."""
    mse = (record.get("test") or {}).get("mse")
    time_mean = (record.get("baselines") or {}).get("time_mean")
    return f"  {name}: test MSE, time-mean MSE", f"{fmt(mse)}, {versus(time_mean, mse)}"


def baselines_note(source: str) -> str:
    """The line under a table that says what the baselines are; `source` names the train
    split whose time mean is used."""
    return (f"baselines: hold x(0), and the time mean of {source}; "
            "×: baseline MSE / model MSE")


def metrics_table(result: dict[str, Any], state_names: Sequence[str], title: str,
                  baselines: dict[str, Any] | None = None) -> Table:
    """One evaluation: errors (beside the naive baselines), per-state RMSE, error at a few
    horizons."""
    table = titled(title, show_header=False)
    table.add_column(style="bold")
    table.add_column(justify="right")
    table.add_row("trajectories", f"{result['trajectories']} ({result['failed']} failed)")
    ensemble = _ensemble_rows(result)
    table.add_row("MSE of the members' mean (normalized)" if ensemble else "MSE (normalized)",
                  fmt(result["mse"]))
    baselines = baselines or {}
    table.add_row("hold-x(0) MSE (× model)", versus(baselines.get("hold_x0"), result["mse"]))
    table.add_row("time-mean MSE (× model)", versus(baselines.get("time_mean"), result["mse"]))
    for row in ensemble:
        table.add_row(*row)
    table.add_row("Huber loss", fmt(result["huber"]))
    for name, rmse in zip(state_names, result["rmse"], strict=False):
        table.add_row(f"RMSE {name}", fmt(rmse))
    curve = result["mse_vs_time"]
    for frac in (0.25, 0.5, 1.0):
        k = max(1, round(frac * (len(curve) - 1)))
        table.add_row(f"MSE at sample {k}/{len(curve) - 1}", fmt(curve[k]))
    table.add_row("RHS evaluations", fmt(result["n_f_evals"]))
    table.add_row("seconds", fmt(result["seconds"], 3))
    return table


def degree_table(bins: Sequence[dict[str, Any]], title: str) -> Table:
    """One row per in-degree bin (`mpnode_cli.training.by_degree.DegreeSums.rows`): its
    node-trajectories, the model's MSE (physical) beside the naive predictors' and its
    skill (MSE ÷ time-mean MSE: under 1 beats the time mean); an ensemble's members' MSE
    as mean ± std."""
    ensemble = any("members_mean" in row for row in bins)
    table = titled(title)
    for name in ("in-degree", "node-traj.", "MSE", "time mean", "skill", "hold x(0)",
                 "outside", *(("members' MSE",) if ensemble else ())):
        table.add_column(name, justify="left" if name == "in-degree" else "right")
    for row in bins:
        failed = f" ({row['failed']} failed)" if row["failed"] else ""
        outside = row.get("states_outside")
        table.add_row(f"[{row['lo']}, {row['hi']})", f"{row['node_trajectories']:,}{failed}",
                      fmt(row["mse"]), fmt(row["time_mean"]), fmt(row["skill"], 3),
                      fmt(row["hold_x0"]), "—" if outside is None else f"{100 * outside:.1f}%",
                      *((format_mean_std(row.get("members_mean"), row.get("members_std")),)
                        if ensemble else ()))
    return table


def zeroshot_table(rows: Sequence[dict[str, Any]], title: str) -> Table:
    """One row per dataset: where the trained node network ran, and how well.

    MSE is normalized, beside the baselines' (with their ratio to it); RMSE is in physical
    units, averaged over the states (per state in `--json`). An ensemble's MSE is its
    members' mean's, followed by the members' MSE (mean ± std), the spread and the
    spread-error correlation.
    """
    table = titled(title, box=box.SIMPLE_HEAD)
    ensemble = any(row["result"].get("members") for row in rows)
    for name in ("dataset", "system", "N", "topology", "K", "failed", "MSE",
                 *(("members' MSE", "spread", "spread~error") if ensemble else ()),
                 "hold x(0)", "time mean", "Huber", "RMSE"):
        table.add_column(name, justify="left" if name in ("dataset", "system", "topology")
                         else "right")
    for row in rows:
        r = row["result"]
        rmse = [v for v in r["rmse"] if v is not None]
        base = row.get("baselines") or {}
        spread = ((members_mse(r), fmt(r.get("spread")), fmt(r.get("spread_error_corr"), 3))
                  if ensemble else ())
        table.add_row(row["dataset"], row["system"], str(row["num_nodes"]),
                      fmt(row["topology"]), str(r["trajectories"]), str(r["failed"]),
                      fmt(r["mse"]), *spread, versus(base.get("hold_x0"), r["mse"]),
                      versus(base.get("time_mean"), r["mse"]), fmt(r["huber"]),
                      fmt(sum(rmse) / len(rmse) if rmse else None))
    return table


def compare_table(summaries: Sequence[dict[str, Any]]) -> Table:
    """Runs side by side. Table-2 is the paper's figure: best epoch × min validation loss;
    the test MSE sits beside the naive baselines' on the same split. An ensemble's test MSE
    is its members' mean's, followed by its members' test MSE (mean ± std, and S)."""
    table = titled("runs (val: validation loss; MSE normalized)", box=box.SIMPLE_HEAD)
    ensemble = any(s.get("members") for s in summaries)
    columns = ("run", "model", "params", "epochs", "best", "min val", "Table-2", "test MSE",
               *(("members' test MSE",) if ensemble else ()), "hold x(0)", "time mean",
               "s/epoch")
    for name in columns:
        table.add_column(name, justify="left" if name in ("run", "model") else "right")
    for s in summaries:
        test, base = s.get("test") or {}, s.get("baselines") or {}
        epochs = fmt(s.get("epochs")) + ("" if s.get("finished", True) else "…")
        members = s.get("members") or []
        spread = (members_mse(test) + (f" (S={len(members)})" if members else ""),
                  ) if ensemble else ()
        table.add_row(Path(s["run_dir"]).name, fmt(s.get("model")), fmt(s.get("parameters")),
                      epochs, fmt(s.get("best_epoch")), fmt(s.get("min_val_loss")),
                      fmt(s.get("table2")), fmt(test.get("mse")), *spread,
                      versus(base.get("hold_x0"), test.get("mse")),
                      versus(base.get("time_mean"), test.get("mse")),
                      fmt(s.get("seconds_per_epoch"), 3))
    return table


def train_table(summary: dict[str, Any]) -> Table:
    """The end of a training run."""
    table = titled(f"trained {summary['run_dir']}", show_header=False)
    table.add_column(style="bold")
    table.add_column(justify="right")
    test, base = summary.get("test") or {}, summary.get("baselines") or {}
    several = summary.get("by_dataset") or {}
    data = f"{summary['dataset']} ({summary['system']}, N={summary['num_nodes']})"
    if several:  # the pooled numbers below, then each dataset's test MSE
        sizes = ", ".join(f"{name} (N={d['num_nodes']})" for name, d in several.items())
        data = f"{sizes} ({summary['system']}; the MSEs are pooled)"
    members = summary.get("members") or []
    rows = [
        ("model", f"{summary['model']} ({fmt(summary['parameters'])} parameters)"),
        *([("members", f"{len(members)} (seeds {members[0]['seed']}–{members[-1]['seed']})")]
          if members else []),
        ("data", data),
        ("epochs", fmt(summary["epochs"])),
        ("best epoch", fmt(summary["best_epoch"])),
        (f"min validation loss ({summary['loss']}{'; mean over members' * bool(members)})",
         fmt(summary["min_val_loss"])),
        ("min validation MSE", fmt(summary["min_val_mse"])),
        ("Table-2 (best epoch × min val loss)", fmt(summary["table2"])),
        ("test MSE of the members' mean (normalized)" if members else "test MSE (normalized)",
         fmt(test.get("mse"))),
        ("test hold-x(0) MSE (× model)", versus(base.get("hold_x0"), test.get("mse"))),
        ("test time-mean MSE (× model)", versus(base.get("time_mean"), test.get("mse"))),
        *_ensemble_rows(test, "test "),
        ("test Huber", fmt(test.get("huber"))),
        *[_dataset_test_row(name, d) for name, d in several.items()],
        ("seconds per epoch", fmt(summary["seconds_per_epoch"], 3)),
        ("wall seconds", fmt(summary["wall_seconds"], 3)),
        ("skipped batches / restores", f"{summary['skipped_batches']} / {summary['restores']}"),
    ]
    if summary.get("parent_sha256"):
        rows.append(("finetuned from", f"{summary['init_checkpoint']} "
                                       f"(sha256 {summary['parent_sha256'][:12]})"))
    for row in rows:
        table.add_row(*row)
    return table
