"""Figures are written whole or not at all (`report.plots.save_whole`)."""

from __future__ import annotations

import matplotlib.pyplot as plt
import pytest

from mpnode_cli.report.plots import save_whole


def test_a_figure_is_saved_whole_and_a_failed_save_keeps_the_old_file(tmp_path):
    path = tmp_path / "plots" / "error.png"
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    save_whole(fig, path, dpi=20)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    before = path.read_bytes()

    fig, _ = plt.subplots()

    def cut_off(target, **_):  # half a file, then the disk fills
        with open(target, "wb") as f:
            f.write(b"\x89PNG half")
        raise OSError(28, "No space left on device")

    fig.savefig = cut_off
    with pytest.raises(OSError):
        save_whole(fig, path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in path.parent.iterdir()) == ["error.png"]
