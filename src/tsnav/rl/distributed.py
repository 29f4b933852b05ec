"""Data parallelism for the batched trainer under ``torchrun`` (gloo on the CPU, NCCL on GPUs).

Every rank steps its own episodes with its own seed; gradients are averaged with one all-reduce per update,
so all ranks keep identical weights. Without ``torchrun`` (``WORLD_SIZE`` unset or 1) everything is a no-op.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist


@dataclass
class DistInfo:
    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def enabled(self) -> bool:
        return self.world > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def init_distributed(device: torch.device) -> DistInfo:
    """Join the process group when launched by ``torchrun``; returns this process's rank and world size."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return DistInfo()
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    info = DistInfo(dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", "0")))
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
