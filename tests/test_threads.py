"""The thread policy: `--threads` beats `MPNODE_THREADS` beats one."""

from __future__ import annotations

import pytest

from mpnode_cli.threads import ENV_VAR, ThreadChoice, choose_threads


def test_flag_beats_variable_beats_default():
    assert choose_threads("3", {ENV_VAR: "2"}) == ThreadChoice(3, "--threads")
    assert choose_threads(None, {ENV_VAR: " 2 "}) == ThreadChoice(2, ENV_VAR)
    assert choose_threads(None, {}) == ThreadChoice(1, "default")
    assert choose_threads(None, {ENV_VAR: ""}) == ThreadChoice(1, "default")  # set but empty
    assert choose_threads(4, {ENV_VAR: "bad"}).count == 4  # an overridden variable is unread


@pytest.mark.parametrize("value", ["0", "-1", "1.5", "two", " "])
def test_bad_values_name_their_source(value):
    with pytest.raises(ValueError, match=f"--threads must be a whole number ≥ 1, got '{value}'"):
        choose_threads(value, {})
    if value.strip():
        with pytest.raises(ValueError, match=f"{ENV_VAR} must be a whole number ≥ 1"):
            choose_threads(None, {ENV_VAR: value})


def test_describe_says_how_to_change_the_default():
    assert ThreadChoice(1, "default").describe() == (
        "1 (default: one per process; --threads or MPNODE_THREADS to change)")
    assert ThreadChoice(2, ENV_VAR).describe() == "2 (from MPNODE_THREADS)"

