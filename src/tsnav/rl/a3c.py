"""Asynchronous advantage actor-critic, the paper's trainer (III-D; Mnih et al. 2016; the lineage's A3C).

``workers`` processes (torch.multiprocessing, spawn) share one model (``share_memory``) and one Adam
(AMSGrad) whose moment estimates and step counters live in shared memory (:class:`SharedAdam`). Each worker
owns a :class:`~tsnav.sim.batch.BatchEnv` with a single episode (``num_envs = 1``, the lineage's one episode
per worker) and a local copy of the model. Per update a worker

1. copies the shared weights into its local model,
2. collects a rollout of ``rollout_steps`` steps (the same rollout, GAE and loss as the batched trainer),
3. back-propagates on the local model, clips the gradient norm, hands the gradients to the shared
   parameters and steps the shared optimizer (Hogwild: no lock, as in the lineage).

Counters (updates, environment steps, episodes) are shared; finished-episode statistics and losses go to the
main process through a queue. The main process logs, checkpoints every ``checkpoint_every`` updates and stops
the workers when the budget is used up. Resume restores weights, optimizer state and counters; the episodes in
flight and the workers' RNG streams start anew (A3C is not deterministic anyway).
"""

from __future__ import annotations

import queue as queue_mod
import time
import traceback
from pathlib import Path

import numpy as np
import torch
import torch.multiprocessing  # noqa: F401  (registers the shared-memory transport of tensors sent to the workers)

from ..agent.model import ActorCritic, AgentConfig
from ..distributed import set_threads, spawn_context
from .assemble import load_bank, make_model, make_observer, make_train_env
from .checkpoint import save_checkpoint
from .config import TrainConfig
from .logger import LogWindow
from .progress import RunOutput, budget_used, resume_progress, schedule_lr
from .rollout import RolloutCollector, collect_and_loss


class SharedAdam(torch.optim.Adam):
    """Adam (AMSGrad by default, as the lineage) whose state is allocated up front in shared memory, so that
    every worker process steps the same moments and step counters."""

    def __init__(
        self,
        params,
        lr: float = 1e-4,
        betas=(0.9, 0.999),
        eps: float = 1e-8,
        weight_decay: float = 0.0,
        amsgrad: bool = True,
    ):
        super().__init__(params, lr=lr, betas=betas, eps=eps, weight_decay=weight_decay, amsgrad=amsgrad, foreach=False)
        for group in self.param_groups:
            for p in group["params"]:
                st = self.state[p]
                st["step"] = torch.zeros((), dtype=torch.float32).share_memory_()
                st["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format).share_memory_()
                st["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format).share_memory_()
                if amsgrad:
                    st["max_exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format).share_memory_()

    def load_shared(self, other: torch.optim.Optimizer) -> None:
        """Copy the state of ``other`` (same parameters, e.g. loaded from a checkpoint) into the shared tensors."""
        for group, ogroup in zip(self.param_groups, other.param_groups):
            for k, v in ogroup.items():
                if k != "params":
                    group[k] = v
            for p, op in zip(group["params"], ogroup["params"]):
                for k, v in other.state[op].items():
                    self.state[p][k].copy_(v)


def a3c_update(
    local: ActorCritic,
    shared: ActorCritic,
    optimizer: torch.optim.Optimizer,
    collector: RolloutCollector,
    cfg: TrainConfig,
    update: int = 0,
):
    """One worker update (steps 1-3 of the module docstring); returns ``(loss parts, rollout)``. ``update``: the
    shared update counter when the rollout starts, which sets the learning rate of a scheduled run
    (:attr:`TrainConfig.lr_schedule`)."""
    local.load_state_dict(shared.state_dict())
    local.train()
    ro, loss, parts = collect_and_loss(collector, cfg)
    local.zero_grad(set_to_none=True)
    loss.backward()
    parts["grad_norm"] = float(torch.nn.utils.clip_grad_norm_(local.parameters(), cfg.max_grad_norm))
    for lp, sp in zip(local.parameters(), shared.parameters()):
        sp._grad = lp.grad
    schedule_lr(cfg, optimizer, update, parts)
    optimizer.step()
    return parts, ro


def _worker(
    wid: int,
    cfg_d: dict,
    agent_d: dict,
    scenes,
    shared: ActorCritic,
    optimizer: SharedAdam,
    features: torch.Tensor,
    depth,
    counters,
    out_queue,
    stop,
    seed: int,
) -> None:
    set_threads(1)
    try:
        cfg = TrainConfig.from_dict(cfg_d)
        torch.manual_seed(seed)
        bank, det = load_bank(cfg, scenes)
        agent = AgentConfig(**agent_d)
        observer = make_observer(bank, cfg, features=features, det_features=det, agent=agent, target_depth=depth)
        local = make_model(agent, observer, seed)
        collector = RolloutCollector(make_train_env(bank, cfg, 1, seed=seed), observer, local, precision=cfg.precision)
        collector.start()
        while not stop.is_set():
            parts, ro = a3c_update(local, shared, optimizer, collector, cfg, int(counters[0]))
            with counters.get_lock():
                counters[0] += 1
                counters[1] += ro.steps
                counters[2] += ro.episodes
            eps = collector.stats.pop()
            out_queue.put({"worker": wid, "parts": parts, "episodes": {k: v.tolist() for k, v in eps.items()}})
    except Exception:
        out_queue.put({"worker": wid, "error": traceback.format_exc()})
        raise


def train_a3c(
    cfg: TrainConfig,
    agent: AgentConfig,
    run_dir: str | Path,
    *,
    progress_bar: bool = True,
    scenes=None,
    poll_seconds: float = 0.2,
) -> dict:
    """Train (or resume) the A3C run in ``run_dir`` with ``cfg.workers`` processes; returns the progress."""
    run_dir = Path(run_dir)
    if agent.mirror_policy:
        raise ValueError("a mirror-symmetric agent (mirror_policy) trains with the batched trainer (--algo batched)")
    set_threads(cfg.threads)
    bank, det = load_bank(cfg, scenes)
    observer = make_observer(bank, cfg, det_features=det, agent=agent)
    features = observer.features.share_memory_()
    depth = observer.target_depth  # the depth maps, made once and shared as the features are
    if depth is not None:
        depth.maps.share_memory_()
    shared = make_model(agent, observer, cfg.seed)
    shared.share_memory()
    optimizer = SharedAdam(shared.parameters(), lr=cfg.lr, amsgrad=cfg.amsgrad)

    plain = torch.optim.Adam(shared.parameters(), lr=cfg.lr, amsgrad=cfg.amsgrad)
    progress, state = resume_progress(run_dir, shared, plain, sessions=0)  # copies into the shared parameters
    if state is not None:
        optimizer.load_shared(plain)

    def checkpoint(model: ActorCritic) -> None:
        save_checkpoint(run_dir, progress, model, optimizer, milestone_every=cfg.milestone_every)

    if budget_used(cfg, progress, lambda: checkpoint(shared)):
        return progress
    session = progress["sessions"]
    progress["sessions"] += 1

    workers = _Workers(cfg, agent, scenes, shared, optimizer, features, depth, progress, session)
    out = RunOutput(run_dir, cfg, progress, progress_bar=progress_bar)
    t_start, seconds0 = time.perf_counter(), progress["seconds"]
    last_log = progress["update"] // cfg.log_every
    last_ckpt = progress["update"] // cfg.checkpoint_every

    def snapshot() -> None:  # the workers' shared counters and this session's seconds into ``progress``
        progress["update"], progress["env_steps"], progress["episodes"] = workers.counts()
        progress["seconds"] = seconds0 + time.perf_counter() - t_start

    try:
        while True:
            time.sleep(poll_seconds)
            workers.drain(out.window)
            snapshot()
            if cfg.budget_reached(progress):
                break
            log = progress["update"] // cfg.log_every > last_log and bool(out.window)
            if log:
                last_log = progress["update"] // cfg.log_every
            out.show(progress, log)
            if progress["update"] // cfg.checkpoint_every > last_ckpt:
                last_ckpt = progress["update"] // cfg.checkpoint_every
                checkpoint(_copy(shared))
            workers.check(out.window)
        workers.finish(out.window)  # budget used up: stop the workers, keep the updates they finish meanwhile
        snapshot()
        out.show(progress, log=bool(out.window))
    finally:
        workers.close()
        out.close()
    progress["finished"] = cfg.budget_reached(progress)
    checkpoint(_copy(shared))
    return progress


class _Workers:
    """The worker processes of one session (spawned), their shared counters (updates, environment steps,
    episodes) and the queue of their messages (loss parts and finished episodes, or an error)."""

    def __init__(
        self,
        cfg: TrainConfig,
        agent: AgentConfig,
        scenes,
        shared: ActorCritic,
        optimizer: SharedAdam,
        features: torch.Tensor,
        depth,
        progress: dict,
        session: int,
    ):
        ctx = spawn_context()
        self.counters = ctx.Array("d", [progress["update"], progress["env_steps"], progress["episodes"]])
        self.queue = ctx.Queue()
        self.stop = ctx.Event()
        self.procs = []
        for w in range(cfg.workers):
            seed = int(np.random.SeedSequence([cfg.seed, w, session]).generate_state(1)[0])
            p = ctx.Process(
                target=_worker,
                args=(
                    w,
                    cfg.to_dict(),
                    agent.__dict__.copy(),
                    scenes,
                    shared,
                    optimizer,
                    features,
                    depth,
                    self.counters,
                    self.queue,
                    self.stop,
                    seed,
                ),
                daemon=True,
            )
            p.start()
            self.procs.append(p)

    def counts(self) -> tuple[int, int, int]:
        """Updates, environment steps and finished episodes so far (all workers, resumed sessions included)."""
        with self.counters.get_lock():
            return tuple(int(v) for v in self.counters[:])

    def drain(self, window: LogWindow, block: float = 0.0) -> None:
        """Add the queued messages to ``window`` (waiting up to ``block`` seconds for each); a worker's error is
        raised here."""
        while True:
            try:
                msg = self.queue.get(timeout=block) if block else self.queue.get_nowait()
            except queue_mod.Empty:
                return
            if "error" in msg:
                raise RuntimeError(f"A3C worker {msg['worker']} failed:\n{msg['error']}")
            window.add(msg["parts"], {k: np.asarray(v) for k, v in msg["episodes"].items()})

    def check(self, window: LogWindow) -> None:
        """``RuntimeError`` when a worker has exited with an error (its queued message first, when it sent one)."""
        dead = [p for p in self.procs if p.exitcode not in (None, 0)]
        if dead:
            self.drain(window)
            raise RuntimeError(f"an A3C worker exited with code {dead[0].exitcode}")

    def finish(self, window: LogWindow, timeout: float = 60) -> None:
        """Ask the workers to stop and gather what they send until they have (at most ``timeout`` seconds)."""
        self.stop.set()
        deadline = time.time() + timeout
        while any(p.is_alive() for p in self.procs) and time.time() < deadline:
            self.drain(window, block=0.1)
        self.drain(window)

    def close(self) -> None:
        """Stop every worker: joined when it ends, terminated when it does not."""
        self.stop.set()
        for p in self.procs:
            if p.is_alive():
                try:  # unblock a worker waiting on a full queue
                    while True:
                        self.queue.get_nowait()
                except (queue_mod.Empty, OSError, ValueError):
                    pass
                p.join(timeout=5)
            if p.is_alive():
                p.terminate()
                p.join(timeout=5)


def _copy(shared: ActorCritic) -> ActorCritic:
    """A private copy of the shared model (a consistent snapshot to save while workers keep updating)."""
    m = ActorCritic.from_description(shared.describe())
    m.load_state_dict({k: v.clone() for k, v in shared.state_dict().items()})
    return m
