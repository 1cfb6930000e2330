"""A user's text files (edge lists, CSV tables, config files, experiment specs, a run
folder's JSON), read in one place: a file that is missing, unreadable or not UTF-8 text is
one `ValueError` that names it, never a bare `'utf-8' codec can't decode` from deep inside
a parser. A byte-order mark at the start (Excel's "CSV UTF-8", Notepad) is dropped, so that
a first line reads as what it says ("utf-8-sig": plain UTF-8 reads the same).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any


def read_text(path: str | Path, what: str) -> str:
    """The whole of a UTF-8 text file.

    Args:
        path: the file.
        what: what it is, as messages name it ("config file"; "" for just the path).

    Raises:
        ValueError: a file that cannot be opened or read, or is not UTF-8 text.
    """
    try:
        text = Path(path).read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise ValueError(_not_text(path, what)) from None
    except OSError as exc:
        raise ValueError(f"cannot read {_named(path, what)}: {exc.strerror or exc}") from None
    if "\x00" in text:
        raise ValueError(_not_text(path, what))
    return text


def read_json(path: str | Path, what: str = "") -> Any:
    """A UTF-8 JSON file's value.

    Raises:
        ValueError: as `read_text`, or text that is not JSON (with the line).
    """
    import json

    try:
        return json.loads(read_text(path, what))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{_named(path, what)} is not valid JSON (line {exc.lineno}: "
                         f"{exc.msg})") from None


def text_lines(path: str | Path, what: str, max_chars: int) -> Iterator[tuple[int, str]]:
    """`(line number from 1, line)` of a UTF-8 text file, read one line at a time.

    Args:
        path: the file.
        what: what it is, as messages name it ("edge list").
        max_chars: the longest line this kind of file has; a longer one (a binary file
            without newlines) is refused without being read whole.

    Raises:
        ValueError: a file that cannot be opened or read, is not UTF-8 text (a NUL byte
            counts as binary), or has a line longer than `max_chars`.
    """
    try:
        with open(path, encoding="utf-8-sig") as f:
            lineno = 0
            while raw := f.readline(max_chars + 1):
                lineno += 1
                if "\x00" in raw:
                    raise ValueError(_not_text(path, what))
                if len(raw) > max_chars:
                    raise ValueError(f"{path}:{lineno}: a line of more than {max_chars} "
                                     f"characters, which no {what or 'such file'} has (a "
                                     "binary file?)")
                yield lineno, raw
    except UnicodeDecodeError:
        raise ValueError(_not_text(path, what)) from None
    except OSError as exc:
        raise ValueError(f"cannot read {_named(path, what)}: {exc.strerror or exc}") from None


def _named(path: str | Path, what: str) -> str:
    return f"{what} {path}" if what else str(path)


def _not_text(path: str | Path, what: str) -> str:
    return f"{_named(path, what)} is not UTF-8 text (a binary file?)"
