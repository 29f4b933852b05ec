"""Batched synchronous advantage actor-critic (A2C) over ``B`` parallel episodes (paper III-D, made batched).

Same network, reward, rollout and loss as the paper's A3C (:mod:`tsnav.rl.a3c`), but one process steps
``num_envs`` episodes of a :class:`~tsnav.sim.batch.BatchEnv` together and makes one synchronous update per
rollout of ``rollout_steps`` steps, so the network runs on batches instead of single frames.

Data parallel on one machine: with ``procs`` = N (``tsnav train --procs N``, or ``torchrun --nproc-per-node N``)
N processes each step their own ``num_envs / N`` of the ``num_envs`` episodes, with their own env sampler and
action RNG, and the gradients are averaged with one all-reduce per update. Each rank's loss is the mean over its
rows of the per-row rollout loss, so the average of the N ranks' gradients is the gradient of the mean over all
``num_envs`` rows: the update of one process stepping the same ``num_envs`` episodes, and the learning rate
means the same for every N. A run is deterministic for a given (seed, procs); the episodes drawn, and so the
run, differ between values of ``procs`` (``procs`` = 1 is the single-process trainer, bit-identical to it).

With ``ranks`` = ``staggered`` the N processes each step ``num_envs`` episodes of their own instead, and a round
(one rollout per rank, from the same weights) gathers their N gradients and applies them one after another, in
rank order, each clipped and stepped by Adam as one process's would be: N updates of ``num_envs`` episodes per
round, where rank r's gradient was computed on weights r updates old (A3C's workers apply gradients of weights as
old as that). Every rank keeps the same replica of the weights and the optimizer. This mode is not bounded by the
work of a rank that does not shrink with its rows, which bounds ``split``; it is another algorithm than one
process (staler gradients), and deterministic for a given (seed, procs) as ``split`` is.

Each update, top to bottom:

1. collect a rollout of ``T`` steps (auto-reset; truncated episodes bootstrap from the critic),
2. GAE advantages and returns (gamma 0.99, tau 1.0),
3. loss = policy - 0.01 entropy + 0.5 value; backward; all-reduce; clip the gradient norm at 100,
4. Adam (AMSGrad) step.

Checkpoints every ``checkpoint_every`` updates hold weights, optimizer state, progress and every rank's RNG
states; after saving, every row starts a fresh episode. A run killed at any moment and started again
resumes from its last checkpoint and continues exactly like an uninterrupted run (bit-identical weights on
the CPU); a finished run is not retrained.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from ..agent.model import AgentConfig
from ..checkpoint import weights_digest
from ..distributed import (
    DistInfo,
    all_sum,
    allreduce_gradients,
    barrier,
    broadcast_model,
    device_for,
    gather_gradients,
    init_distributed,
    resolve_device,
    run_ranks,
    set_gradients,
    set_threads,
)
from .assemble import load_bank, make_model, make_observer, make_train_env
from .checkpoint import checkpoint_tmp, checkpoint_tmp_path, commit_checkpoint, rng_state, set_rng_state, write_rng
from .config import TrainConfig
from .progress import new_progress  # noqa: F401 (tests)
from .progress import RunOutput, budget_used, resume_progress, schedule_lr
from .rollout import RolloutCollector, collect_and_loss


def train_batched(
    cfg: TrainConfig, agent: AgentConfig, run_dir: str | Path, *, progress_bar: bool = True, on_update=None, scenes=None
) -> dict:
    """Train (or resume) the run in ``run_dir``; returns the final progress dict.

    ``on_update(progress)`` is called after every update (tests use it to interrupt a run); ``scenes``
    replaces loading ``cfg.split`` of ``cfg.data`` (the scenes still need their feature caches). With
    ``cfg.procs`` > 1 and no process group yet, this process becomes rank 0 of ``cfg.procs`` CPU processes
    (:func:`tsnav.distributed.run_ranks`); the progress bar and ``on_update`` stay with rank 0. Under
    ``torchrun`` this process is the rank torchrun made it.
    """
    launched = int(os.environ.get("WORLD_SIZE", "1")) > 1  # by torchrun: this process is one of its ranks
    if cfg.procs > 1 and not launched and not (dist.is_available() and dist.is_initialized()):
        return run_ranks(
            _train,
            cfg.procs,
            cfg,
            agent,
            run_dir,
            progress_bar=False,
            scenes=scenes,
            rank0_kwargs={"progress_bar": progress_bar, "on_update": on_update},
        )
    return _train(cfg, agent, run_dir, progress_bar=progress_bar, on_update=on_update, scenes=scenes)


def _train(
    cfg: TrainConfig, agent: AgentConfig, run_dir: str | Path, *, progress_bar: bool = True, on_update=None, scenes=None
) -> dict:
    """:func:`train_batched` in this process, as one rank of the process group when there is one."""
    run_dir = Path(run_dir)
    info, device = _join(cfg)
    set_threads(cfg.threads)
    bank, det_features = load_bank(cfg, scenes)
    observer = make_observer(bank, cfg, det_features=det_features, device=device, agent=agent)
    model = make_model(agent, observer, cfg.seed).to(device)
    broadcast_model(model, info)
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr, amsgrad=cfg.amsgrad)
    staggered = cfg.ranks == "staggered"
    rows = cfg.num_envs if staggered else cfg.num_envs // info.world
    env = make_train_env(bank, cfg, rows, seed=cfg.seed * 1000 + info.rank)
    torch.manual_seed(cfg.seed * 1000 + 7919 * info.rank + 1)  # dropout and action sampling

    progress, state = resume_progress(run_dir, model, optimizer, aside=info.is_main)
    if state is not None:
        _restore_rng(state["rng"].get(info.rank), env, cfg.seed, info.rank, progress["update"])

    def checkpoint() -> None:
        _checkpoint(run_dir, progress, model, optimizer, env, info, cfg.milestone_every)

    if budget_used(cfg, progress, checkpoint):
        return progress

    collector = RolloutCollector(env, observer, model, precision=cfg.precision)
    collector.start()
    out = RunOutput(run_dir, cfg, progress, main=info.is_main, progress_bar=progress_bar)
    t_start, seconds0 = time.perf_counter(), progress["seconds"]
    updates_per_round = info.world if staggered else 1
    steps_per_round = cfg.num_envs * cfg.rollout_steps * updates_per_round
    cpu0 = time.process_time()
    try:
        while True:
            # 1-2. rollout, advantages and loss; 3. backward, all-reduce, clip; 4. Adam step
            model.train()
            ro, loss, parts = collect_and_loss(collector, cfg)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if staggered:  # every rank's gradient in turn (each one's update as one process makes it)
                norms = []
                for i, flat in enumerate(gather_gradients(model, info)):
                    set_gradients(model, flat)
                    norms.append(float(torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.max_grad_norm)))
                    schedule_lr(cfg, optimizer, progress["update"] + i, parts)
                    optimizer.step()
                parts["grad_norm"] = sum(norms) / len(norms)
            else:
                allreduce_gradients(model, info)
                parts["grad_norm"] = float(torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.max_grad_norm))
                schedule_lr(cfg, optimizer, progress["update"], parts)
                optimizer.step()

            # counters over all ranks (every rank's CPU time: steps per CPU-second show how the ranks scale)
            cpu = time.process_time()
            episodes, seconds, cpu_s = all_sum(
                [ro.episodes, time.perf_counter() - t_start if info.is_main else 0.0, cpu - cpu0], info, device
            )
            cpu0 = cpu
            progress["update"] += updates_per_round
            progress["env_steps"] += steps_per_round
            progress["episodes"] += int(episodes)
            progress["seconds"] = seconds0 + seconds
            out.window.add(parts, collector.stats.pop(), cpu_s)

            # log, and checkpoint at every boundary (log windows never span a checkpoint)
            reached = cfg.budget_reached(progress)
            boundary = reached or progress["update"] % cfg.checkpoint_every == 0
            out.show(progress, log=progress["update"] % cfg.log_every == 0 or boundary)
            if boundary:
                progress["finished"] = reached
                checkpoint()
                if not reached:
                    collector.start()  # fresh episodes: a resumed run starts here too
            if on_update is not None:
                on_update(dict(progress))
            if reached:
                break
    finally:
        out.close()
    return progress


def _join(cfg: TrainConfig) -> tuple[DistInfo, torch.device]:
    """This process in the run's process group (one of ``cfg.procs`` processes, each stepping an equal share of
    the ``num_envs`` episodes) and its device."""
    device = resolve_device(cfg.device)
    info = init_distributed(device)
    device = device_for(info, device)
    if info.world != cfg.procs:
        raise ValueError(f"this run is configured for procs={cfg.procs} but runs in {info.world} process(es)")
    if cfg.num_envs % info.world:
        raise ValueError(f"num_envs {cfg.num_envs} does not split evenly over {info.world} processes")
    return info, device


def _restore_rng(rng: dict | None, env, seed: int, rank: int, update: int) -> None:
    """Restore this rank's RNG states from the checkpoint it resumes (``rng``); a rank that did not exist when
    the checkpoint was written (None) seeds its streams from the seed, its rank and the update instead."""
    if rng is not None:
        set_rng_state(rng, env.np_random)
    else:
        torch.manual_seed(seed * 1000 + 7919 * rank + update)
        env.np_random = np.random.default_rng([seed, rank, update])


def _checkpoint(
    run_dir: Path, progress: dict, model, optimizer, env, info: DistInfo, milestone_every: int | None = None
) -> None:
    """Checkpoint with every rank's RNG states (rank 0 writes the rest and commits)."""
    if info.is_main:
        checkpoint_tmp(run_dir, progress["update"])
    barrier(info)
    tmp = checkpoint_tmp_path(run_dir, progress["update"])
    write_rng(tmp, info.rank, {**rng_state(env.np_random), "weights": weights_digest(model.state_dict())})
    barrier(info)
    if info.is_main:
        commit_checkpoint(run_dir, tmp, progress, model, optimizer, milestone_every=milestone_every)
    barrier(info)
