"""Data-parallel training over the processes `torchrun` starts, with `torch.distributed`.

    torchrun --nproc-per-node K -m mpnode_cli train DATASET ...

Every process (rank) holds the whole model and the whole dataset, draws the same batch
order and noise from the same seeded generator, and computes the loss of its own
contiguous slice of every global batch. The update is the one a single process makes
from that global batch:

- each rank's gradient is scaled by its share of the batch (n_r / n) and the gradients are
  summed over ranks, which gives the gradient of the batch's mean loss even when the
  slices differ in size (every loss here is a mean over the trajectories of a batch);
- the clip to the global gradient norm comes after the sum, so it sees the global norm;
- whether a batch is skipped (a failed solve or a non-finite loss on any rank) is agreed
  by a sum over ranks before any backward pass, so ranks never diverge;
- validation is sharded the same way and its error sums are added up, so that every rank
  sees the same validation loss and takes the same plateau and best-epoch decisions.

The sums are `torch.distributed.all_reduce` calls (gloo on CPU, NCCL on CUDA: the backends
PyTorch's distributed documentation recommends for each). `DistributedDataParallel` is not
used: it averages gradients over ranks with equal weights (n / K trajectories assumed on
each), it hooks the module's `forward` while training calls `training_loss`, and a rank
that skips a backward pass leaves the others waiting in theirs. One all-reduce of the
flattened gradients per step is what DDP's bucketing amounts to for these models: its
default bucket (25 MiB) holds all of MP-NODE's gradients (a few thousand parameters) and
L2S's (1.4 million, 5.6 MB, on a 4-node gene set). `DistributedSampler` is not used
either: it pads the epoch with repeated samples and shuffles with its own per-epoch seed,
so the global batches would not be one process's.

Rank 0 alone writes the run folder and reports progress; the loop asks `World.main`.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, TypeVar

import torch
import torch.distributed as dist

from mpnode_cli.devices import torch_device

T = TypeVar("T")


@dataclass(frozen=True)
class World:
    """This process's place among the training processes.

    Attributes:
        rank: 0 … size − 1 (0 writes files and reports). size: processes in all (1 without
            torchrun). backend: "gloo", "nccl", or None for a single process.
    """

    rank: int = 0
    size: int = 1
    backend: str | None = None

    @property
    def main(self) -> bool:
        return self.rank == 0

    def shard(self, n: int) -> slice:
        """This rank's contiguous part of `n` items; parts differ in size by at most one
        (`torch.tensor_split`'s), and a rank gets none when `n` < size."""
        q, r = divmod(n, self.size)
        lo = self.rank * q + min(self.rank, r)
        return slice(lo, lo + q + (self.rank < r))

    def sum(self, values: torch.Tensor) -> torch.Tensor:
        """`values` summed over ranks (every rank gets the sum)."""
        return self._all_reduce(values, dist.ReduceOp.SUM)

    def max(self, values: torch.Tensor) -> torch.Tensor:
        """The element-wise maximum of `values` over ranks."""
        return self._all_reduce(values, dist.ReduceOp.MAX)

    def _all_reduce(self, values: torch.Tensor, op) -> torch.Tensor:
        if self.size == 1:
            return values
        if self.backend == "nccl" and values.device.type != "cuda":  # NCCL reduces on GPUs
            return self._all_reduce(values.cuda(), op).to(values.device)
        dist.all_reduce(values, op=op)
        return values

    def sum_gradients(self, params: list[torch.nn.Parameter], share: float) -> None:
        """Replace each gradient with Σ_r share_r · grad_r, the global batch's gradient.

        A parameter that no rank's loss reached keeps no gradient (None, as in one
        process, so that Adam leaves it alone); one that only some ranks reached gets the
        sum of those. A rank whose slice is empty contributes zeros.
        """
        if self.size == 1:
            return
        for group in _by_dtype_and_device([p for p in params if p.requires_grad]):
            ref = group[0]
            parts = [(p.grad * share if p.grad is not None else torch.zeros_like(p)).flatten()
                     for p in group]
            used = torch.tensor([p.grad is not None for p in group], dtype=ref.dtype,
                                device=ref.device)
            flat = self.sum(torch.cat([*parts, used]))  # one all-reduce per dtype
            offset = 0
            for p, reached in zip(group, flat[-len(group):].tolist(), strict=True):
                n = p.numel()
                p.grad = flat[offset:offset + n].view_as(p).clone() if reached else None
                offset += n

    def broadcast_module(self, module: torch.nn.Module) -> None:
        """Give every rank rank 0's parameters and buffers (they are built from one seed,
        but a start that is the same by construction should be checked to be)."""
        if self.size == 1:
            return
        with torch.no_grad():
            for tensor in [*module.parameters(), *module.buffers()]:
                dist.broadcast(tensor, src=0)

    def from_main(self, make: Callable[[], T]) -> T:
        """Run `make` on rank 0 and give its result (any picklable value) to every rank.

        An exception on rank 0 is re-raised there and raised on the others as a
        `ValueError` with the same message, so that no rank waits on one that has failed.
        """
        if self.size == 1:
            return make()
        box: list[Any] = [None, None]
        if self.main:
            try:
                box[0] = make()
            except Exception as exc:
                box[1] = str(exc)
                dist.broadcast_object_list(box, src=0)
                raise
        dist.broadcast_object_list(box, src=0)
        if box[1] is not None:
            raise ValueError(box[1])
        return box[0]


def world() -> World:
    """The world of the initialized default process group, else a single process."""
    if dist.is_available() and dist.is_initialized():
        return World(dist.get_rank(), dist.get_world_size(), str(dist.get_backend()))
    return World()


def launched_size() -> int:
    """WORLD_SIZE as torchrun sets it (1 when not launched by torchrun)."""
    return int(os.environ.get("WORLD_SIZE", "1") or 1)


@contextmanager
def process_group(device: str) -> Iterator[World]:
    """Join the processes torchrun started, for the duration of the block.

    torchrun sets WORLD_SIZE, RANK, LOCAL_RANK, MASTER_ADDR and MASTER_PORT in each
    process (https://pytorch.org/docs/stable/elastic/run.html), and
    `init_process_group` reads them (the env:// method). On CUDA each process takes the GPU
    LOCAL_RANK of its machine. Outside torchrun, or with one process, nothing happens. A
    group that is already there (a caller initialized it) is used and left in place.

    Raises:
        ValueError: CUDA asked for but absent, too few GPUs for the processes on this
            machine, or torchrun's variables incomplete (one line).
    """
    size = launched_size()
    if size <= 1 or dist.is_initialized():
        yield world()
        return
    if not dist.is_available():
        raise ValueError("this torch build has no torch.distributed: run one process")
    backend = "gloo"
    if device == "cuda":
        local = int(os.environ.get("LOCAL_RANK", "0"))
        torch_device("cuda")
        if local >= torch.cuda.device_count():
            raise ValueError(f"process LOCAL_RANK {local} needs a GPU of its own, but this "
                             f"machine has {torch.cuda.device_count()}: start at most that "
                             "many processes per node (--nproc-per-node)")
        torch.cuda.set_device(local)
        backend = "nccl"
    try:
        dist.init_process_group(backend)
    except (RuntimeError, ValueError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"could not join torchrun's {size} processes ({backend}): {first}"
                         ) from None
    try:
        yield world()
    finally:
        dist.destroy_process_group()


def _by_dtype_and_device(params: list[torch.nn.Parameter]) -> list[list[torch.nn.Parameter]]:
    groups: dict[tuple[torch.dtype, torch.device], list[torch.nn.Parameter]] = {}
    for p in params:
        groups.setdefault((p.dtype, p.device), []).append(p)
    return list(groups.values())
