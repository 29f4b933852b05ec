"""Run folders, pickle-free checkpoints, and loading a trained agent as an evaluation policy.

Run folder layout::

    RUN/config.json                      resolved configuration (training, agent, reward, features, scenes)
    RUN/log.jsonl                        one JSON line per log interval (losses, rewards per term, SR, ...)
    RUN/tb/                              TensorBoard events
    RUN/checkpoints/ckpt_<update>/       model.safetensors   weights, metadata: the network description and
                                                             action_order (rows of the actor head)
                                         optimizer.safetensors  optimizer state tensors (optim.safetensors
                                                             in checkpoints written before; still read)
                                         state.json          progress (update, env steps, episodes, seconds,
                                                             finished), optimizer groups
                                         rng_rank<r>.json    RNG states of rank r (torch, env sampler)

The layout is the one of every trainer (:mod:`tsnav.checkpoint`). A checkpoint folder is written under a
temporary name and renamed when complete, so the newest folder whose name has no dot is always whole; older ones beyond ``keep`` (2) are removed. A newest checkpoint broken later
(a truncated file) is reported in one line, renamed ``ckpt_<update>.broken`` and training resumes from the one
before it (:func:`resume_checkpoint`).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

from ..agent.model import ActorCritic
from ..agent.observe import DetectionTable, Observer, TargetDepth, load_bank_features
from ..data.detections import load_scene_detections
from .. import checkpoint as ckpt
from ..checkpoint import (
    CHECKPOINTS,
    atomic_write_json,
    load_tensors,
    optimizer_file,
    optimizer_from_tensors,
    optimizer_to_tensors,
    read_json,
    resume_newest,
    set_aside,
)
from ..constants import ACTION_ORDER, NUM_ACTIONS, OLD_ACTION_ORDER, action_permutation, check_same_class_set
from .assemble import install
from .config import TrainConfig
from .policy import AgentPolicy


CKPT = CHECKPOINTS
MODEL_FORMAT = "tsnav-agent"

#: Parameters with one row per action id (the actor head; the previous-action embedding, whose last row is
#: the "no action yet" marker). Their rows follow ``constants.ACTIONS``; checkpoints store the order.
ACTION_ROW_PARAMS = ("actor.weight", "actor.bias", "action_embed.weight")


def convert_action_rows(tensors: dict, order: str) -> dict:
    """``tensors`` (model weights, or optimizer state keyed ``<param>::<state>``) with the action rows of
    :data:`ACTION_ROW_PARAMS` moved from the action ``order`` they were trained in to ``constants.ACTIONS``.
    Other tensors are returned as they are."""
    perm = action_permutation(order)
    if (perm == np.arange(NUM_ACTIONS)).all():
        return dict(tensors)
    out = {}
    for k, v in tensors.items():
        if k.split("::", 1)[0] in ACTION_ROW_PARAMS and v.ndim >= 1 and v.shape[0] >= NUM_ACTIONS:
            v = v.clone()
            v[torch.as_tensor(perm)] = tensors[k][:NUM_ACTIONS].clone()
        out[k] = v
    return out


def checkpoint_action_order(meta: dict, path: Path, quiet: bool = False) -> str:
    """The action order a checkpoint was trained in (``action_order`` of its metadata; checkpoints written
    before tsnav followed the lineage's order carry none and used :data:`OLD_ACTION_ORDER`). Prints one line
    to stderr when the checkpoint is converted on load."""
    order = meta.get("action_order", OLD_ACTION_ORDER)
    if order != ACTION_ORDER and not quiet:
        print(
            f"note: {path} was trained with the action order {order}; its actor and action-embedding rows "
            f"are converted on load to {ACTION_ORDER} (the lineage's)",
            file=sys.stderr,
        )
    return order


def checkpoint_tmp_path(run_dir: str | Path, update: int) -> Path:
    """Temporary folder of the checkpoint of ``update`` (renamed when complete)."""
    return ckpt.checkpoint_tmp_path(Path(run_dir) / CKPT, update)


def checkpoint_tmp(run_dir: str | Path, update: int) -> Path:
    """Create (empty) the temporary folder of the checkpoint of ``update`` (renamed when complete; every rank
    writes its RNG file into it first)."""
    return ckpt.checkpoint_tmp(Path(run_dir) / CKPT, update)


def rng_state(env_rng: np.random.Generator | None = None) -> dict:
    """JSON-able RNG states: torch's global CPU generator (as a list of bytes) and the env's sampler."""
    d = {"torch": torch.get_rng_state().tolist()}
    if env_rng is not None:
        d["env"] = env_rng.bit_generator.state
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        d["cuda"] = [s.tolist() for s in torch.cuda.get_rng_state_all()]
    return d


def set_rng_state(d: dict, env_rng: np.random.Generator | None = None) -> None:
    """Inverse of :func:`rng_state`."""
    torch.set_rng_state(torch.tensor(d["torch"], dtype=torch.uint8))
    if env_rng is not None and "env" in d:
        env_rng.bit_generator.state = d["env"]
    if "cuda" in d and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([torch.tensor(s, dtype=torch.uint8) for s in d["cuda"]])


def write_rng(tmp: Path, rank: int, state: dict) -> None:
    atomic_write_json(Path(tmp) / f"rng_rank{rank}.json", state)


def commit_checkpoint(
    run_dir: str | Path,
    tmp: Path,
    progress: dict,
    model: ActorCritic,
    optimizer: torch.optim.Optimizer | None,
    keep: int = 2,
    milestone_every: int | None = None,
) -> Path:
    """Write the model, optimizer and progress into ``tmp`` and rename it to its final name. The ``keep`` newest
    checkpoints stay, plus every one whose update is a multiple of ``milestone_every`` (for model selection on a
    validation split afterwards)."""
    names = [n for n, _ in model.named_parameters()]
    state, tensors = {"progress": dict(progress)}, None
    if optimizer is not None:
        tensors, state["optimizer"] = optimizer_to_tensors(optimizer, names)
    ckpt.write_checkpoint_files(
        tmp,
        model.state_dict(),
        {"format": MODEL_FORMAT, "model": json.dumps(model.describe(), sort_keys=True), "action_order": ACTION_ORDER},
        state,
        tensors,
    )
    return ckpt.commit_checkpoint(Path(run_dir) / CKPT, tmp, progress["update"], keep, milestone_every)


def save_checkpoint(
    run_dir: str | Path,
    progress: dict,
    model: ActorCritic,
    optimizer=None,
    rng: dict | None = None,
    keep: int = 2,
    milestone_every: int | None = None,
) -> Path:
    """Single-process checkpoint of ``progress["update"]`` (see the module docstring and
    :func:`commit_checkpoint`)."""
    tmp = checkpoint_tmp(run_dir, progress["update"])
    if rng is not None:
        write_rng(tmp, 0, rng)
    return commit_checkpoint(run_dir, tmp, progress, model, optimizer, keep, milestone_every)


def list_checkpoints(run_dir: str | Path) -> list[Path]:
    """Complete checkpoint folders of a run, oldest first."""
    return ckpt.list_checkpoints(Path(run_dir) / CKPT)


def latest_checkpoint(run_dir: str | Path) -> Path | None:
    found = list_checkpoints(run_dir)
    return found[-1] if found else None


def load_checkpoint(path: str | Path, model: ActorCritic | None = None, optimizer=None) -> dict:
    """Load weights (and optimizer state) of a checkpoint folder; returns its ``state.json`` content plus
    ``rng`` (rank -> RNG state dict) when present. :class:`~tsnav.checkpoint.BrokenCheckpoint` names a file
    that cannot be read. A checkpoint trained in another action order (see :func:`checkpoint_action_order`)
    has its action rows converted to ``constants.ACTIONS``."""
    path = Path(path)
    state = read_json(path / "state.json")
    order = ACTION_ORDER
    if model is not None:
        sd, meta = load_tensors(path / "model.safetensors")
        if meta.get("format") != MODEL_FORMAT:
            raise ValueError(f"{path / 'model.safetensors'}: not a tsnav agent checkpoint")
        order = checkpoint_action_order(meta, path)
        model.load_state_dict(convert_action_rows(sd, order))
    if optimizer is not None and "optimizer" in state:
        tensors, _ = load_tensors(optimizer_file(path))
        tensors = convert_action_rows(tensors, order)
        optimizer_from_tensors(optimizer, [n for n, _ in model.named_parameters()], tensors, state["optimizer"])
    state["rng"] = {}
    for f in path.glob("rng_rank*.json"):
        state["rng"][int(f.stem[len("rng_rank") :])] = read_json(f)
    return state


def resume_checkpoint(
    run_dir: str | Path, model: ActorCritic | None = None, optimizer=None, aside: bool = True
) -> tuple[Path, dict] | None:
    """Load the newest checkpoint of a run that reads (:func:`load_checkpoint`); a broken newer one is reported
    in one line and, with ``aside``, renamed by :func:`set_aside`. None when the run has no checkpoint."""
    return resume_newest(
        list_checkpoints(run_dir)[::-1],
        lambda p: load_checkpoint(p, model, optimizer),
        on_broken=set_aside if aside else None,
        label=lambda p: p.name,
    )


def read_run_config(run_dir: str | Path) -> dict:
    """The ``config.json`` of a run folder; ``FileNotFoundError`` / ``ValueError`` naming it otherwise."""
    p = Path(run_dir) / "config.json"
    if not p.exists():
        raise FileNotFoundError(f"{run_dir}: not a training run (no config.json)")
    with open(p) as f:
        cfg = json.load(f)
    if cfg.get("format") != "tsnav-train-run":
        raise ValueError(f"{p}: not a tsnav training run config")
    return cfg


def load_model(run_dir: str | Path, checkpoint: str | Path | None = None) -> tuple[ActorCritic, dict]:
    """The trained network of a run (latest checkpoint unless given) in eval mode, and the checkpoint state."""

    def load(path: Path) -> tuple[ActorCritic, dict]:
        _, meta = load_tensors(path / "model.safetensors")
        if meta.get("format") != MODEL_FORMAT:
            raise ValueError(f"{path / 'model.safetensors'}: not a tsnav agent checkpoint")
        model = ActorCritic.from_description(json.loads(meta["model"]))
        return model.eval(), load_checkpoint(path, model)

    if checkpoint is not None:
        return load(Path(checkpoint))
    found = resume_newest(list_checkpoints(run_dir)[::-1], load, label=lambda p: p.name)  # a reader: sets nothing aside
    if found is None:
        raise FileNotFoundError(f"{run_dir}: no checkpoint yet")
    return found[1]


#: Folder of a run holding a copy of the checkpoint chosen on validation episodes (``tsnav select``).
BEST = "best"
#: ``checkpoint=`` choices of :func:`resolve_checkpoint` besides a path.
CHECKPOINT_CHOICES = ("auto", "best", "latest")


def resolve_checkpoint(run_dir: str | Path, which: str | Path | None = "auto") -> Path | None:
    """The checkpoint folder ``which`` names: ``auto`` (or None) the run's ``best`` (chosen on validation
    episodes by ``tsnav select``) when it has one, else the latest; ``best`` (``FileNotFoundError`` when the
    run has none); ``latest`` (returned as None: :func:`load_model` then takes the newest readable one); or a
    checkpoint folder's path."""
    best = Path(run_dir) / BEST
    has_best = (best / "state.json").exists() and (best / "model.safetensors").exists()
    if which is None or str(which) == "auto":
        return best if has_best else None
    if str(which) == "best":
        if not has_best:
            raise FileNotFoundError(f"{run_dir}: no best checkpoint (run `tsnav select --run {run_dir}` first)")
        return best
    if str(which) == "latest":
        return None
    path = Path(which)
    if not (path / "model.safetensors").exists():
        raise FileNotFoundError(f"{path}: not a checkpoint folder (no model.safetensors)")
    return path


def load_policy(
    run_dir: str | Path,
    bank,
    greedy: bool = True,
    seed: int = 0,
    device: str = "cpu",
    checkpoint: str | Path | None = "auto",
    detections: str | None = None,
):
    """The trained agent of ``run_dir`` as a :class:`~tsnav.eval.policies.Policy` over ``bank``.

    The bank's scenes need the run's feature cache (``features_<name>.hdf5``); when the run used detection
    tables and the bank has none installed, they are installed (so the evaluation's stage switch uses the same
    detector as training). Actions are greedy (the most probable), as the lineage evaluates (IOM / DOA take
    ``prob.argmax`` at test time and sample only while training); ``greedy=False`` samples from the policy with
    a generator seeded by ``seed`` instead. ``checkpoint`` (:func:`resolve_checkpoint`): ``auto`` the run's
    ``best`` checkpoint when validation chose one, else the latest; ``best``, ``latest`` or a folder's path.
    ``detections`` names another detection table for the agent to read instead of its training one (a detector
    swapped at test time, e.g. ``oracle`` to measure what a perfect detector is worth); the bank's stage switch
    must then follow the same table (install it, or leave the bank without one and it is installed here).
    """
    cfg = TrainConfig.from_dict(read_run_config(run_dir)["train"])
    model, _ = load_model(run_dir, resolve_checkpoint(run_dir, checkpoint))
    check_same_class_set(model.class_set, bank.class_set, f"the agent of {run_dir}", "these scenes")
    det_features = None
    name = detections if detections is not None else cfg.detections
    if name is not None:
        if bank.detections is None:
            det_features = install(bank, name)
        else:
            det_features = load_scene_detections(bank.scenes, name).features
    features = load_bank_features(bank, cfg.features)
    if tuple(features.shape[1:]) != model.feature_shape:
        raise ValueError(
            f"features_{cfg.features} of these scenes have shape {tuple(features.shape[1:])} but the "
            f"agent of {run_dir} was trained on {model.feature_shape}"
        )
    depth = None
    if model.config.target_depth:
        depth = TargetDepth.of(model.config.target_depth, bank, features, cfg.features)
    mirror = None
    if model.config.mirror_policy:
        from .assemble import mirror_observer

        mirror = mirror_observer(bank, cfg.features, name, device, model.config.target_depth)
    observer = Observer(
        bank, features, DetectionTable(bank, det_features), device=device, target_depth=depth, mirror=mirror
    )
    if observer.det_dim != model.det_dim:
        raise ValueError(f"detection features of size {observer.det_dim} do not match the agent's {model.det_dim}")
    return AgentPolicy(model.to(device), observer, greedy=greedy, seed=seed)
