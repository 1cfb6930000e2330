"""Files as records name them: a file's identity (`file_sha256`), and a path or a command
line as a committed record shows it (`shown_path`, `shown_argv`), without the folders of
the machine that wrote it.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file's bytes: a checkpoint's identity (recorded by finetunes and
    predictions), an imported input's."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def shown_path(path: str | Path, placeholder: str) -> str:
    """`path` as a committed record shows it: a relative path as given, an absolute one
    under the current folder relative to it, any other absolute one as `placeholder`
    (e.g. `<work>`), so records do not carry the folders of the machine that wrote them."""
    path = Path(path)
    if not path.is_absolute():
        return str(path)
    try:
        return str(path.relative_to(Path.cwd())) or "."
    except ValueError:
        return placeholder


def shown_argv(args: list[str]) -> list[str]:
    """Command-line arguments as a record shows them: each absolute path through
    `shown_path`, its placeholder named after the option before it (`--runs /tmp/x` →
    `--runs <runs>`)."""
    out = []
    for i, arg in enumerate(args):
        before = args[i - 1] if i else ""
        name = before.lstrip("-") if before.startswith("--") else "path"
        out.append(shown_path(arg, f"<{name}>") if os.path.isabs(arg) else arg)
    return out
