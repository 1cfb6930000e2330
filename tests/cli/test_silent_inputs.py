"""Inputs once taken in silence, or refused for the wrong reason: each is now its own check
and one line (exit 2), or read as it is meant."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
import torch
from conftest import invoke, one_line_error

from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.data.validate import check_dataset


def test_a_models_predictions_are_no_training_data_unless_asked_for(user_files, tmp_path):
    pred = tmp_path / "pred.h5"
    result = invoke("evaluate", user_files["run"], user_files["data"], "--split", "all",
                    "--save-predictions", pred)
    assert result.exit_code == 0, result.output
    for verb in (["train"], ["finetune", user_files["checkpoint"]]):
        line = one_line_error(invoke(*verb, pred, "--epochs", 1, "--no-plots", "--run-dir",
                                     tmp_path / "r"))
        assert "pred.h5 holds a model's predictions" in line, line
        assert "--allow-predictions" in line and not (tmp_path / "r").exists()
    result = invoke("train", pred, "--epochs", 1, "--no-plots", "--run-dir", tmp_path / "r",
                    "--allow-predictions")
    assert result.exit_code == 0, result.output


def test_controls_are_part_of_the_data_fingerprint(user_files, tmp_path):
    controls = tmp_path / "u.npy"
    u = np.random.default_rng(1).normal(size=(6, 5, 3, 1))
    np.save(controls, u)
    with_u = tmp_path / "with_u.h5"
    result = invoke("import", "--states", user_files["states"], "--adjacency",
                    user_files["adjacency"], "--dt", 0.1, "--controls", controls, "--out", with_u)
    assert result.exit_code == 0, result.output
    plain, controlled = TrajectoryData.load(user_files["data"]), TrajectoryData.load(with_u)
    # The definition: float32 states, the graphs, graph_index, time, then float32 controls.
    states = np.load(user_files["states"]).astype(np.float32)
    graph = np.ones((1, 3, 3), np.uint8).tobytes()
    rest = graph + np.zeros(6, np.int32).tobytes() + (np.arange(5) * 0.1).tobytes()
    assert plain.fingerprint == hashlib.sha256(states.tobytes() + rest).hexdigest()
    assert controlled.fingerprint == hashlib.sha256(
        states.tobytes() + rest + u.astype(np.float32).tobytes()).hexdigest()
    line = one_line_error(invoke("train", user_files["data"], with_u, "--epochs", 1,
                                 "--no-plots", "--run-dir", tmp_path / "r"))
    assert "same data" not in line and "control_dim 1" in line, line
    # A file written before controls counted recorded the fingerprint without them: valid.
    import h5py

    with h5py.File(with_u, "r+") as f:
        f.attrs["fingerprint"] = plain.fingerprint
    assert check_dataset(with_u).ok, check_dataset(with_u).problems


@pytest.mark.parametrize(("version", "words"), [
    ("6", "format_version '6', not a whole number from 1 to"),
    (True, "format_version True, not a whole number"),
    (0, "format_version 0, below the first (1)"),
    (99, "is checkpoint format v99, newer than this mpnode reads"),
])
def test_a_checkpoint_version_that_is_no_version_is_refused(user_files, tmp_path, version,
                                                            words):
    payload = torch.load(user_files["checkpoint"], weights_only=True)
    payload["format_version"] = version
    payload.pop("payload_sha256")  # a file edited by hand, not one mpnode saved
    path = tmp_path / "edited.pt"
    torch.save(payload, path)
    assert words in one_line_error(invoke("check", path))


def test_a_checkpoint_is_read_as_the_version_it_says(user_files, tmp_path):
    payload = torch.load(user_files["checkpoint"], weights_only=True)
    payload["format_version"] = 1  # through every upgrade, each a no-op on newer contents
    payload.pop("payload_sha256")  # version 1 carried no digest
    path = tmp_path / "v1.pt"
    torch.save(payload, path)
    result = invoke("check", path, "--json")
    assert result.exit_code == 0, result.output
    shown = json.loads(result.output)["summary"]["format"]
    assert shown.endswith("(upgraded from v1 on reading)"), shown


def test_a_csv_saved_with_a_byte_order_mark_imports(user_files, tmp_path):
    states = np.load(user_files["states"])  # [K, T, N, D] = [6, 5, 3, 2]
    rows = [f"{k},{t * 0.1:g},{n},{states[k, t, n, 0]:.17g},{states[k, t, n, 1]:.17g}"
            for k in range(6) for t in range(5) for n in range(3)]
    csv = tmp_path / "bom.csv"
    csv.write_text("\ufefftrajectory,time,node,x,v\n" + "\n".join(rows) + "\n",
                   encoding="utf-8")
    assert csv.read_bytes().startswith(b"\xef\xbb\xbftrajectory")  # Excel's "CSV UTF-8"
    out = tmp_path / "o.h5"
    result = invoke("import", "--states", csv, "--adjacency", user_files["adjacency"],
                    "--dt", 0.1, "--out", out)
    assert result.exit_code == 0, result.output
    loaded = TrajectoryData.load(out)
    assert loaded.state_names == ("x", "v")
    np.testing.assert_allclose(loaded.states.numpy(), states, rtol=1e-6)


@pytest.mark.parametrize(("content", "words"), [
    (b"", "is an empty file (0 bytes)"),
    (bytes(range(256)) * 3, "is not an HDF5 file"),
])
def test_check_says_what_a_dot_h5_that_is_no_hdf5_file_is(tmp_path, content, words):
    path = tmp_path / "x.h5"
    path.write_bytes(content)
    line = one_line_error(invoke("check", path))
    assert words in line and "checkpoint (torch" not in line, line
    report = json.loads(invoke("check", path, "--json").output)
    assert report["kind"] == "file" and words in report["problems"][0]


@pytest.mark.parametrize(("args", "env", "words"), [
    (["--threads", "100000"], {}, "--threads must be at most 256"),
    (["--threads", "0"], {}, "--threads must be a whole number ≥ 1, got '0'"),
    (["--threads", "abc"], {}, "--threads must be a whole number ≥ 1, got 'abc'"),
    ([], {"MPNODE_THREADS": "abc"}, "MPNODE_THREADS must be a whole number ≥ 1"),
])
def test_the_root_threads_option_and_variable_are_checked_for_every_verb(user_files, args,
                                                                         env, words):
    line = one_line_error(invoke(*args, "info", user_files["data"], env=env))
    assert words in line, line
    assert invoke("--threads", 2, "info", user_files["data"]).exit_code == 0
