"""What mpnode prints, made to survive any terminal and any shell.

- **ASCII where a stream needs it.** mpnode's lines use a few characters beyond ASCII
  (× — … ≥ ± →). On a stream that cannot encode them (`LC_ALL=C PYTHONIOENCODING=ascii`)
  the error handler `ASCII_ERRORS` writes each as its ASCII spelling instead of raising
  `UnicodeEncodeError` (`mpnode_cli.cli.common.ascii_fallback` installs it).
- **Suggested commands that paste.** A command mpnode tells its user to run
  (`suggested`) is shell-quoted word by word (`shlex.quote`, POSIX shells), and a path
  that begins with `-` is written `./-name`, so that it is not read as an option.
"""

from __future__ import annotations

import codecs
import os
import shlex

ASCII_ERRORS = "mpnode-ascii"

# The ASCII spelling of each character mpnode prints beyond ASCII; any other is '?'.
_SPELLED = {
    "×": "x", "—": "--", "–": "-", "…": "...", "≥": ">=", "≤": "<=", "±": "+/-",
    "→": "->", "←": "<-", "↔": "<->", "‖": "||", "·": ".", "≈": "~", "÷": "/", "≠": "!=",
    "²": "^2", "³": "^3", "₀": "0", "₁": "1", "√": "sqrt", "∞": "inf", "σ": "sigma",
    "μ": "mu", "π": "pi", "°": "deg", "•": "*", "✓": "ok", "✗": "x", "‘": "'", "’": "'",
    "“": '"', "”": '"', "\u00a0": " ",
}


def _spell(exc: UnicodeError) -> tuple[str, int]:
    """`codecs.register_error`'s handler: the unencodable run in ASCII."""
    if not isinstance(exc, UnicodeEncodeError):
        raise exc
    text = exc.object[exc.start:exc.end]
    return "".join(_SPELLED.get(char, "?") for char in text), exc.end


def register_ascii_errors() -> None:
    """Register `ASCII_ERRORS` with `codecs` (again is harmless)."""
    codecs.register_error(ASCII_ERRORS, _spell)


def suggested(*words: str | os.PathLike) -> str:
    """`mpnode` and `words` as a command line to paste into a POSIX shell.

    Args:
        words: the verb, its options (`str`) and its paths (`os.PathLike`, e.g. `Path`:
            one that begins with `-` gets a leading `./`).

    Returns:
        E.g. `mpnode check 'out dir/my set.h5'`, `mpnode check ./-x.h5`.
    """
    shown = []
    for word in words:
        text = os.fspath(word)
        if not isinstance(word, str) and text.startswith("-"):
            text = os.path.join(os.curdir, text)
        shown.append(shlex.quote(text))
    return " ".join(["mpnode", *shown])
