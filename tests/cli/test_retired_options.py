"""Options that a bench measured and mpnode retired (`mpnode_cli.config.upgrade.RETIRED`,
docs/transfer.md): a checkpoint, a run's config.json or a config file that holds one at
its "off" value reads as today's; one that used it is refused in one line that names it
and the last mpnode that reads it.

The old files are today's files with the retired keys written back into them, as the
mpnode before the retirement stored every option (resolved, defaults included).
"""

from __future__ import annotations

import json

import pytest
import torch
from conftest import invoke, one_line_error

from mpnode_cli.config.upgrade import RETIRED_AFTER, RetiredOptionError, upgrade_train_fields
from mpnode_cli.training.checkpoint import CheckpointFormatError, load_checkpoint, read_checkpoint
from mpnode_cli.training.run import checkpoint_path

OFF_MODEL = {"linear_path": False, "gain": "mlp", "input_scale": "z"}
REFUSED = f"an option retired after mpnode {RETIRED_AFTER} (the last version that reads it"


def _as_stored_before(raw: dict, **on) -> dict:
    """A checkpoint's dict as the mpnode before the retirement wrote it: every retired
    option in its model config and train config at "off", but those in `on`."""
    model = {**OFF_MODEL, **{k: v for k, v in on.items() if k in OFF_MODEL}}
    raw["model_config"] |= model
    raw["train_config"]["model_options"] |= model
    raw["train_config"]["normalize"] = on.get("normalize", "z")
    raw.pop("payload_sha256")  # written before checkpoints carried their digest
    return raw


def test_a_checkpoint_with_the_retired_options_off_reads_as_today(user_files, tmp_path):
    raw = torch.load(user_files["checkpoint"], weights_only=True)
    old = tmp_path / "old.pt"
    torch.save(_as_stored_before(raw), old)
    today, before = load_checkpoint(user_files["checkpoint"]), load_checkpoint(old)
    assert before.model_config == today.model_config
    assert before.train_config == today.train_config
    assert not set(OFF_MODEL) & set(before.model_config)
    assert "normalize" not in before.train_config
    a, b = today.build_model().state_dict(), before.build_model().state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    result = invoke("evaluate", old, user_files["data"], "--json")
    assert result.exit_code == 0, result.output


@pytest.mark.parametrize(("on", "shown"), [
    ({"linear_path": True}, "linear_path = true"),
    ({"gain": "linear"}, 'gain = "linear"'),
    ({"input_scale": "asinh"}, 'input_scale = "asinh"'),
    ({"normalize": "asinh"}, 'normalize = "asinh"'),
])
def test_a_checkpoint_trained_with_a_retired_option_is_refused_naming_it(
        user_files, tmp_path, on, shown):
    raw = torch.load(user_files["checkpoint"], weights_only=True)
    old = tmp_path / "old.pt"
    torch.save(_as_stored_before(raw, **on), old)
    with pytest.raises(CheckpointFormatError,
                       match=f"this checkpoint was trained with {shown}, an option retired"):
        read_checkpoint(old)
    line = one_line_error(invoke("evaluate", old, user_files["data"]))
    assert f"{old}: this checkpoint was trained with {shown}, {REFUSED}" in line, line


def test_an_asinh_scale_in_the_normalizer_is_the_retired_normalize(user_files, tmp_path):
    raw = torch.load(user_files["checkpoint"], weights_only=True)
    raw["normalizer"]["x_scale"] = [1.0] * len(raw["normalizer"]["x_mean"])
    raw.pop("payload_sha256")  # written before checkpoints carried their digest
    torch.save(raw, tmp_path / "old.pt")
    with pytest.raises(CheckpointFormatError, match='trained with normalize = "asinh"'):
        load_checkpoint(tmp_path / "old.pt")


def test_a_train_config_drops_the_retired_fields_off_and_refuses_them_on():
    fields = {"dataset": "d.h5", "normalize": "z", "model_options": {"hidden": 8, **OFF_MODEL}}
    assert upgrade_train_fields(fields) == {"dataset": "d.h5", "model_options": {"hidden": 8}}
    with pytest.raises(RetiredOptionError) as exc:
        upgrade_train_fields({**fields, "model_options": {"linear_path": True}})
    assert str(exc.value) == f"the config sets linear_path = true, {REFUSED}; docs/transfer.md)"


@pytest.mark.parametrize(("table", "shown"), [
    ("[model_options]\nlinear_path = true\n", "linear_path = true"),
    ('normalize = "asinh"\n', 'normalize = "asinh"'),
])
def test_a_config_file_with_a_retired_option_on_is_one_line(user_files, tmp_path, table, shown):
    (tmp_path / "c.toml").write_text(table)
    line = one_line_error(invoke("train", user_files["data"], "--config", tmp_path / "c.toml",
                                 "--epochs", 1, "--no-plots", "--run-dir", tmp_path / "r"))
    assert f"the config sets {shown}, {REFUSED}" in line, line
    assert not (tmp_path / "r").exists()


def test_a_run_stored_with_the_retired_options_off_resumes(own_user_files):
    """A run folder of the mpnode before: config.json and both checkpoints hold every
    retired option at "off"; it resumes, and one whose config.json used one is refused."""
    run = own_user_files["run"]
    for which in ("best", "last"):
        path = checkpoint_path(run, which)
        torch.save(_as_stored_before(torch.load(path, weights_only=True)), path)
    config = json.loads((run / "config.json").read_text())
    config = {**config, "normalize": "z",
              "model_options": {**config["model_options"], **OFF_MODEL}}
    (run / "config.json").write_text(json.dumps(config))
    result = invoke("train", "--resume", run, "--epochs", 2)
    assert result.exit_code == 0, result.output
    config["model_options"]["linear_path"] = True
    (run / "config.json").write_text(json.dumps(config))
    line = one_line_error(invoke("train", "--resume", run, "--epochs", 3))
    assert f"linear_path = true, {REFUSED}" in line, line
