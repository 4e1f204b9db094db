"""Process-group handling: the same code runs alone or under ``torchrun`` (DistributedDataParallel).

When ``WORLD_SIZE`` is set (torchrun sets it), the process group starts with NCCL on GPUs or gloo on CPUs,
each process trains on its shard of every epoch (:class:`torch.utils.data.DistributedSampler`), gradients are
averaged by DDP, and only rank 0 validates, writes checkpoints and logs and shows progress.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as torch_dist
from torch import nn
from torch.nn.parallel import DistributedDataParallel


@dataclass(frozen=True)
class Dist:
    rank: int = 0
    world: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")
    enabled: bool = False

    @property
    def main(self) -> bool:
        return self.rank == 0


def setup() -> Dist:
    """Start the process group when launched by torchrun; choose the device (this rank's GPU, else the CPU)."""
    cuda = torch.cuda.is_available()
    if "WORLD_SIZE" not in os.environ:
        return Dist(device=torch.device("cuda" if cuda else "cpu"))
    local_rank = int(os.environ.get("LOCAL_RANK", 0))
    if cuda:
        torch.cuda.set_device(local_rank)
    if not torch_dist.is_initialized():
        torch_dist.init_process_group(backend="nccl" if cuda else "gloo")
    device = torch.device("cuda", local_rank) if cuda else torch.device("cpu")
    return Dist(torch_dist.get_rank(), torch_dist.get_world_size(), local_rank, device, True)


def cleanup(dist: Dist) -> None:
    if dist.enabled and torch_dist.is_initialized():
        torch_dist.destroy_process_group()


def wrap(module: nn.Module, dist: Dist) -> nn.Module:
    """DDP around the module being trained (alone: the module itself)."""
    if not dist.enabled:
        return module
    device_ids = [dist.local_rank] if dist.device.type == "cuda" else None
    return DistributedDataParallel(module, device_ids=device_ids)


def broadcast(value, dist: Dist):
    """Rank 0's ``value`` on every rank (any picklable object)."""
    if not dist.enabled:
        return value
    box = [value]
    torch_dist.broadcast_object_list(box, src=0)
    return box[0]


def all_reduce_max(value: int, dist: Dist) -> int:
    """The largest ``value`` over the ranks (so that a stop request seen by one rank stops all)."""
    if not dist.enabled:
        return value
    tensor = torch.tensor([value], dtype=torch.int64, device=dist.device if dist.device.type == "cuda" else "cpu")
    torch_dist.all_reduce(tensor, op=torch_dist.ReduceOp.MAX)
    return int(tensor.item())
