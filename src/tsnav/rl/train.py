"""One entry point for a training run folder: resolve and save the configuration, then train with the chosen
algorithm (A3C or batched A2C), resuming from the last checkpoint; a finished run is not retrained."""

from __future__ import annotations

import os
from dataclasses import asdict, replace
from pathlib import Path

import h5py
import torch

from ..agent.model import AgentConfig
from ..agent.observe import NO_DETECTIONS
from ..data.reader import list_scenes
from ..checkpoint import atomic_write_json
from ..pretrain.features import h5py_str
from ..sim.batch import SimConfig
from .a3c import train_a3c
from .batched import train_batched
from .checkpoint import read_run_config
from .config import BUDGET_FIELDS, TrainConfig


RUN_FORMAT = "tsnav-train-run"


def feature_info(cfg: TrainConfig) -> dict:
    """Encoder description and shape of the feature cache ``cfg.features`` (from the first training scene)."""
    scenes = list_scenes(cfg.data, cfg.split)
    if not scenes:
        raise ValueError(f"{cfg.data}: no complete scene of split {cfg.split!r}")
    f = scenes[0] / f"features_{cfg.features}.hdf5"
    if not f.exists():
        raise FileNotFoundError(f"{f}: no feature cache {cfg.features!r} (run `tsnav features` first)")
    with h5py.File(f, "r") as h:
        attrs = {
            k: h5py_str(v) if isinstance(v, (bytes, str)) else v.item() if hasattr(v, "item") else v
            for k, v in h.attrs.items()
            if k != "config"
        }
        shape = list(h["features"].shape[1:])
    return {"name": cfg.features, "shape": shape, **attrs, "scenes": [p.name for p in scenes]}


def resolved_config(cfg: TrainConfig, agent: AgentConfig) -> dict:
    """Everything the run depends on, as saved in ``config.json``."""
    reward = cfg.reward_config()
    sim = SimConfig(
        success_distance=cfg.success_distance, max_steps=cfg.max_steps, autoreset=True, protocol=cfg.protocol
    )
    return {
        "format": RUN_FORMAT,
        "train": cfg.to_dict(),
        "agent": asdict(agent),
        "reward": asdict(reward),
        "sim": asdict(sim),
        "features": feature_info(cfg),
        "budget": cfg.budget,
        "detections": cfg.detections,
        "protocol": cfg.protocol,
        "torch": torch.__version__,
    }


def check_resume(run_dir: Path, cfg: TrainConfig, agent: AgentConfig) -> None:
    """``ValueError`` naming the differing fields when ``run_dir`` holds a run with another configuration."""
    old_cfg, old_agent = stored_config(run_dir)  # fields added since (at their defaults) compare equal
    diff = [k for k, v in cfg.identity().items() if old_cfg.identity().get(k) != v]
    diff += [f"agent.{k}" for k, v in asdict(agent).items() if getattr(old_agent, k) != v]
    if diff:
        raise ValueError(
            f"{run_dir} holds a run with another configuration ({', '.join(diff)}); "
            f"use another --out or the same settings"
        )


def train_run(cfg: TrainConfig, agent: AgentConfig, run_dir: str | Path, *, progress_bar: bool = True) -> dict:
    """Train, resume or (when finished) skip the run in ``run_dir``; returns its progress dict.

    The run's configuration is written to ``run_dir/config.json`` (by rank 0 under torchrun); a run folder
    holding another configuration is refused, except for the budget, which may change between sessions.
    ``cfg.detections`` must name a detection table (no ground-truth fallback).
    """
    run_dir = Path(run_dir)
    if cfg.detections is None:
        raise ValueError(NO_DETECTIONS)
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and cfg.procs == 1:  # launched by torchrun: its processes are the run's
        cfg = replace(cfg, procs=world)
    if (run_dir / "config.json").exists():
        check_resume(run_dir, cfg, agent)
    if int(os.environ.get("RANK", "0")) == 0:
        atomic_write_json(run_dir / "config.json", resolved_config(cfg, agent))
    if cfg.algo == "a3c":
        return train_a3c(cfg, agent, run_dir, progress_bar=progress_bar)

    return train_batched(cfg, agent, run_dir, progress_bar=progress_bar)


def stored_config(run_dir: str | Path) -> tuple[TrainConfig, AgentConfig]:
    """The training and agent configuration saved in a run folder."""
    d = read_run_config(run_dir)
    return TrainConfig.from_dict(d["train"]), AgentConfig(**d["agent"])


__all__ = ["BUDGET_FIELDS", "check_resume", "feature_info", "resolved_config", "stored_config", "train_run"]
