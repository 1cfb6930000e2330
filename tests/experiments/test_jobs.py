"""The benches' jobs on the experiments' engine (`mpnode_cli.experiments.jobs`): a job runs
once, in its folder, its record in `step.json`; a failed job skips what needs it and not
the rest, and is tried again next time; the plan's wall time is list scheduling's."""

from __future__ import annotations

import json
import math
import sys
import textwrap

import pytest

from mpnode_cli.experiments import jobs
from mpnode_cli.experiments.spec import CallStep

MODULE = textwrap.dedent('''
    import json
    from pathlib import Path

    def work(folder, inputs, resumed, name, fail=False, log=""):
        with open(log, "a") as f:
            f.write(name + "\\n")
        if fail:
            raise RuntimeError(f"{name} broke")
        got = {i: r.result["value"] for i, r in inputs.items()}
        (Path(folder) / "out.txt").write_text(name)
        return {"job": name, "value": len(name) + sum(got.values()), "inputs": got}
''')


@pytest.fixture()
def module(tmp_path, monkeypatch):
    (tmp_path / "jobs_under_test.py").write_text(MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield tmp_path / "log.txt"
    sys.modules.pop("jobs_under_test", None)


def _step(name: str, log, needs=(), fail=False, seconds=1.0) -> CallStep:
    return CallStep(verb="call", id=name, target="jobs_under_test:work",
                    args={"name": name, "fail": fail, "log": str(log)}, needs=list(needs),
                    seconds=seconds, group="g")


def _ran(log) -> list[str]:
    return log.read_text().split() if log.exists() else []


def test_a_failed_job_skips_what_needs_it_and_is_tried_again(module, tmp_path):
    work = tmp_path / "work"
    steps = [_step("a", module), _step("b", module, fail=True), _step("c", module, ["b"]),
             _step("d", module, ["a"])]
    events = []
    failed = jobs.run_jobs(steps, work, 1, events.append)
    assert set(failed) == {"b", "c"}
    assert "b broke" in failed["b"] and "skipped" in failed["c"]
    assert sorted(_ran(module)) == ["a", "b", "d"]  # c never started
    by_job = {r["job"]: r for r in jobs.records(work)}
    assert set(by_job) == {"a", "d"}
    assert by_job["d"]["inputs"] == {"a": 1} and by_job["d"]["value"] == 2
    assert [e["id"] for e in events if e["event"] == "step-failed"] == ["b", "c"]
    # The next run: a and d are done; b runs again (and fails again), c is skipped again.
    assert set(jobs.run_jobs(steps, work, 1, events.append)) == {"b", "c"}
    assert sorted(_ran(module)) == ["a", "b", "b", "d"]
    # Fixed, b runs and c with it; a and d stay done.
    steps[1] = _step("b", module)
    assert jobs.run_jobs(steps, work, 1, events.append) == {}
    assert sorted(_ran(module)) == ["a", "b", "b", "b", "c", "d"]
    assert {r["job"] for r in jobs.records(work)} == {"a", "b", "c", "d"}


def test_the_record_is_the_engines_step_record(module, tmp_path):
    work = tmp_path / "work"
    jobs.run_jobs([_step("a", module)], work, 1, lambda e: None)
    (folder,) = [p for p in work.iterdir() if p.is_dir()]
    assert folder.name.startswith("a-") and (folder / "out.txt").read_text() == "a"
    record = json.loads((folder / "step.json").read_text())
    assert record["verb"] == "call" and record["result"]["job"] == "a"
    assert record["options"] == {"target": "jobs_under_test:work",
                                 "args": {"name": "a", "fail": False, "log": str(module)}}


def test_other_arguments_are_another_job(module, tmp_path):
    work = tmp_path / "work"
    jobs.run_jobs([_step("a", module)], work, 1, lambda e: None)
    planned = _step("a", module, seconds=99.0)  # a new estimate is the same job
    jobs.run_jobs([planned], work, 1, lambda e: None)
    assert _ran(module) == ["a"]
    other = CallStep(**{**planned.model_dump(), "args": {**planned.args, "name": "a2"}})
    jobs.run_jobs([other], work, 1, lambda e: None)
    assert _ran(module) == ["a", "a2"]


def test_two_processes_run_every_job_once(module, tmp_path):
    work = tmp_path / "work"
    steps = [_step(f"j{i}", module) for i in range(4)] + [_step("last", module, ["j0", "j3"])]
    assert jobs.run_jobs(steps, work, 2, lambda e: None) == {}
    assert sorted(_ran(module)) == ["j0", "j1", "j2", "j3", "last"]


def test_the_plans_wall_time_is_list_scheduling(module, tmp_path):
    # Closed forms: 3 independent jobs of 1 h on 2 workers take 2 h; a chain of 2 takes 2 h
    # on any number of workers; the critical path goes first: a 2 h chain (x then y) beside
    # two 1 h jobs on 2 workers takes 2 h, not 3.
    assert jobs.schedule({n: (3600.0, ()) for n in "abc"}, 2) == 7200.0
    assert jobs.schedule({"a": (3600.0, ()), "b": (3600.0, ("a",))}, 4) == 7200.0
    chain = {"p": (3600.0, ()), "q": (3600.0, ()), "x": (3600.0, ()),
             "y": (3600.0, ("x",))}
    assert jobs.schedule(chain, 2) == 7200.0
    steps = [_step("a", module, seconds=1800.0), _step("b", module, ["a"], seconds=1800.0)]
    text = jobs.plan(steps, tmp_path / "work", 2, {"s": ["g"]})
    assert "g                      2      1.00" in text and "about 1.00 h" in text
    jobs.run_jobs(steps[:1], tmp_path / "work", 1, lambda e: None)
    left = jobs.plan(steps, tmp_path / "work", 2)
    assert math.isclose(float(left.splitlines()[1].split()[-1]), 0.5)  # b's half hour left


def test_the_reporter_says_what_ran_finished_and_failed(module, tmp_path):
    lines, done = [], []
    steps = [_step("a", module), _step("b", module, fail=True), _step("c", module, ["b"])]
    jobs.run_jobs(steps, tmp_path / "work", 1, jobs.reporter(lines.append, done.append))
    said = sorted(tuple(line.split()[:2]) for line in lines)  # b first: c waits for it
    assert said == [("FAIL", "b:"), ("FAIL", "c:"), ("done", "a"), ("start", "a"),
                    ("start", "b")]
    assert done == ["a"] and "skipped" in next(x for x in lines if x.startswith("FAIL   c"))
