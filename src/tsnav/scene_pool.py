"""Per-scene work over several CPU processes: the feature caches and detection tables of many rooms (issue 26, both
cores in every long stage).

Each room is independent: a worker computes one room's array on **one torch thread** and writes its file
atomically, so the files are the same bytes whatever the number of workers, and the same as the one-thread loop
in this process (``workers=1``, the reference :func:`map_scenes` falls back to; tests hold the two together).
Workers are started with ``spawn`` (no forked torch state); the model they run is sent to each worker once, when it
starts, by multiprocessing's own transport in memory (nothing written to disk, nothing a user exchanges).
"""

from __future__ import annotations

import os
import signal
import sys
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from typing import Any, Callable, Iterable, Iterator

import torch

from .distributed import set_threads, spawn_context

#: The state a worker keeps between its tasks (set once by :func:`_init`).
_STATE: dict[str, Any] = {}


#: At most this many default workers: each holds a copy of the model and one room's frames.
MAX_DEFAULT_WORKERS = 8


def default_workers() -> int:
    """Worker processes for per-scene work: the CPU cores this process may use, at most
    :data:`MAX_DEFAULT_WORKERS`."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        n = os.cpu_count() or 1
    return max(1, min(n, MAX_DEFAULT_WORKERS))


def as_is(x: Any) -> Any:
    """The ``setup`` of :func:`map_scenes` when the object sent to the workers is their context as it is."""
    return x


def _init(setup: Callable[[Any], Any], arg: Any) -> None:
    signal.signal(signal.SIGTERM, _exit_on_term)  # a terminated worker unwinds: atomic writes remove their temp files
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    set_threads(1)
    _STATE["ctx"] = setup(arg)


def _exit_on_term(signum, frame):
    sys.exit(128 + signum)


def map_scenes(
    fn: Callable[[Any, Any], Any], items: Iterable[Any], setup: Callable[[Any], Any], arg: Any, workers: int = 1
) -> Iterator[tuple[int, Any]]:
    """Yield ``(index, fn(ctx, item))`` for every item, where ``ctx = setup(arg)`` is built once per process.

    ``workers`` <= 1, or a single item: in this process on one torch thread (the caller's count restored), in
    order. Otherwise a ``spawn`` pool of ``min(workers, len(items))`` processes on one thread each; results come in
    the order they finish. ``fn`` and ``setup`` must be module-level functions (they are sent by name). An error
    in a worker is raised here (a worker that dies outright: ``BrokenProcessPool``); the items not started are
    cancelled and the running ones finished before it propagates.
    """
    items = list(items)
    n = min(max(1, workers), len(items))
    if n <= 1:
        before = torch.get_num_threads()
        set_threads(1)
        try:
            ctx = setup(arg)
            for i, item in enumerate(items):
                yield i, fn(ctx, item)
        finally:
            set_threads(before)
        return
    pool = ProcessPoolExecutor(n, mp_context=spawn_context(), initializer=_init, initargs=(setup, arg))
    try:
        pending = {pool.submit(fn_at, fn, item): i for i, item in enumerate(items)}
        while pending:  # a worker that dies without an exception breaks the pool: BrokenProcessPool, no hang
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for f in done:
                yield pending.pop(f), f.result()
    except BaseException:  # an error or Ctrl-C here: the workers are stopped (SIGTERM; their temp files removed)
        _terminate_workers(pool)
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _terminate_workers(pool: ProcessPoolExecutor) -> None:
    """SIGTERM to the pool's live workers: ``terminate_workers()`` where Python has it (3.14 and later); before
    that the executor keeps its processes only in the private ``_processes`` mapping, read here and nowhere else."""
    public = getattr(pool, "terminate_workers", None)
    if public is not None:
        public()
        return
    for proc in list((getattr(pool, "_processes", None) or {}).values()):
        if proc.is_alive():
            proc.terminate()


def fn_at(fn: Callable[[Any, Any], Any], item: Any) -> Any:
    """``fn(ctx, item)`` in a worker, with the worker's context."""
    return fn(_STATE["ctx"], item)
