"""Devices, CPU threads and data parallelism for every trainer under ``torchrun`` (gloo on the CPU, NCCL on GPUs), or in
processes started here (:func:`run_ranks`: ``tsnav train --procs N`` on one machine's CPU cores).

The batched agent trainer steps its own episodes on every rank and averages gradients with one all-reduce per
update; pretraining wraps its model in DistributedDataParallel. Without ``torchrun`` (``WORLD_SIZE`` unset or
1) and without an existing process group everything here is a no-op.
"""

from __future__ import annotations

import multiprocessing
import os
import shutil
import sys
import tempfile
import traceback
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any, Callable

import torch
import torch.distributed as dist


def set_threads(n: int) -> int:
    """Set this process's torch intra-op CPU threads to ``n`` (at least 1); returns the number set. The one
    place tsnav sets them (trainers, their workers and ranks, commands)."""
    n = max(1, int(n))
    torch.set_num_threads(n)
    return n


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
    _copy_flat(flat, grads)


def _copy_flat(flat: torch.Tensor, tensors: list[torch.Tensor]) -> None:
    """Copy consecutive slices of ``flat`` into ``tensors`` (the layout of ``torch.cat`` of their flattenings)."""
    i = 0
    for t in tensors:
        n = t.numel()
        t.copy_(flat[i : i + n].view_as(t))
        i += n


def gather_gradients(model: torch.nn.Module, info: DistInfo) -> list[torch.Tensor]:
    """Every rank's gradients of ``model``, flat, in rank order (one all-gather; every parameter must have a
    gradient). Without a process group: this process's alone."""
    grads = [p.grad for p in model.parameters()]
    if any(g is None for g in grads):
        raise ValueError("gather_gradients: a parameter has no gradient (it did not take part in the loss)")
    flat = torch.cat([g.reshape(-1) for g in grads])
    if not info.enabled:
        return [flat]
    out = [torch.empty_like(flat) for _ in range(info.world)]
    dist.all_gather(out, flat)
    return out


def set_gradients(model: torch.nn.Module, flat: torch.Tensor) -> None:
    """Copy a flat gradient (:func:`gather_gradients`' layout) into the parameters' gradients."""
    _copy_flat(flat, [p.grad for p in model.parameters()])


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


#: Seconds a rank waits in a collective before giving up (a peer that died is usually noticed at once, when its
#: sockets close; this bounds the rest).
GROUP_TIMEOUT_S = 600


def _rank_main(fn: Callable[..., Any], rank: int, world: int, init_file: str, args: tuple, kwargs: dict) -> None:
    """Body of a started rank (1..N-1): join the group, run ``fn``, leave; a failure is printed and exits 1."""
    try:
        dist.init_process_group(
            "gloo",
            init_method=f"file://{init_file}",
            rank=rank,
            world_size=world,
            timeout=timedelta(seconds=GROUP_TIMEOUT_S),
        )
        try:
            fn(*args, **kwargs)
        finally:
            dist.destroy_process_group()
    except BaseException:
        print(f"rank {rank}: " + traceback.format_exc(), file=sys.stderr, flush=True)
        sys.exit(1)


@contextmanager
def spawnable_main():
    """While processes are started with ``spawn``: hide a ``__main__`` whose file does not exist (a script piped to
    ``python -``, whose ``__file__`` is ``<stdin>``). A spawned child re-runs the parent's main file by path; with
    none on disk it dies at start (``FileNotFoundError: '<stdin>'``), which breaks a process pool. The functions
    tsnav sends to its children live in importable modules, so the children need nothing of such a main; a main
    that is a real file, a module (``python -m``) or absent (``python -c``) is left as it is."""
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    hide = (
        path is not None
        and getattr(main, "__spec__", None) is None
        and not os.path.isfile(path if os.path.isabs(path) else os.path.join(os.getcwd(), path))
    )
    if hide:
        del main.__file__
    try:
        yield
    finally:
        if hide:
            main.__file__ = path


def trim_memory() -> bool:
    """Give the memory this process has freed back to the system: ``gc.collect()``, then glibc's ``malloc_trim(0)``.

    glibc keeps freed heap memory mapped (its mmap threshold rises after a large free, so arrays allocated later
    come from the heap), so a long-lived process that once held a large dataset keeps its peak RSS after letting it
    go: the `tsnav experiment` parent held 11 GB after its in-process pretraining while its jobs ran beside it.
    Called after such stages. Returns whether memory was trimmed (False where there is no glibc)."""
    import ctypes
    import ctypes.util
    import gc

    gc.collect()
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):  # musl and other C libraries have no malloc_trim
        return False
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    trim(0)
    return True


class _SpawnableProcess(multiprocessing.context.SpawnProcess):
    """A ``spawn`` process whose start hides a missing main file (:func:`spawnable_main`)."""

    def start(self) -> None:
        with spawnable_main():
            super().start()


class _SpawnableContext(multiprocessing.context.SpawnContext):
    Process = _SpawnableProcess


_SPAWN = _SpawnableContext()


def spawn_context() -> multiprocessing.context.SpawnContext:
    """The ``spawn`` multiprocessing context every tsnav process is started from: its processes (and so the
    workers of a ``Pool`` or ``ProcessPoolExecutor`` given it as context) start under :func:`spawnable_main`,
    so a parent run as ``python -`` can start them. Used wherever tsnav starts processes, in place of
    ``multiprocessing.get_context("spawn")``."""
    return _SPAWN


def run_ranks(fn: Callable[..., Any], procs: int, *args, rank0_kwargs: dict | None = None, **kwargs) -> Any:
    """Run ``fn(*args, **kwargs)`` as ``procs`` ranks of one gloo process group on this machine's CPU cores and
    return rank 0's result.

    This process is rank 0 (so its return value, callbacks given in ``rank0_kwargs`` and progress output stay
    here); ranks 1..N-1 are started with the ``spawn`` method (a fresh interpreter: no forked torch threads),
    and rendezvous through a file in a temporary folder (no port to choose or collide on). The arguments go to
    the started ranks by multiprocessing's own transport, in memory; nothing is written to disk. When rank 0
    fails or is interrupted the other ranks are terminated; when another rank fails, rank 0 raises
    ``RuntimeError`` naming it. ``procs == 1``, an existing process group, or a process launched by ``torchrun``
    (``WORLD_SIZE`` > 1: already one of the ranks) just calls ``fn`` here.
    """
    if procs < 1:
        raise ValueError(f"procs must be >= 1, got {procs}")
    if procs == 1 or (dist.is_available() and dist.is_initialized()) or int(os.environ.get("WORLD_SIZE", "1")) > 1:
        return fn(*args, **{**kwargs, **(rank0_kwargs or {})})
    tmp = Path(tempfile.mkdtemp(prefix="tsnav_ranks_"))
    init_file = str(tmp / "rendezvous")
    ctx = spawn_context()
    children = [
        ctx.Process(target=_rank_main, args=(fn, r, procs, init_file, args, kwargs), daemon=True)
        for r in range(1, procs)
    ]
    try:
        for c in children:
            c.start()
        dist.init_process_group(
            "gloo",
            init_method=f"file://{init_file}",
            rank=0,
            world_size=procs,
            timeout=timedelta(seconds=GROUP_TIMEOUT_S),
        )
        try:
            result = fn(*args, **{**kwargs, **(rank0_kwargs or {})})
        except BaseException as e:
            if isinstance(e, RuntimeError):  # gloo's error when a peer died: give that peer time to exit
                for c in children:
                    c.join(timeout=30)
            failed = [r for r, c in enumerate(children, 1) if c.exitcode not in (None, 0)]
            if failed:  # rank 0 saw the collective break because another rank died first
                raise RuntimeError(f"rank {failed[0]} of {procs} failed (its error is printed above)") from None
            raise
        finally:
            dist.destroy_process_group()
        for r, c in enumerate(children, 1):
            c.join()
            if c.exitcode != 0:
                raise RuntimeError(f"rank {r} of {procs} failed (exit code {c.exitcode}; its error is printed above)")
        return result
    finally:
        for c in children:
            if c.is_alive():
                c.terminate()
            c.join()
        shutil.rmtree(tmp, ignore_errors=True)
