"""Devices and data parallelism for every trainer under ``torchrun`` (gloo on the CPU, NCCL on GPUs).

The batched agent trainer steps its own episodes on every rank and averages gradients with one all-reduce per
update; pretraining wraps its model in DistributedDataParallel. Without ``torchrun`` (``WORLD_SIZE`` unset or
1) and without an existing process group everything here is a no-op.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist


def resolve_device(name: str) -> torch.device:
    """``auto`` (CUDA when present), ``cpu``, ``cuda`` (this process's ``LOCAL_RANK`` GPU) or ``cuda:<i>``;
    ``ValueError`` for another name or CUDA without a GPU."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cpu":
        return torch.device("cpu")
    if name == "cuda" or name.startswith("cuda:"):
        if not torch.cuda.is_available():
            raise ValueError(f"device {name!r} requested but CUDA is not available")
        return torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0))) if name == "cuda" else torch.device(name)
    raise ValueError(f"unknown device {name!r} (auto, cpu, cuda)")


@dataclass
class DistInfo:
    """This process in its process group (rank 0 of 1 when not distributed)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    owns_group: bool = False
    """This process created the group (and destroys it when done)."""

    @property
    def enabled(self) -> bool:
        return self.world > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def init_distributed(device: torch.device) -> DistInfo:
    """Join the process group when one exists already or when launched by ``torchrun`` (``WORLD_SIZE > 1``);
    returns this process's rank and world size."""
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if dist.is_available() and dist.is_initialized():
        info = DistInfo(dist.get_rank(), dist.get_world_size(), local, owns_group=False)
    elif int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return DistInfo()
    else:
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        info = DistInfo(dist.get_rank(), dist.get_world_size(), local, owns_group=True)
    if device.type == "cuda":
        torch.cuda.set_device(info.local_rank)
    return info


def device_for(info: DistInfo, device: torch.device) -> torch.device:
    """The rank's device: ``cuda:<local_rank>`` for CUDA, else ``device``."""
    return torch.device("cuda", info.local_rank) if device.type == "cuda" else device


def allreduce_gradients(model: torch.nn.Module, info: DistInfo) -> None:
    """Average the gradients of ``model`` over ranks (one flat all-reduce)."""
    if not info.enabled:
        return
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    flat = torch.cat([g.reshape(-1) for g in grads])
    dist.all_reduce(flat)
    flat /= info.world
    i = 0
    for g in grads:
        n = g.numel()
        g.copy_(flat[i:i + n].view_as(g))
        i += n


def all_sum(values: list[float], info: DistInfo, device: torch.device) -> list[float]:
    """Sum a few numbers over ranks."""
    if not info.enabled:
        return list(values)
    t = torch.tensor(values, dtype=torch.float64, device=device)
    dist.all_reduce(t)
    return t.tolist()


def broadcast_model(model: torch.nn.Module, info: DistInfo) -> None:
    """Copy rank 0's weights to every rank."""
    if info.enabled:
        for p in model.state_dict().values():
            dist.broadcast(p, 0)


def barrier(info: DistInfo) -> None:
    if info.enabled:
        dist.barrier()
