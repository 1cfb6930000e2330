"""The README's commands work as written, and every link in the README and `docs/` leads
to a file (and heading) that exists.

The commands run in order, verbatim, in an empty folder through the CLI (`CliRunner`, one
process), at a test's size by one mechanical rule: `SMALL[verb]` is appended to each
command of that verb, and a later option wins over an earlier one. The files a README
reader brings along (their arrays, their graphs) are written first, tiny (`YOUR_FILES`);
`examples/` is copied in, as a clone's root has it. `make demo` and `make test` are the
set-up, not run here.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import doc_commands
from typer.testing import CliRunner

from mpnode_cli.cli.app import app

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]

# Later options win: the README's commands at a test's size.
SMALL = {"generate": ["--trajectories", "12"],
         "train": ["--epochs", "1", "--batch-size", "4"],
         "finetune": ["--epochs", "1", "--batch-size", "4"]}


def your_files(folder: Path) -> None:
    """The inputs the README's commands name, tiny: 10 trajectories of 11 samples on a
    3-node chain (D = 2) to import, and 2 initial states of the session's Lorenz model
    (D = 3) on a 5-node ring to simulate."""
    rng = np.random.default_rng(0)
    np.save(folder / "states.npy", rng.normal(size=(10, 11, 3, 2)).cumsum(axis=1) * 0.1)
    np.save(folder / "graph.npy", np.array([[0, 1, 0], [1, 0, 1], [0, 1, 0]], np.uint8))
    np.save(folder / "x0.npy", rng.normal(size=(2, 5, 3)))
    (folder / "big-graph.txt").write_text("".join(f"{i} {(i + 1) % 5}\n" for i in range(5)))


def test_the_setup_is_make_demo_and_make_test():
    commands = [" ".join(words) for words in doc_commands(README.read_text())]
    assert "make demo" in commands and "make test" in commands


def test_every_readme_command_runs(tmp_path, monkeypatch):
    commands = doc_commands(README.read_text())
    others = [c for c in commands if c[0] != "mpnode" and c not in (["make", "demo"],
                                                                      ["make", "test"])]
    assert not others, f"README commands this test does not run: {others}"
    mpnode = [c[1:] for c in commands if c[0] == "mpnode"]
    verbs = [c[0] for c in mpnode]
    for verb in ("generate", "train", "evaluate", "zeroshot", "finetune", "compare", "import"):
        assert verb in verbs

    monkeypatch.chdir(tmp_path)
    shutil.copytree(ROOT / "examples", tmp_path / "examples")
    your_files(tmp_path)
    runner = CliRunner()
    for args in mpnode:
        result = runner.invoke(app, [*args, *SMALL.get(args[0], [])])
        assert result.exit_code == 0, f"mpnode {' '.join(args)}\n{result.output}"
    assert (tmp_path / "runs" / "l7-ft" / "summary.json").is_file()
    assert (tmp_path / "predictions" / "big.h5").is_file()


LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", flags=re.S | re.M)


def anchors(page: Path) -> set[str]:
    """The anchors GitHub gives a page's headings: lower case, punctuation dropped, spaces
    to hyphens, `-1`, `-2` ... after a repeat."""
    seen: dict[str, int] = {}
    out = set()
    for heading in re.findall(r"^#+ (.+)$", FENCE.sub("", page.read_text()), flags=re.M):
        slug = re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")
        out.add(f"{slug}-{seen[slug]}" if slug in seen else slug)
        seen[slug] = seen.get(slug, 0) + 1
    return out


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_link_resolves(page):
    broken = []
    for target in LINK.findall(FENCE.sub("", page.read_text())):
        if re.match(r"[a-z]+:", target):  # https:, mailto:: outside the repository
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            broken.append(target)
        elif anchor and file.suffix == ".md" and anchor not in anchors(file):
            broken.append(target)
    assert not broken, f"{page.relative_to(ROOT)}: links to nothing: {broken}"
