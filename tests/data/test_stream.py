"""Streamed training (`mpnode train --stream`): batches read from the file on demand.

References: numpy moments of the whole array, the in-memory `TrajectoryData`, and the
in-memory training run of the same config.
"""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from mpnode_cli.cli.app import app
from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.config.train import TrainConfig
from mpnode_cli.data import stream as stream_module
from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.data.generate import generate
from mpnode_cli.data.hdf5 import Dataset
from mpnode_cli.data.hdf5_write import write_dataset
from mpnode_cli.data.stream import StreamedTrajectories, prefetched
from mpnode_cli.graphs.matrices import Graphs
from mpnode_cli.training.evaluate import baseline_mse
from mpnode_cli.training.loop import TrainingInterrupted, train
from mpnode_cli.training.run import read_metrics

runner = CliRunner()


@pytest.fixture(scope="module")
def gene(tmp_path_factory):
    """Gene dynamics on three graphs of a 2×2 grid: 40 trajectories × 11 samples."""
    out = tmp_path_factory.mktemp("data") / "gene.h5"
    generate(GenerateConfig(system="gene", grid=2, topology="er", graphs=3, trajectories=40,
                            t_end=1.0, dt=0.1, out=out))
    return out


@pytest.fixture(scope="module")
def controlled(tmp_path_factory):
    """Random states far from zero (mean ~1e3) and controls: 30 × 7 samples × 4 nodes."""
    rng = np.random.default_rng(5)
    k, t, n = 30, 7, 4
    states = (1e3 + rng.normal(size=(k, t, n, 2)) * [1.0, 1e-3]).astype(np.float32)
    out = tmp_path_factory.mktemp("data") / "custom.h5"
    write_dataset(out, Dataset(
        system="custom", dt=0.1, state_names=("p", "q"), control_names=("u",), seed=0,
        config={}, time=np.arange(t) * 0.1, states=states,
        controls=rng.normal(size=(k, t, n, 1)).astype(np.float32) * 3 - 1,
        graphs=Graphs.from_adjacency(
            np.ones((1, n, n), np.uint8) - np.eye(n, dtype=np.uint8)[None]),
        graph_index=np.zeros(k, np.int32), split=(np.arange(k) % 3).astype(np.uint8)))
    return out


def test_streamed_normalizer_equals_numpy_moments(controlled, monkeypatch):
    monkeypatch.setattr(stream_module, "_BLOCK_VALUES", 7 * 4 * 2 * 3)  # blocks of 3
    data = StreamedTrajectories.open(controlled).subset("train")
    fitted = data.fit_normalizer()
    whole = TrajectoryData.load(controlled).subset("train")
    x = whole.states.numpy().astype(np.float64).reshape(-1, 2)
    u = whole.controls.numpy().astype(np.float64).reshape(-1, 1)
    np.testing.assert_allclose(fitted.x_mean, x.mean(axis=0), rtol=1e-6)
    np.testing.assert_allclose(fitted.x_std, x.std(axis=0), rtol=1e-6)
    np.testing.assert_allclose(fitted.u_mean, u.mean(axis=0), rtol=1e-6)
    np.testing.assert_allclose(fitted.u_std, u.std(axis=0), rtol=1e-6)


def test_take_reads_what_memory_holds(gene):
    memory, disk = TrajectoryData.load(gene), StreamedTrajectories.open(gene)
    assert disk.fingerprint == memory.fingerprint
    index = torch.tensor([7, 2, 27, 2, 0])  # any order, repeats too
    a, b = memory.subset("train").take(index), disk.subset("train").take(index)
    for name in ("states", "adjacency", "split", "graph_index"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert torch.equal(disk.graph(), memory.graph())
    assert torch.equal(disk.split, memory.split)


def test_streamed_baselines_equal_in_memory(gene, monkeypatch):
    monkeypatch.setattr(stream_module, "_BLOCK_VALUES", 11 * 4 * 7)  # blocks of 7
    memory, disk = TrajectoryData.load(gene), StreamedTrajectories.open(gene)
    norm = disk.subset("train").fit_normalizer()
    want = baseline_mse(memory.subset("train"), memory.subset("test"), norm)
    have = baseline_mse(disk.subset("train"), disk.subset("test"), norm)
    assert have == pytest.approx(want, rel=1e-12)


def prefetch_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "mpnode-prefetch"]


def test_prefetch_reads_in_order_and_at_most_depth_ahead(gene, monkeypatch):
    disk = StreamedTrajectories.open(gene)
    indices = [torch.tensor([i]) for i in range(10)]
    reads = []
    take = StreamedTrajectories.take

    def counting(self, index, f=None):
        reads.append(int(index[0]))
        return take(self, index, f)

    monkeypatch.setattr(StreamedTrajectories, "take", counting)
    with prefetched(disk, indices, depth=2) as batches:
        first = next(batches)
        time.sleep(0.3)  # the reader fills the queue and waits
        # One handed out, two waiting in the queue, one read and waiting for room.
        assert len(reads) <= 4
        rest = list(batches)
    assert reads == list(range(10))
    memory = TrajectoryData.load(gene)
    for i, batch in enumerate([first, *rest]):  # in order
        assert torch.equal(batch.states, memory.states[i:i + 1])
    assert not prefetch_threads()


def test_prefetch_stops_on_error_and_on_leaving_early(gene, monkeypatch):
    disk = StreamedTrajectories.open(gene)
    indices = [torch.tensor([i]) for i in range(10)]
    with prefetched(disk, indices) as batches:  # the loop stops after one batch
        next(batches)
    assert not prefetch_threads()
    with pytest.raises(KeyboardInterrupt), prefetched(disk, indices) as batches:
        next(batches)
        raise KeyboardInterrupt
    assert not prefetch_threads()

    take = StreamedTrajectories.take

    def failing(self, index, f=None):
        if int(index[0]) == 3:
            raise OSError("disk gone")
        return take(self, index, f)

    monkeypatch.setattr(StreamedTrajectories, "take", failing)
    seen = []
    # Raised where the file is read, an OSError is HDF5's: one line naming the file.
    with pytest.raises(ValueError, match="disk gone"), prefetched(disk, indices) as batches:
        for batch in batches:
            seen.append(batch)
    assert len(seen) == 3 and not prefetch_threads()


def test_a_file_replaced_while_streaming_is_refused(gene, tmp_path):
    """The run's file is pinned when it is opened: replaced since (here by a copy of the
    same data: a new file all the same), each pass and read refuses it in one line rather
    than training on whatever is there now."""
    import shutil

    path = tmp_path / "gene.h5"
    shutil.copy(gene, path)
    disk = StreamedTrajectories.open(path)
    assert len(list(disk.blocks())) >= 1
    shutil.copy(gene, tmp_path / "new.h5")
    (tmp_path / "new.h5").replace(path)
    def prefetch():  # an epoch's pass
        with prefetched(disk, [torch.tensor([i]) for i in range(3)]) as batches:
            list(batches)

    for read in (lambda: list(disk.blocks()), lambda: disk.take(torch.tensor([0])), prefetch):
        with pytest.raises(ValueError, match=f"{path} changed while this run was reading"):
            read()


def metrics(run_dir) -> list[tuple]:
    return [(r["epoch"], r["train_loss"], r["val_loss"], r["val_mse"])
            for r in read_metrics(run_dir)]


def assert_same_losses(a, b):
    assert [r[0] for r in a] == [r[0] for r in b]
    for row_a, row_b in zip(a, b, strict=True):
        for x, y in zip(row_a[1:], row_b[1:], strict=True):
            assert (x is None and y is None) or x == pytest.approx(y, rel=1e-5)


def test_streamed_cli_training_equals_in_memory_and_resumes(gene, tmp_path):
    config = tmp_path / "train.toml"
    config.write_text("[solver]\ncompile = false\n")  # tests never compile
    common = [str(gene), "--config", str(config), "--batch-size", "8", "--lr", "1e-2",
              "--no-plots"]

    def run(name, *args):
        result = runner.invoke(app, ["train", *common, "--run-dir", str(tmp_path / name),
                                     *args])
        assert result.exit_code == 0, result.output
        return result

    run("memory", "--epochs", "2")
    streamed = run("stream", "--epochs", "2", "--stream")
    assert "streamed from the file" in streamed.output
    assert json.loads((tmp_path / "stream" / "config.json").read_text())["stream"] is True
    assert json.loads((tmp_path / "memory" / "config.json").read_text())["stream"] is False
    memory = metrics(tmp_path / "memory")
    assert_same_losses(metrics(tmp_path / "stream"), memory)
    summaries = [json.loads((tmp_path / n / "summary.json").read_text())
                 for n in ("memory", "stream")]
    assert summaries[1]["test"]["mse"] == pytest.approx(summaries[0]["test"]["mse"], rel=1e-5)
    assert summaries[1]["baselines"] == pytest.approx(summaries[0]["baselines"], rel=1e-9)

    # Streamed for one epoch, resumed streamed for the second: the same two epochs.
    run("resumed", "--epochs", "1", "--stream")
    result = runner.invoke(app, ["train", "--resume", str(tmp_path / "resumed"), "--epochs",
                                 "2", "--stream"])
    assert result.exit_code == 0, result.output
    assert_same_losses(metrics(tmp_path / "resumed"), memory)


def test_streamed_finetune_equals_in_memory(gene, tmp_path):
    base = TrainConfig(dataset=gene, run_dir=tmp_path / "parent", epochs=1, batch_size=8,
                       plots=False, solver={"compile": False})
    train(base)
    parent = tmp_path / "parent" / "checkpoints" / "best.pt"
    for stream in (False, True):
        train(base.model_copy(update={"run_dir": tmp_path / f"ft-{stream}", "stream": stream,
                                      "init_checkpoint": parent, "renormalize": True,
                                      "epochs": 2}))
    assert_same_losses(metrics(tmp_path / "ft-True"), metrics(tmp_path / "ft-False"))


def test_interrupted_streamed_training_leaves_no_thread(gene, tmp_path):
    def interrupt(event):
        if event["event"] == "batch" and event["epoch"] == 2 and event["batch"] == 2:
            raise KeyboardInterrupt

    config = TrainConfig(dataset=gene, run_dir=tmp_path / "cut", epochs=3, batch_size=4,
                         plots=False, stream=True, solver={"compile": False})
    with pytest.raises(TrainingInterrupted) as info:
        train(config, progress=interrupt)
    assert info.value.epoch == 1 and not prefetch_threads()
