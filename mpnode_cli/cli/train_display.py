"""What `mpnode train` and `finetune` draw on stderr while training runs: a rich display
of the loop's progress events (`TrainingDisplay`: bars, and epoch lines above them), and
where training is (`TrainingStep`), which a line names if memory runs out. `mpnode
experiment` draws its training steps with the same display.
"""

from __future__ import annotations

from typing import Any

from mpnode_cli.cli.common import warn
from mpnode_cli.threads import applied_threads


class TrainingStep:
    """Where training is, from the loop's events: what a line names if memory runs out."""

    def __init__(self) -> None:
        self.now = "loading the data and building the model"

    def told(self, on_event):
        """`on_event`, after noting each event's step."""
        def seen(event: dict[str, Any]) -> None:
            kind = event.get("event")
            if kind == "start":
                self.now = f"training epoch {event['first_epoch']}"
            elif kind == "epoch":  # the next one starts (or the test, after the last)
                self.now = f"training epoch {event['epoch'] + 1}"
            elif kind == "batch":
                self.now = (f"training epoch {event['epoch']}, past batch {event['batch']} "
                            f"of {event['batches']}")
            elif kind == "test":
                self.now = "testing the best checkpoint"
            on_event(event)
        return seen

    def __str__(self) -> str:
        return self.now


class TrainingDisplay:
    """A rich progress display fed by the loop's events; epoch lines go above the bars."""

    def __init__(self, out, shown: bool = True):
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        self.console = out
        # No bars when stderr is not a terminal (pipes, logs, tests); epoch lines remain.
        self.bar = Progress(TextColumn("{task.description}"), BarColumn(),
                            MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn(),
                            TextColumn("{task.fields[info]}"), console=out,
                            transient=True, disable=not (shown and out.is_terminal))
        self.epochs = self.bar.add_task("epochs", total=None, info="")
        self.batches = self.bar.add_task("batches", total=None, info="")
        self.every, self.last_epoch, self.best = 1, 0, float("inf")

    def __enter__(self):
        self.bar.__enter__()
        return self

    def __exit__(self, *exc):
        return self.bar.__exit__(*exc)

    def on_event(self, event: dict[str, Any]) -> None:
        kind = event["event"]
        if kind == "start":
            self.last_epoch = event["epochs"]
            self.every = max(1, event["epochs"] // 20)
            self.bar.update(self.epochs, total=event["epochs"], completed=event["first_epoch"] - 1)
            self.bar.update(self.batches, total=event["batches"], completed=0)
            self.console.print(f"run {event['run_dir']}: {event['parameters']:,} parameters, "
                               f"epochs {event['first_epoch']}–{event['epochs']}")
            if threads := applied_threads():
                self.console.print(f"threads: {threads.describe()}")
            if "solver" in event:
                self.console.print(f"solver: {event['solver']}")
            if event.get("in_degree"):
                lo, hi = event["in_degree"]
                self.console.print(f"in-degree covered by training: {lo}–{hi}")
            if event.get("stream"):
                self.console.print("data: streamed from the file, two batches read ahead")
            if event.get("processes", 1) > 1:
                self.console.print(f"processes: {event['processes']} ({event['backend']}), "
                                   "each training its slice of every batch")
        elif kind == "batch":
            self.bar.update(self.batches, completed=event["batch"],
                            info=f"loss {event['loss']:.4g}")
        elif kind == "epoch":
            self._epoch(event)
        elif kind == "skip":
            self.console.print(f"[yellow]epoch {event['epoch']} batch {event['batch']}: "
                               f"update skipped ({event['reason']})")
        elif kind == "restore":
            self.console.print(f"[yellow]epoch {event['epoch']}: rolled back to the last "
                               f"good epoch, lr now {event['lr']:.3g}")
        elif kind == "test":
            self.bar.update(self.batches, description="testing", completed=0)
        elif kind == "warning":
            warn(event["text"])
        elif kind == "coverage":
            self.console.print(
                f"coverage: simulating {event['trajectories']} trajectories on "
                f"{event['nodes']}-node graphs whose {event['hubs']} hubs hear every other "
                f"node up to {event['multiplicity']} times (in-degree up to "
                f"{event['multiplicity'] * (event['nodes'] - 1)}, for {event['reach']}) "
                f"into {event['path']}")

    def _epoch(self, row: dict[str, Any]) -> None:
        from mpnode_cli.report.tables import fmt

        epoch, val = row["epoch"], row["val_loss"]
        self.best = min(self.best, val) if val is not None else self.best
        info = f"val {fmt(val)} · best {fmt(self.best)} · lr {row['lr']:.2g}"
        self.bar.update(self.epochs, completed=epoch, info=info)
        self.bar.update(self.batches, completed=0)
        if epoch % self.every == 0 or epoch == self.last_epoch:
            each = "".join(f" {name} {fmt(mse)}"  # several datasets: each one's MSE
                           for name, mse in row.get("val_mse_by_dataset", {}).items())
            self.console.print(f"epoch {epoch:>4}  train {fmt(row['train_loss']):>7}  "
                               f"val {fmt(val):>7} (MSE {fmt(row['val_mse']):>7}{each})  "
                               f"lr {row['lr']:.2g}  {row['seconds']:.2f}s  "
                               f"{row['rhs_evals']} evals{_per_sample(row)}")


def _per_sample(row: dict[str, Any]) -> str:
    """` (12.5 per sample)`: the epoch's right-hand-side evaluations per trajectory sample."""
    per = row.get("rhs_evals_per_sample")
    return f" ({per:.3g} per sample)" if per else ""
