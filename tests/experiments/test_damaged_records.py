"""A run record that is not one mpnode wrote, an `--out` holding no runs, and a disk that
fills while a report is written: each one line (exit 2), and nothing changed.

Once, `{}` or a line of notes in a `results.json` ended `experiment report` (and `run`) in
a KeyError or a JSONDecodeError; a truncated one said only "Expecting value" without the
file; a record whose scale was 123 was reported, linking figures that do not exist; and a
mistyped `--out` got an index of 67 "not run" rows.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

import pytest
from conftest import invoke, one_line_error

from mpnode_cli.experiments import report as report_module
from mpnode_cli.experiments import spec
from mpnode_cli.experiments.report import write_report
from mpnode_cli.experiments.runner import RunRecord, StepRecord
from mpnode_cli.paths import OutputError

ROOT = Path(__file__).resolve().parents[2]
RECORD = Path("message-pca") / "tiny-mpnode" / "results.json"


def _tree(tmp_path: Path, text: str) -> Path:
    out = tmp_path / "rep"
    (out / RECORD).parent.mkdir(parents=True)
    (out / RECORD).write_text(text)
    return out


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*")
            if p.is_file()}


@pytest.mark.parametrize("text, said", [
    ("{}", "scale None is none of"),
    ("notes\n", "not JSON"),
    ('{"broken": \n', "not JSON: Expecting value: line 2"),
    ('{"scale": 123, "recipe": "mpnode", "steps": []}', "scale 123 is none of"),
    ('{"scale": "small", "recipe": "mpnode", "steps": []}',
     "it is the record of small-mpnode/, not of tiny-mpnode/"),
    ('{"scale": "tiny", "recipe": "mpnode", "steps": [{"id": 3}]}', "its steps are not"),
])
def test_a_record_mpnode_did_not_write_is_refused_naming_it(tmp_path, text, said):
    out = _tree(tmp_path, text)
    before = _files(out)
    for args in (["experiment", "report", "--out", out],
                 ["experiment", "run", "message-pca", "--scale", "tiny", "--seeds", 1,
                  "--out", out, "--work", tmp_path / "work"]):
        line = one_line_error(invoke(*args))
        assert f"{out / RECORD} is not a run record mpnode wrote" in line and said in line, line
    assert _files(out) == before
    assert not (tmp_path / "work").exists()  # refused before any step ran


def test_report_on_a_folder_without_runs_writes_nothing(tmp_path):
    line = one_line_error(invoke("experiment", "report", "--out", tmp_path / "nonexist"))
    assert "no saved runs under" in line, line
    assert not (tmp_path / "nonexist").exists()


def _saved_record(tmp_path: Path) -> tuple[RunRecord, spec.Experiment, Path]:
    """A committed record of message-pca, as a `RunRecord` whose steps made no figures."""
    data = json.loads((ROOT / "reports" / "message-pca" / "small-mpnode" / "results.json")
                      .read_text())
    steps = [StepRecord(**{**s, "figures": []}) for s in data["steps"]]
    fields = {k: v for k, v in data.items() if k in RunRecord.__dataclass_fields__}
    return (RunRecord(**{**fields, "steps": steps, "work": str(tmp_path / "work")}),
            spec.load("message-pca"), tmp_path / "rep")


def test_a_disk_that_fills_while_a_report_is_written_is_one_line(tmp_path, monkeypatch):
    record, experiment, out = _saved_record(tmp_path)
    write_report(record, experiment, out)
    before = _files(out)

    def full(path, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(report_module, "atomic_text", full)
    with pytest.raises(OutputError, match=r"cannot write .*small-mpnode: No space left on "
                                          r"device \(the record there is as it was\)"):
        write_report(record, experiment, out)
    assert _files(out) == before
    assert [p.name for p in (out / "message-pca").iterdir()
            if p.name.endswith(".tmp")] == []
    line = one_line_error(invoke("experiment", "report", "--out", out))
    assert "cannot rebuild the reports in" in line and "No space left" in line, line
    assert _files(out) == before
    shutil.rmtree(out)
