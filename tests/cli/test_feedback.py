"""What the verbs tell a user while and after they work: progress on long verbs, lines that
are not broken when written to a pipe, plots that call predictions predictions, what `info`
says of imported data, and one `--json` name for one fact."""

from __future__ import annotations

import json
from contextlib import contextmanager

import numpy as np
import pytest

from tests.conftest import invoke


@pytest.fixture
def bars(monkeypatch) -> list[dict]:
    """Every `task_bar` a verb opens, with its description, `quiet` and each
    `progress(done, total)` call (the bar itself draws only on a terminal)."""
    from mpnode_cli.cli import common

    opened: list[dict] = []

    class Bar:
        def stop(self) -> None:
            pass

    @contextmanager
    def recording(description, columns=None, total=None, *, quiet=False):
        calls: list[tuple[float, float]] = []
        opened.append({"description": description, "quiet": quiet, "calls": calls})
        yield Bar(), lambda done, total: calls.append((done, total))

    monkeypatch.setattr(common, "task_bar", recording)
    return opened


def test_import_simulate_and_evaluate_show_progress(user_files, tmp_path, bars):
    f = user_files
    verbs = {
        "import": ["import", "--states", f["states"], "--adjacency", f["adjacency"], "--dt",
                   0.1, "--out", tmp_path / "d.h5", "--json"],
        "simulate": ["simulate", f["run"], "--x0", f["x0"], "--adjacency", f["adjacency"],
                     "--t-end", 0.4, "--dt", 0.1, "--batch-size", 1, "--out",
                     tmp_path / "p.h5"],
        "evaluate": ["evaluate", f["run"], f["data"], "--split", "all", "--batch-size", 2],
    }
    for name, args in verbs.items():
        start = len(bars)
        result = invoke(*args)
        assert result.exit_code == 0, result.output
        (bar,) = bars[start:]
        assert bar["calls"], f"{name}: the bar never moved"
        done, total = bar["calls"][-1]
        assert done == total > 0 and len(bar["calls"]) > 1, (name, bar["calls"])
        assert bar["quiet"] == ("--json" in args), name  # no bar beside --json output


def test_import_memory_maps_a_npy(tmp_path):
    from mpnode_cli.data.user_inputs import load_states

    np.save(tmp_path / "s.npy", np.arange(2 * 3 * 2 * 1, dtype=np.float32).reshape(2, 3, 2, 1))
    assert isinstance(load_states(tmp_path / "s.npy").states, np.memmap)


def test_lines_are_not_wrapped_without_a_terminal(user_files, tmp_path):
    deep = tmp_path / ("a-rather-long-folder-name-" * 3) / "data-with-a-long-name.h5"
    result = invoke("import", "--states", user_files["states"], "--adjacency",
                    user_files["adjacency"], "--dt", 0.1, "--out", deep)
    assert result.exit_code == 0, result.output
    assert f"check it with: mpnode check {deep}" in result.output.splitlines()[-1]
    result = invoke("info", deep)
    assert result.exit_code == 0, result.output
    assert result.output.splitlines()[0].strip() == str(deep)  # a table's title, whole


def _legends(monkeypatch) -> list[list[str]]:
    """The legend of each rollout figure saved from now on."""
    from mpnode_cli.report import plots

    seen, save = [], plots._save

    def keep(fig, path, dpi=plots.DPI):
        legend = fig.axes[0].get_legend()
        texts = [] if legend is None else [text.get_text() for text in legend.get_texts()]
        if texts and plots.BASELINE_LABELS[0] not in texts:  # not the error plot's
            seen.append(texts)
        return save(fig, path, dpi)

    monkeypatch.setattr(plots, "_save", keep)
    return seen


def test_predictions_are_plotted_as_predictions(user_files, tmp_path, monkeypatch):
    f = user_files
    predictions = tmp_path / "p.h5"
    assert invoke("simulate", f["run"], "--x0", f["x0"], "--adjacency", f["adjacency"],
                  "--t-end", 0.4, "--dt", 0.1, "--out", predictions).exit_code == 0
    legends = _legends(monkeypatch)
    result = invoke("evaluate", f["run"], predictions, "--plot", "--plot-dir", tmp_path / "e")
    assert result.exit_code == 0, result.output
    (evaluated,) = legends
    assert "true" not in evaluated and any("prediction" in label for label in evaluated)
    # The prediction file alone, as `info --plot` draws it.
    result = invoke("info", predictions, "--plot", "--plot-dir", tmp_path / "i")
    assert result.exit_code == 0, result.output
    assert (tmp_path / "i" / "p-trajectory-0.png").is_file()
    assert legends[1:] == [["predicted"]]


def test_info_of_imported_data_says_what_is_known(user_files):
    result = invoke("info", user_files["data"])
    assert result.exit_code == 0, result.output
    assert "graphs ?" not in result.output and "trajectories 0" not in result.output
    assert "split 0" in result.output  # the import's seed drew only the split
    # Cells fold to fit 100 columns: a long one continues on the next lines.
    flat = "".join(line.strip(" │") for line in result.output.splitlines())
    origin = flat[flat.index("imported from"):]
    assert user_files["states"].name in origin and user_files["adjacency"].name in origin
    facts = json.loads(invoke("info", user_files["data"], "--json").stdout)
    assert facts["seeds"] == {"split": 0}


def test_json_names_split_counts_alike(user_files, tmp_path):
    out = tmp_path / "d.h5"
    imported = json.loads(invoke("import", "--states", user_files["states"], "--adjacency",
                                 user_files["adjacency"], "--dt", 0.1, "--out", out,
                                 "--json").stdout)
    generated = json.loads(invoke("generate", "lorenz", "--nodes", 2, "--trajectories", 10,
                                  "--t-end", 0.2, "--dt", 0.1, "--out", tmp_path / "g.h5",
                                  "--json").stdout)
    described = json.loads(invoke("info", out, "--json").stdout)
    assert "split_counts" not in imported
    assert imported["split"] == described["split"] == {"train": 4, "validation": 1, "test": 1}
    assert generated["split"].keys() == imported["split"].keys()
