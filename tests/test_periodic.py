"""Periodic states (angles): declared by systems, plug-ins and `mpnode import --periodic`,
recorded in datasets (format version 3) and checkpoints, embedded as (sin θ, cos θ) by
MP-NODE's `--periodic embed`, and compared mod 2π under `--wrap-angles`.

References are independent of the code under test: numpy's own sin/cos and arctan2, files
written by h5py directly and edited by hand.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import invoke, one_line_error

from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.data.hdf5 import read_dataset, read_header
from mpnode_cli.data.validate import check_dataset

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "fitzhugh_nagumo.py"


# --- 1. Declaration ----------------------------------------------------------------------

def test_built_in_systems_declare_their_angles():
    from mpnode_cli.systems.registry import SYSTEMS

    assert SYSTEMS["kuramoto"].periodic_states == ("theta1", "theta2", "theta3")
    assert SYSTEMS["pendulum"].periodic_states == ("theta",)
    for name, cls in SYSTEMS.items():
        assert set(cls.periodic_states) <= set(cls.state_names), name
    assert SYSTEMS["lorenz"].periodic_states == ()


def test_a_plugin_declares_periodic_states_and_a_bad_name_is_refused(tmp_path):
    from mpnode_cli.systems.registry import load_system_file

    source = EXAMPLE.read_text()
    anchor = '    state_names: ClassVar[tuple[str, ...]] = ("v", "w")\n'
    assert anchor in source
    good = tmp_path / "good.py"
    good.write_text(source.replace(anchor, anchor + '    periodic_states = ("w",)\n'))
    assert load_system_file(good).periodic_states == ("w",)
    bad = tmp_path / "bad.py"
    bad.write_text(source.replace(anchor, anchor + '    periodic_states = ("phi",)\n'))
    line = one_line_error(invoke("generate", "--system-file", bad, "--out", tmp_path / "x.h5"))
    assert "declares periodic_states = ('phi',), not a tuple of distinct names among its " \
           "state_names" in line, line


def test_a_kuramoto_dataset_generated_now_declares_its_phases(tmp_path):
    from mpnode_cli.config import GenerateConfig
    from mpnode_cli.data.generate import generate

    path = generate(GenerateConfig(system="kuramoto", nodes=6, trajectories=3, t_end=0.1,
                                   dt=0.05, out=tmp_path / "k.h5")).path
    with h5py.File(path, "r") as f:
        assert f.attrs["format_version"] == 3
        assert json.loads(f.attrs["periodic_states"]) == ["theta1", "theta2", "theta3"]
    assert read_dataset(path).periodic_states == ("theta1", "theta2", "theta3")
    assert TrajectoryData.load(path).attrs["periodic_states"] == ("theta1", "theta2", "theta3")
    assert check_dataset(path).ok


# --- 2. Format: import, and files from before version 3 ----------------------------------

@pytest.fixture
def arrays(tmp_path):
    rng = np.random.default_rng(0)
    np.save(tmp_path / "s.npy", rng.normal(size=(4, 5, 3, 2)))
    np.save(tmp_path / "a.npy", np.ones((3, 3), np.uint8))
    return tmp_path


def test_import_periodic_records_the_names(arrays):
    out = arrays / "d.h5"
    result = invoke("import", "--states", arrays / "s.npy", "--adjacency", arrays / "a.npy",
                    "--dt", 0.1, "--state-names", "q,p", "--periodic", "q", "--out", out)
    assert result.exit_code == 0, result.output
    with h5py.File(out, "r") as f:
        assert json.loads(f.attrs["periodic_states"]) == ["q"]
    assert read_dataset(out).periodic_states == ("q",)
    assert read_header(out)["attrs"]["periodic_states"] == ["q"]
    assert check_dataset(out).ok
    plain = arrays / "plain.h5"
    assert invoke("import", "--states", arrays / "s.npy", "--adjacency", arrays / "a.npy",
                  "--dt", 0.1, "--out", plain).exit_code == 0
    assert read_dataset(plain).periodic_states == ()


def test_import_refuses_a_periodic_name_that_is_no_state(arrays):
    out = arrays / "d.h5"
    line = one_line_error(invoke("import", "--states", arrays / "s.npy", "--adjacency",
                                 arrays / "a.npy", "--dt", 0.1, "--periodic", "theta",
                                 "--out", out))
    assert "--periodic 'theta' is not a state name (states: x0, x1)" in line, line
    assert not out.exists()


def _as_version_2(path: Path) -> None:
    """Make a file written now into the version 2 file it would have been: no
    `periodic_states` attribute, format_version 2."""
    with h5py.File(path, "r+") as f:
        del f.attrs["periodic_states"]
        f.attrs["format_version"] = 2


def test_a_version_2_dataset_loads_with_no_periodic_states(arrays):
    out = arrays / "d.h5"
    assert invoke("import", "--states", arrays / "s.npy", "--adjacency", arrays / "a.npy",
                  "--dt", 0.1, "--periodic", "x0", "--out", out).exit_code == 0
    _as_version_2(out)
    assert check_dataset(out).ok
    assert read_dataset(out).periodic_states == ()
    assert read_header(out)["attrs"]["periodic_states"] == []
    assert TrajectoryData.load(out).attrs["periodic_states"] == ()


def test_a_dataset_whose_periodic_states_are_not_state_names_is_refused(arrays):
    out = arrays / "d.h5"
    assert invoke("import", "--states", arrays / "s.npy", "--adjacency", arrays / "a.npy",
                  "--dt", 0.1, "--out", out).exit_code == 0
    with h5py.File(out, "r+") as f:
        f.attrs["periodic_states"] = json.dumps(["nope"])
    report = check_dataset(out)
    assert not report.ok
    assert any("periodic_states" in p for p in report.problems), report.problems


def test_wrapped_difference_reference_constants():
    """numpy's own: atan2(sin π, cos π) is π (to rounding), the reference below leans on."""
    assert abs(abs(math.atan2(math.sin(math.pi), math.cos(math.pi))) - math.pi) < 1e-15
