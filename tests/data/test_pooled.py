"""Several datasets at once: each batch from one dataset, every trajectory once an epoch,
one dataset exactly as before; and the datasets that cannot go together refused in a line."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
from conftest import synthetic

from mpnode_cli.data.pooled import check_poolable, epoch_batches, load_datasets


def one_dataset_batches(k: int, batch_size: int, even: bool, generator: torch.Generator):
    """The batches of a one-dataset run, as the training loop drew them before it took
    several datasets."""
    order = torch.randperm(k, generator=generator)
    if even:
        return order.tensor_split(math.ceil(len(order) / batch_size))
    return order.split(batch_size)


@pytest.mark.parametrize("even", [True, False])
@pytest.mark.parametrize(("k", "batch_size"), [(48, 16), (33, 10), (5, 32)])
def test_one_dataset_draws_its_batches_as_before(k, batch_size, even):
    ours, before = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    for _ in range(2):  # two epochs: the generator is left where it was left before
        got = epoch_batches([k], batch_size, even, ours)
        want = one_dataset_batches(k, batch_size, even, before)
        assert [i for i, _ in got] == [0] * len(want)
        assert all(torch.equal(a, b) for (_, a), b in zip(got, want, strict=True))
    assert torch.equal(ours.get_state(), before.get_state())


@pytest.mark.parametrize("even", [True, False])
def test_batches_of_several_datasets_mix_and_cover_each_once(even):
    sizes, batch_size = [10, 7, 3], 4
    gen = torch.Generator().manual_seed(0)
    batches = epoch_batches(sizes, batch_size, even, gen)
    for i, k in enumerate(sizes):
        mine = [idx for j, idx in batches if j == i]
        assert sorted(torch.cat(mine).tolist()) == list(range(k))  # each trajectory once
        lengths = sorted(len(idx) for idx in mine)
        assert len(mine) == math.ceil(k / batch_size)
        if even:  # nearly equal sizes, per dataset
            assert lengths[-1] - lengths[0] <= 1
        else:  # full batches and a partial last one, per dataset
            assert lengths[1:] == [batch_size] * (len(mine) - 1)
    order = [i for i, _ in batches]
    assert order != sorted(order)  # interleaved, not one dataset after another
    def plan(batches):
        return [(i, idx.tolist()) for i, idx in batches]

    # Seeded: the same seed draws the same epoch; the next epoch draws another.
    assert plan(epoch_batches(sizes, batch_size, even, torch.Generator().manual_seed(0))) == (
        plan(batches))
    assert plan(epoch_batches(sizes, batch_size, even, gen)) != plan(batches)


def test_datasets_of_other_sizes_and_lengths_on_one_grid_go_together():
    check_poolable([synthetic(4, 6, seed=1), synthetic(3, 9, seed=2, nodes=5)])


@pytest.mark.parametrize(("change", "message"), [
    ({"system": "other"}, "has system other but toy1.h5 has toy"),
    ({"state_names": ("a", "c")}, "has state names"),
    ({"time": torch.arange(6, dtype=torch.float64) * 0.2}, "the same start time and dt"),
    ({"time": 1 + torch.arange(6, dtype=torch.float64) * 0.1}, "the same start time and dt"),
    ({"fingerprint": "1"}, "holds the same data as toy1.h5"),
])
def test_datasets_that_do_not_go_together_are_refused_in_one_line(change, message):
    other = replace(synthetic(3, 6, seed=2, nodes=4), **change)
    with pytest.raises(ValueError, match=message) as info:
        check_poolable([synthetic(4, 6, seed=1), other])
    assert "\n" not in str(info.value)


def test_other_per_node_sizes_and_a_repeated_name_are_refused():
    wider = synthetic(3, 6, seed=2)
    wider = replace(wider, states=torch.cat([wider.states, wider.states[..., :1]], dim=-1))
    with pytest.raises(ValueError, match=r"has node_dim 3 but toy1\.h5 has 2"):
        check_poolable([synthetic(4, 6, seed=1), wider])
    with pytest.raises(ValueError, match=r"two datasets are named toy1 \(toy1\.h5 is the second\)"):
        check_poolable([synthetic(4, 6, seed=1), replace(synthetic(3, 6, seed=2),
                                                         path=synthetic(1, 2, 1).path)])


def test_streaming_takes_one_dataset():
    with pytest.raises(ValueError, match="--stream reads one dataset"):
        load_datasets(["a.h5", "b.h5"], stream=True)  # refused before any file is read
