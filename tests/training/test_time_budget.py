"""A short `--time-limit` is not spent compiling.

Once, `train --epochs 1000000000 --time-limit 2` chose a compiled run (`compile=auto`: a long
run by its epochs), whose first epoch alone took 18 s compiling: the budget overrun 23×.
"""

from __future__ import annotations

from mpnode_cli.config.train import TrainConfig
from mpnode_cli.training import recipe


def test_a_time_limit_shorter_than_a_compile_runs_eager(monkeypatch):
    monkeypatch.setattr(recipe, "have_cxx", lambda: True)
    long = TrainConfig(dataset="d.h5", epochs=10**9, batch_size=32)
    assert recipe.resolve_compile(long, 64).solver.compile is True  # long: compiled
    for seconds, compiled in ((2, False), (recipe.COMPILE_MIN_SECONDS - 1, False),
                              (recipe.COMPILE_MIN_SECONDS, True), (86_400, True)):
        config = long.model_copy(update={"time_limit": seconds})
        assert recipe.resolve_compile(config, 64).solver.compile is compiled, seconds
