"""Training recipes: precedence, the paper's choices, system recommendations, batching and
the lr schedules."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import gene_data

from mpnode_cli.config.train import TrainConfig
from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.systems.registry import SYSTEMS
from mpnode_cli.training.loop import train
from mpnode_cli.training.recipe import CURRICULUM_MIN_SAMPLES, resolve_recipe
from mpnode_cli.training.run import read_config, read_metrics


def resolved(recipe_stored=None, system="gene", samples=51, accepts=("aggregate",),
             aggregate=None, **given):
    if aggregate is not None:
        given["model_options"] = {"aggregate": aggregate}
    config = TrainConfig(dataset="x.h5", **given)
    return resolve_recipe(config, system, recipe_stored, samples, lambda k: k in accepts)


def test_paper_recipe_is_the_authors_configuration():
    lorenz = resolved(system="lorenz", recipe="paper")
    assert (lorenz.loss, lorenz.batch_size, lorenz.patience, lorenz.epochs) == (
        "huber", 128, 500, 4000)
    assert (lorenz.even_batches, lorenz.horizon_curriculum) == (False, False)
    assert lorenz.model_options["aggregate"] == "mean"
    assert lorenz.val_batch_size == 128  # the authors validate with the training batch size
    assert resolved(system="gene", recipe="paper").loss == "mse"  # the paper's App. A.3


def test_options_beat_the_recipe_and_the_system_recommendation():
    ours = resolved()
    assert (ours.loss, ours.model_options["aggregate"], ours.batch_size) == ("mse", "sum", 32)
    mine = resolved(loss="huber", aggregate="pna", batch_size=7)
    assert (mine.loss, mine.model_options["aggregate"], mine.batch_size) == ("huber", "pna", 7)
    assert resolved(recipe="paper", batch_size=64).val_batch_size == 64


def test_a_recommended_model_option_applies_only_to_models_that_have_it():
    assert "aggregate" not in resolved(accepts=()).model_options


MODEL_OPTIONS = ("aggregate", "update", "message_init")


def test_the_default_update_is_the_affine_sum_except_where_a_system_declares_otherwise():
    affine = {"aggregate": "sum", "update": "affine", "message_init": "learned"}
    for system in ("gene", "kuramoto", "my-own-system"):  # the last: no declaration at all
        assert resolved(system=system, accepts=MODEL_OPTIONS).model_options == affine
    for system in ("lorenz", "quadrotor"):  # the paper's MLP update over the mean
        assert resolved(system=system, accepts=MODEL_OPTIONS).model_options == {
            "aggregate": "mean"}
    assert resolved(recipe="paper", accepts=MODEL_OPTIONS).model_options == {"aggregate": "mean"}


def test_curriculum_by_default_only_for_long_trajectories():
    assert resolved(samples=CURRICULUM_MIN_SAMPLES).horizon_curriculum
    assert not resolved(samples=CURRICULUM_MIN_SAMPLES - 1).horizon_curriculum
    assert not resolved(samples=500, horizon_curriculum=False).horizon_curriculum
    # Lorenz recommends it at 51 samples (its escape from the origin: the recipe docs).
    assert resolved(system="lorenz", samples=51).horizon_curriculum
    assert not resolved(system="lorenz", samples=51, horizon_curriculum=False).horizon_curriculum


def test_a_stored_recipe_wins_over_the_system_declaration():
    stored = {"mpnode": {"batch_size": 5}, "paper": {"loss": "huber"}}
    assert resolved(recipe_stored=stored).batch_size == 5
    # Lorenz declares the mean; a stored recipe without model options leaves the recipe's own.
    assert resolved(recipe_stored=stored, system="lorenz").model_options["aggregate"] == "sum"
    assert resolved(recipe_stored=stored, recipe="paper").loss == "huber"


@pytest.fixture(scope="module")
def gene(tmp_path_factory):
    """Gene dynamics on a 2×2 grid: 48 trajectories × 11 samples."""
    return gene_data(tmp_path_factory.mktemp("data"), t_end=1.0)


def test_generate_stores_the_system_recipe_and_train_applies_it(gene, tmp_path):
    data = TrajectoryData.load(gene)
    assert data.attrs["recipe"] == SYSTEMS["gene"].recipe()
    train(TrainConfig(dataset=gene, run_dir=tmp_path / "r", epochs=1, plots=False))
    written = read_config(tmp_path / "r")
    chosen = {k: written.model_options[k] for k in MODEL_OPTIONS}
    assert chosen == {"aggregate": "sum", "update": "affine", "message_init": "learned"}
    assert written.loss == "mse"
    assert "recipe" in written.model_fields_set  # every field explicit: resume re-applies none


def test_even_batches_leave_no_tiny_tail(gene, tmp_path, monkeypatch):
    from mpnode_cli.training import loop

    sizes = []
    real = loop.train_step

    def spy(model, optimizer, inputs, *args):
        sizes.append(inputs[0][0].shape[0])  # (x: [B, H, N, D], u) of the one model
        return real(model, optimizer, inputs, *args)

    monkeypatch.setattr(loop, "train_step", spy)
    k = int((TrajectoryData.load(gene).split == 0).sum())
    assert k % 16 not in (0, 15)  # so that the authors' batching leaves a small tail
    for even in (True, False):
        sizes.clear()
        train(TrainConfig(dataset=gene, run_dir=tmp_path / str(even), epochs=1, plots=False,
                          batch_size=16, even_batches=even))
        assert sum(sizes) == k and len(sizes) == math.ceil(k / 16)
        if even:
            assert max(sizes) - min(sizes) <= 1
        else:
            assert sizes[:-1] == [16] * (len(sizes) - 1) and sizes[-1] == k % 16


def test_cosine_schedule_follows_its_closed_form(gene, tmp_path):
    cfg = TrainConfig(dataset=gene, run_dir=tmp_path / "c", epochs=4, plots=False,
                      schedule="cosine", lr=1e-2, min_lr=1e-4)
    train(cfg)
    lrs = [row["lr"] for row in read_metrics(tmp_path / "c")[1:]]
    want = [1e-4 + 0.5 * (1e-2 - 1e-4) * (1 + math.cos(math.pi * (e - 1) / 4))
            for e in range(1, 5)]
    assert lrs == pytest.approx(want, rel=1e-12)


def test_validation_does_not_depend_on_its_batch_size(gene, tmp_path):
    losses = []
    for vb in (1, 1024):
        torch.manual_seed(0)
        train(TrainConfig(dataset=gene, run_dir=tmp_path / f"v{vb}", epochs=1, plots=False,
                          val_batch_size=vb, solver={"fixed_dt": 0.05}))
        losses.append(read_metrics(tmp_path / f"v{vb}")[0]["val_loss"])
    assert losses[0] == pytest.approx(losses[1], rel=1e-5)
