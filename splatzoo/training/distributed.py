"""Data-parallel training over processes (torch.distributed): what the training step needs from the process group.

Every rank holds the whole model and the same random generator, so every rank draws the same views and takes the
same decisions; each renders its share of a step's views, and gradients (and, before a densification decision,
the densification statistics) are summed over the ranks. One process is `Comm()`, which does nothing.
"""
from __future__ import annotations

import os

import torch


def launched_world() -> int:
    """The number of processes when a launcher such as torchrun started this one as a rank of several (it sets
    RANK and WORLD_SIZE), else 0."""
    try:
        world = int(os.environ.get("WORLD_SIZE", "1"))
    except ValueError:
        return 0
    return world if world > 1 and "RANK" in os.environ else 0


class Comm:
    """The single-process communicator: rank 0 of 1; every reduction is the identity."""

    rank, world = 0, 1

    def sum_(self, tensors: list[torch.Tensor]) -> None:
        """Sum each tensor over the ranks, in place."""

    def any(self, flag: bool) -> bool:
        """True on every rank when `flag` is true on any."""
        return flag

    def barrier(self) -> None:
        pass


class ProcessGroupComm(Comm):
    """torch.distributed's default process group (gloo on CPU, NCCL on CUDA); collectives run on `device`, the
    training device."""

    def __init__(self, device: torch.device | str = "cpu"):
        import torch.distributed as dist

        self.dist = dist
        self.device = torch.device(device)
        self.rank, self.world = dist.get_rank(), dist.get_world_size()

    def sum_(self, tensors: list[torch.Tensor]) -> None:
        if not tensors:
            return
        # one flat buffer: one collective per step instead of one per parameter
        device = self.device
        flat = torch.cat([t.reshape(-1).to(device, torch.float32) for t in tensors])
        self.dist.all_reduce(flat)
        offset = 0
        for t in tensors:
            n = t.numel()
            t.copy_(flat[offset:offset + n].view_as(t).to(t.device, t.dtype))
            offset += n

    def any(self, flag: bool) -> bool:
        t = torch.tensor([1.0 if flag else 0.0], device=self.device)
        self.dist.all_reduce(t)
        return bool(t.item() > 0)

    def barrier(self) -> None:
        self.dist.barrier()
