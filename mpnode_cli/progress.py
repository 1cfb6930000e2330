"""How long work tells its caller how far it has come: a `Progress` callback, called as
`progress(done, total)` in the work's own units (trajectories, values), and `pass_of` for
work done in several passes that one bar shows as one.

The library only calls it; `cli/` turns it into a progress bar
(`mpnode_cli.cli.common.task_bar`).
"""

from __future__ import annotations

from collections.abc import Callable

Progress = Callable[[float, int], None]


def pass_of(progress: Progress | None, index: int, passes: int) -> Progress | None:
    """`progress` of pass `index` of `passes` equal passes over the same work, as a share
    of them all: pass 1 of 3 reports `(total + done, 3 · total)`.

    Args:
        progress: the caller's callback, or None (then None).
        index: this pass, from 0.
        passes: the passes in all.
    """
    if progress is None:
        return None
    return lambda done, total: progress(index * total + done, passes * total)
