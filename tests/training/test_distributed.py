"""Data-parallel training under torchrun: two CPU processes (gloo) against one process.

The reference is always one process training the same global batches: in float64 one
step of two ranks must be that step to rounding; in float32 whole runs must agree to 1e-4
relative (they differ by the rounding of sums split across ranks, which training amplifies).
"""

from __future__ import annotations

import json
import math
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from conftest import child_env
from typer.testing import CliRunner

from mpnode_cli.cli.app import app
from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.config.train import TrainConfig
from mpnode_cli.data.dataset import Normalizer, TrajectoryData
from mpnode_cli.data.generate import generate
from mpnode_cli.models.mpnode import MPNODE
from mpnode_cli.models.registry import build_model
from mpnode_cli.solver import Status
from mpnode_cli.training import distributed, loop, step
from mpnode_cli.training.losses import LOSSES
from mpnode_cli.training.optim import Adam
from mpnode_cli.training.run import read_metrics

pytestmark = pytest.mark.skipif(not torch.distributed.is_available(),
                                reason="this torch build has no torch.distributed")

RUN_FILES = {"config.json", "metrics.jsonl", "summary.json", "checkpoints",
             "checkpoints/best.pt", "checkpoints/last.pt"}


@pytest.fixture(scope="module")
def gene(gene_2x2):
    """Gene dynamics on a 2×2 grid: 48 trajectories (34 train, 7 validation, 7 test)."""
    return gene_2x2


@pytest.mark.parametrize("n", [0, 1, 2, 7, 8, 33])
@pytest.mark.parametrize("size", [1, 2, 3])
def test_shards_cover_every_item_once_in_near_equal_parts(n, size):
    parts = [distributed.World(rank, size).shard(n) for rank in range(size)]
    assert [i for s in parts for i in range(n)[s]] == list(range(n))
    assert [len(range(n)[s]) for s in parts] == [len(t) for t in torch.arange(n).tensor_split(size)]


# ---------------------------------------------------------------- two ranks in forked processes
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def spawn_two(fn, *args):
    """Run `fn(rank, *args)` in two forked processes joined by torchrun's variables
    (forked: they share this process's imports, so each starts in milliseconds)."""
    import torch.multiprocessing as mp

    port = free_port()

    def rank_main(rank, *args):
        os.environ.update(WORLD_SIZE="2", RANK=str(rank), LOCAL_RANK=str(rank),
                          MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
        torch.set_num_threads(1)
        with distributed.process_group("cpu") as world:
            assert world.size == 2 and world.rank == rank and world.backend == "gloo"
            fn(rank, *args)

    ranks = mp.start_processes(rank_main, args=args, nprocs=2, join=False,
                               start_method="fork")
    deadline = time.monotonic() + 120
    while not ranks.join(timeout=1):  # raises if a rank failed (and stops the other)
        if time.monotonic() > deadline:  # a rank waits on one that will never answer
            for process in ranks.processes:
                process.kill()
            pytest.fail("two ranks did not finish within 120 s")


def one_step(gene, rank: int | None, out: Path, batch: int, fail: str | None = None):
    """One optimizer step in float64 on the first `batch` train trajectories, on this
    rank's slice (rank None: the whole batch in one process); saves what it did.

    fail: make this rank's loss NaN ("loss") or one of its solves fail ("solver").
    """
    world = distributed.world()
    data = TrajectoryData.load(gene)
    config = loop.resolve_train_config(TrainConfig(dataset=gene, clip=5.0), data)
    train_set = data.subset("train")
    normalizer = Normalizer.fit(train_set.states)
    torch.manual_seed(0)
    model = build_model(config.model, {"node_dim": 1, "control_dim": 0, "num_nodes": 4,
                                       **config.model_options}).double()
    if getattr(model, "update", None) == "affine":
        # The affine gains start at zero, which leaves ψ without a gradient at the first
        # step; give them values, so that every parameter takes part in the step.
        with torch.no_grad():
            torch.nn.init.normal_(model.net[-1].weight, std=0.3)
    model.fit_statistics(normalizer.norm_x(train_set.states), 0.1, train_set.adjacency)
    optimizer = Adam(model.parameters(), lr=1e-2)
    part = world.shard(batch)
    mine = train_set.take(torch.arange(batch)[part])
    loss_fn = nan_on_calls({1}) if fail == "loss" else LOSSES["mse"]
    if fail == "solver":
        rollout = MPNODE.rollout

        def failing(self, *args, **kwargs):
            result = rollout(self, *args, **kwargs)
            result.status[-1] = Status.DT_UNDERFLOW
            return result

        MPNODE.rollout = failing
    x = normalizer.norm_x(mine.states).double()  # (B_r, T, N, D)
    before = [p.detach().clone() for p in model.parameters()]
    (result,) = step.train_step(model, optimizer, [(x, None)], train_set.time,
                           [mine.adjacency.double()], loss_fn, config, world,
                           share=len(mine) / batch)
    loss, norm, reason = result.loss, result.grad_norm, result.skip
    if rank in (None, 0):
        torch.save({"loss": loss, "norm": norm, "reason": reason, "before": before,
                    "params": [p.detach().clone() for p in model.parameters()]}, out)


def two_step_cases(rank, gene, tmp):
    one_step(gene, rank, tmp / "uneven.pt", batch=7)  # slices of 3 and 4
    one_step(gene, rank, tmp / "empty.pt", batch=1)  # rank 1 has nothing
    one_step(gene, rank, tmp / "nan.pt", batch=7, fail="loss" if rank == 1 else None)
    one_step(gene, rank, tmp / "solver.pt", batch=7, fail="solver" if rank == 1 else None)


def test_a_step_on_two_ranks_is_one_process_step(gene, tmp_path):
    spawn_two(two_step_cases, gene, tmp_path)
    for name, batch in (("uneven", 7), ("empty", 1)):
        one_step(gene, None, tmp_path / f"{name}-one.pt", batch=batch)
        two, one = (torch.load(tmp_path / f"{name}{s}.pt") for s in ("", "-one"))
        assert two["reason"] is None and one["reason"] is None
        # Two half-batches summed against one backward over all 7: the same terms in
        # another order. The gradient sums ~10³ row·step terms with cancellation, so its
        # norm may move by n·u·cond ≈ 1e-12 (the loss by less): 1e-10 leaves a margin.
        assert two["loss"] == pytest.approx(one["loss"], rel=1e-10), name
        assert two["norm"] == pytest.approx(one["norm"], rel=1e-10), name
        assert one["norm"] > 5.0  # the clip acted, on the global norm
        for p, q, start in zip(two["params"], one["params"], one["before"], strict=True):
            torch.testing.assert_close(p, q, rtol=1e-12, atol=1e-14)
            assert not torch.equal(p, start)
    # A batch that failed on rank 1 only is skipped on rank 0 too, with the same reason.
    nan, failed = torch.load(tmp_path / "nan.pt"), torch.load(tmp_path / "solver.pt")
    assert nan["reason"] == "non-finite loss"
    assert failed["reason"] == "solver DT_UNDERFLOW on 1 trajectories"
    for skipped in (nan, failed):
        assert math.isnan(skipped["loss"])
        for p, start in zip(skipped["params"], skipped["before"], strict=True):
            assert torch.equal(p, start)


def flaky_on_rank_one(rank, gene, run_dir, fail_calls):
    """Rank 1's loss is NaN on the given calls (one per batch); rank 0's is never."""
    if rank == 1:
        LOSSES["mse"] = nan_on_calls(fail_calls)
    loop.train(small(gene, run_dir, epochs=2, max_bad_steps=2, lr=1e-2))


def nan_on_calls(fail_calls):
    calls, mse = {"n": 0}, LOSSES["mse"]

    def loss(pred, target):
        calls["n"] += 1
        return mse(pred, target) * (math.nan if calls["n"] in fail_calls else 1.0)

    return loss


def small(gene, run_dir, **kw) -> TrainConfig:
    # float64: two ranks sum their gradients in another order than one process; in float32
    # that flips an adaptive step's accept now and then, after which two runs differ by
    # about the solver's tolerance (1e-4), the bound the runs are compared at.
    fields = {"dataset": gene, "run_dir": run_dir, "batch_size": 7, "epochs": 2,
              "plots": False, "dtype": "float64"}
    return TrainConfig(**(fields | kw))


def val_losses(run_dir) -> list[float]:
    return [r["val_loss"] for r in read_metrics(run_dir)]


def test_skips_and_rollbacks_are_agreed_by_every_rank(gene, tmp_path, monkeypatch):
    # 34 train trajectories in batches of 7: 5 steps per epoch; steps 2, 6 and 7 fail.
    spawn_two(flaky_on_rank_one, gene, tmp_path / "two", {2, 6, 7})
    monkeypatch.setitem(LOSSES, "mse", nan_on_calls({2, 6, 7}))
    loop.train(small(gene, tmp_path / "one", max_bad_steps=2, lr=1e-2))
    two, one = read_metrics(tmp_path / "two"), read_metrics(tmp_path / "one")
    assert [r["skip_reasons"] for r in two] == [r["skip_reasons"] for r in one]
    assert [r["skipped"] for r in two[1:]] == [1, 2] and two[2]["lr"] == 5e-3  # rolled back
    assert val_losses(tmp_path / "two") == pytest.approx(val_losses(tmp_path / "one"), rel=1e-4)


def train_two_datasets(rank, datasets, run_dir):
    loop.train(small(datasets, run_dir, lr=1e-2))


def test_two_datasets_on_two_ranks_train_as_in_one_process(gene, tmp_path):
    """Each global batch is one dataset's, split over the ranks; each dataset's validation
    split is shared by the ranks too."""
    gene9 = generate(GenerateConfig(system="gene", grid=3, topology="er", trajectories=20,
                                    t_end=1.0, dt=0.1, out=tmp_path / "gene9.h5")).path
    spawn_two(train_two_datasets, [gene, gene9], tmp_path / "two")
    loop.train(small([gene, gene9], tmp_path / "one", lr=1e-2))
    two, one = read_metrics(tmp_path / "two"), read_metrics(tmp_path / "one")
    assert val_losses(tmp_path / "two") == pytest.approx(val_losses(tmp_path / "one"), rel=1e-4)
    for a, b in zip(two, one, strict=True):
        assert a["val_mse_by_dataset"] == pytest.approx(b["val_mse_by_dataset"], rel=1e-4)


def train_ensemble(rank, gene, run_dir):
    loop.train(small(gene, run_dir, lr=1e-2, seeds=3))


def test_an_ensemble_on_two_ranks_trains_as_in_one_process(gene, tmp_path):
    """Each member's global batch is split over the ranks; the members' losses agree."""
    spawn_two(train_ensemble, gene, tmp_path / "two")
    loop.train(small(gene, tmp_path / "one", lr=1e-2, seeds=3))
    two, one = read_metrics(tmp_path / "two"), read_metrics(tmp_path / "one")
    for a, b in zip(two, one, strict=True):
        assert [m["val_loss"] for m in a["members"]] == pytest.approx(
            [m["val_loss"] for m in b["members"]], rel=1e-4)


# ---------------------------------------------------------------- torchrun, end to end
@pytest.fixture(scope="module")
def torchrun_run(gene, tmp_path_factory):
    """`torchrun --standalone --nproc-per-node 2 -m mpnode_cli train`, 2 epochs, from an
    empty folder, run folder by default name."""
    cwd = tmp_path_factory.mktemp("launch")
    out = subprocess.run(
        [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node",
         "2", "-m", "mpnode_cli", "train", str(gene), "--epochs", "2", "--batch-size", "7",
         "--no-plots", "--dtype", "float64"],
        cwd=cwd, env=child_env(), capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    return cwd, out


@pytest.fixture(scope="module")
def one_process(gene, tmp_path_factory):
    """The reference: one process, the same global batches, 3 epochs."""
    run_dir = tmp_path_factory.mktemp("one") / "run"
    loop.train(small(gene, run_dir, epochs=3))
    return run_dir


def test_two_torchrun_processes_match_one_and_write_one_run(torchrun_run, one_process):
    cwd, out = torchrun_run
    assert [p.name for p in cwd.iterdir()] == ["runs"]
    (run_dir,) = (cwd / "runs").iterdir()
    assert {p.relative_to(run_dir).as_posix() for p in run_dir.rglob("*")} == RUN_FILES
    assert [r["epoch"] for r in read_metrics(run_dir)] == [0, 1, 2]
    assert val_losses(run_dir) == pytest.approx(val_losses(one_process)[:3], rel=1e-4)
    assert json.loads((run_dir / "summary.json").read_text())["world_size"] == 2
    assert out.stderr.count("processes: 2 (gloo)") == 1  # rank 0 alone reports
    assert out.stdout.count("min validation loss") == 1  # one summary table


def test_a_two_process_run_resumes_in_one_process(torchrun_run, one_process):
    cwd, _ = torchrun_run
    (run_dir,) = (cwd / "runs").iterdir()
    result = CliRunner().invoke(app, ["train", "--resume", str(run_dir), "--epochs", "3"])
    assert result.exit_code == 0, result.output
    assert [r["epoch"] for r in read_metrics(run_dir)] == [0, 1, 2, 3]
    assert val_losses(run_dir) == pytest.approx(val_losses(one_process), rel=1e-4)
    assert json.loads((run_dir / "summary.json").read_text())["world_size"] == 1


def test_cuda_under_torchrun_without_a_gpu_is_refused_in_one_line(monkeypatch):
    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    monkeypatch.setenv("WORLD_SIZE", "2")
    with pytest.raises(ValueError, match="no CUDA device"), distributed.process_group("cuda"):
        pass


def resume_on_two_ranks(rank, run_dir, epochs):
    from mpnode_cli.training.run import read_config

    config = read_config(run_dir).model_copy(update={"epochs": epochs})
    summary = loop.train(config, resume=True)
    assert (summary is None) == (rank != 0)  # rank 0 alone reports


def test_a_one_process_run_resumes_on_two_ranks(gene, one_process, tmp_path):
    loop.train(small(gene, tmp_path / "run", epochs=2))
    spawn_two(resume_on_two_ranks, tmp_path / "run", 3)
    assert [r["epoch"] for r in read_metrics(tmp_path / "run")] == [0, 1, 2, 3]
    assert val_losses(tmp_path / "run") == pytest.approx(val_losses(one_process), rel=1e-4)
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["world_size"] == 2


def train_into_existing(rank, gene, run_dir):
    with pytest.raises(ValueError, match="a folder of other files"):  # on both ranks, none waits
        loop.train(small(gene, run_dir))


def test_a_refusal_on_rank_0_stops_every_rank(gene, tmp_path):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "notes.txt").write_text("someone else's")
    spawn_two(train_into_existing, gene, tmp_path / "run")
    assert [p.name for p in (tmp_path / "run").iterdir()] == ["notes.txt"]


def resume_a_locked_run(rank, run_dir):
    from mpnode_cli.training.run import read_config

    with pytest.raises(ValueError, match="in use by another mpnode process"):  # none waits
        loop.train(read_config(run_dir).model_copy(update={"epochs": 3}), resume=True)


def test_a_run_another_process_holds_stops_every_rank(gene, tmp_path):
    """Rank 0 alone takes the run's lock; refused, it stops the other rank too."""
    from mpnode_cli.training.runlock import lock_run

    loop.train(small(gene, tmp_path / "run", epochs=1))
    held = lock_run(tmp_path / "run")  # as another training would
    try:
        spawn_two(resume_a_locked_run, tmp_path / "run")
    finally:
        held.release()
    assert [r["epoch"] for r in read_metrics(tmp_path / "run")] == [0, 1]


def test_only_rank_0_prints_an_error(gene, monkeypatch, tmp_path):
    monkeypatch.setenv("RANK", "1")
    result = CliRunner().invoke(app, ["train", str(tmp_path / "missing.h5")])
    assert result.exit_code == 2 and result.output == ""
    monkeypatch.setenv("RANK", "0")
    result = CliRunner().invoke(app, ["train", str(tmp_path / "missing.h5")])
    assert result.exit_code == 2 and result.output.startswith("Error:")
