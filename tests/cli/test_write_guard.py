"""The one output guard (`mpnode_cli.paths`) sees every file a verb writes: its inputs (the
config file too) are never outputs, an index it rebuilds replaces only its own, a target the
final rename could not replace is refused before the work, names that become paths are
checked, and an output path is a path (not empty; a file's not ending in `/`)."""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
from pathlib import Path

import pytest
from conftest import invoke, one_line_error

ROOT = Path(__file__).resolve().parents[2]
GENERATE = ["generate", "lorenz", "--nodes", "3", "--trajectories", "8", "--t-end", "0.5"]


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_the_config_file_is_never_the_output_even_with_force(tmp_path):
    config = tmp_path / "c.toml"
    config.write_text('system = "lorenz"\nnodes = 3\ntrajectories = 8\nt_end = 0.5\n')
    before = digest(config)
    line = one_line_error(invoke("generate", "--config", config, "--out", config, "--force"))
    assert "is one of the inputs" in line, line
    assert digest(config) == before


def test_a_users_readme_is_never_the_experiment_index(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    Path("README.md").write_text("my precious readme\n")
    line = one_line_error(invoke("experiment", "run", "message-pca", "--scale", "tiny",
                                 "--out", ".", "--work", "wk"))
    assert "README.md already exists and mpnode did not write it" in line, line
    assert Path("README.md").read_text() == "my precious readme\n"
    assert sorted(os.listdir()) == ["README.md"]  # refused before any step


def test_an_index_mpnode_wrote_is_rebuilt_without_force(tmp_path):
    from mpnode_cli.experiments.saved import INDEX_TITLE
    from mpnode_cli.paths import check_output_file

    index = tmp_path / "README.md"
    index.write_text(f"{INDEX_TITLE}\n\nold rows\n")
    check_output_file(index, overwrite=False, mine=INDEX_TITLE.encode())  # no refusal
    index.write_text("# Something else\n")
    with pytest.raises(FileExistsError):
        check_output_file(index, overwrite=False, mine=INDEX_TITLE.encode())


def test_an_empty_output_path_is_refused(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    line = one_line_error(invoke("experiment", "run", "message-pca", "--scale", "tiny",
                                 "--out", "", "--work", "wk"))
    assert "--out is empty" in line, line
    assert os.listdir() == []


def test_a_files_path_ending_in_a_slash_is_refused(user_files, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    line = one_line_error(invoke("import", "--states", user_files["states"], "--edge-list",
                                 user_files["edges"], "--dt", "0.1", "--out", "newdir/"))
    assert "--out newdir/ ends in '/'" in line, line
    assert os.listdir() == []  # no file named newdir


def test_a_plugin_name_that_is_a_path_is_refused(tmp_path, monkeypatch):
    source = (ROOT / "examples" / "fitzhugh_nagumo.py").read_text()
    old = 'name: ClassVar[str] = "fhn"'
    assert old in source
    plugin = tmp_path / "bad.py"
    plugin.write_text(source.replace(old, 'name: ClassVar[str] = "my system/../x"'))
    monkeypatch.chdir(tmp_path)
    line = one_line_error(invoke("generate", "--system-file", plugin, "--nodes", "4",
                                 "--trajectories", "4", "--t-end", "0.2"))
    assert "declares name = 'my system/../x', not an identifier" in line, line
    assert sorted(os.listdir()) == ["bad.py"]


def test_a_refused_final_rename_is_one_line_and_leaves_no_temporary(tmp_path, monkeypatch):
    out = tmp_path / "g.h5"
    assert invoke(*GENERATE, "--out", out).exit_code == 0
    before = digest(out)
    real = os.replace

    def refuse(src, dst, *args, **kwargs):
        if Path(dst) == out:
            raise PermissionError(1, "Operation not permitted", str(src), None, str(dst))
        return real(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "replace", refuse)
    line = one_line_error(invoke(*GENERATE, "--out", out, "--force"))
    assert f"cannot write {out}: Operation not permitted" in line, line
    assert os.listdir(tmp_path) == ["g.h5"] and digest(out) == before


def _immutable(path: Path) -> bool:
    """Make `path` immutable (chattr +i: root on a filesystem with inode flags)."""
    if shutil.which("chattr") is None:
        return False
    return subprocess.run(["chattr", "+i", str(path)], capture_output=True).returncode == 0


def test_force_over_an_immutable_file_is_refused_before_the_work(tmp_path, monkeypatch):
    import mpnode_cli.data.generate as generate

    out = tmp_path / "g.h5"
    assert invoke(*GENERATE, "--out", out).exit_code == 0
    if not _immutable(out):
        pytest.skip("chattr +i is not available here (needs root and inode flags)")
    try:
        monkeypatch.setattr(generate, "_generate", lambda *a: pytest.fail("the job ran"))
        line = one_line_error(invoke(*GENERATE, "--out", out, "--force"))
        assert f"cannot replace {out}: it is immutable" in line, line
        assert os.listdir(tmp_path) == ["g.h5"]
    finally:
        subprocess.run(["chattr", "-i", str(out)], check=True)


def test_an_empty_run_dir_is_refused(tmp_path):
    assert "--run-dir is empty" in one_line_error(
        invoke("train", tmp_path / "none.h5", "--run-dir", ""))


def test_a_folder_of_the_users_where_a_report_goes_is_refused(tmp_path):
    mine = tmp_path / "out" / "message-pca" / "tiny-mpnode"
    mine.mkdir(parents=True)
    (mine / "notes.txt").write_text("keep me")
    message = one_line_error(invoke("experiment", "run", "message-pca", "--scale", "tiny",
                                    "--out", tmp_path / "out", "--work", tmp_path / "wk"))
    assert "holds no results.json" in message
    assert (mine / "notes.txt").read_text() == "keep me"
    assert not (tmp_path / "wk").exists()


def _no_work(monkeypatch):
    """Fail the test if an evaluation, or the reading of a trajectory to draw, starts."""
    import mpnode_cli.data.hdf5 as hdf5
    import mpnode_cli.training.checkpoint_report as report

    monkeypatch.setattr(report, "evaluate_checkpoint", lambda *a, **k: pytest.fail("ran"))
    monkeypatch.setattr(hdf5, "read_trajectory", lambda *a, **k: pytest.fail("ran"))


@pytest.mark.parametrize("verb", ["evaluate", "info"])
def test_a_plot_refuses_what_is_there_as_every_output_does(user_files, tmp_path, monkeypatch,
                                                           verb):
    """Every plot is checked before any work: the last one of evaluate's here."""
    figs, target = tmp_path / "figs", tmp_path / "target.png"
    target.write_text("their figure")
    name = {"evaluate": "data-all-error.png", "info": "data-trajectory-0.png"}[verb]
    args = {"evaluate": ["evaluate", user_files["run"], user_files["data"], "--split", "all"],
            "info": ["info", user_files["data"]]}[verb]
    figs.mkdir()
    (figs / name).write_text("my figure")
    with monkeypatch.context() as m:
        _no_work(m)
        line = one_line_error(invoke(*args, "--plot", "--plot-dir", figs))
        assert f"{figs / name} already exists (use --force to overwrite)" in line, line
        (figs / name).unlink()
        (figs / name).symlink_to(target)
        line = one_line_error(invoke(*args, "--plot", "--plot-dir", figs, "--force"))
        assert "is a symbolic link: mpnode only replaces regular files" in line, line
    assert os.listdir(figs) == [name] and target.read_text() == "their figure"
    (figs / name).unlink()
    (figs / name).write_text("my figure")
    result = invoke(*args, "--plot", "--plot-dir", figs, "--force")
    assert result.exit_code == 0, result.output
    assert (figs / name).read_bytes().startswith(b"\x89PNG")


def test_infos_default_plot_folder_is_guarded_too(own_user_files):
    plots = own_user_files["data"].parent / "plots"
    plots.mkdir()
    (plots / "data-trajectory-0.png").write_text("my figure")
    line = one_line_error(invoke("info", own_user_files["data"], "--plot"))
    assert "data-trajectory-0.png already exists" in line, line
    assert (plots / "data-trajectory-0.png").read_text() == "my figure"
