"""Pretraining loop for DE-MAE, standard MAE, DE-MAE w/ crop and the supervised ResNet18 baseline.

Paper §III-C / Table III; recipe of MAE (He et al. 2022): AdamW (betas 0.9, 0.95; weight decay 0.05, none
on biases, norms and tokens), ``lr = base_lr * effective_batch / 256``, linear warm-up then half-cosine
decay per optimiser step, gradient accumulation, bf16 autocast on CUDA only.

Distributed: launched under ``torchrun`` (``WORLD_SIZE > 1``) the loop joins a process group (gloo on CPU,
nccl on GPU) and wraps the model in DDP. Every optimiser step consumes one *global* batch of
``batch_size * world_size * accum_iter`` images taken from a per-epoch permutation seeded by ``(seed,
epoch)``; process ``r`` takes every ``world_size``-th image of each micro-batch, and all randomness (flips,
crops, masking noise) is drawn for the global batch from a generator seeded by ``(seed, step)`` and then
sliced. Hence the result does not depend on how the work is split, and a resumed run continues exactly
where the interrupted one stopped.

Run folder::

    config.json                       resolved PretrainConfig and model config
    checkpoints/ckpt_<step>/          the newest two checkpoints in the layout of every trainer
                                      (:mod:`tsnav.checkpoint`): model.safetensors (full model),
                                      optimizer.safetensors (flattened optimiser state), state.json (step,
                                      epoch, total_steps, finished, loss, optimiser groups, RNG state)
    model.safetensors                 final full model          (finished runs)
    encoder.safetensors               final encoder weights, architecture in its metadata
    recon.png                         reconstructions of a few val images (MAE methods)
    tb/                               TensorBoard scalars

Run folders written before the layouts were unified (``progress.json`` naming ``ckpt-<step>-model.safetensors``
and ``ckpt-<step>-optim.safetensors``, the checkpoint before under ``previous``) are still read and resumed
(:func:`read_legacy_progress`); new checkpoints of such a run go to ``checkpoints/``.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import threading
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.nn as nn
import torch.nn.functional as F
from tqdm import tqdm

from ..distributed import DistInfo, barrier, init_distributed, resolve_device
from ..schedule import warmup_cosine
from ..checkpoint import (
    CHECKPOINTS,
    STATE_FILE,
    atomic_write_json,
    list_checkpoints,
    load_tensors,
    optimizer_file,
    optimizer_from_tensors,
    optimizer_to_tensors,
    read_json,
    resume_newest,
    save_checkpoint as save_checkpoint_folder,
    save_tensors,
    set_aside,
)
from ..checkpoint_layout import LEGACY_PROGRESS, read_legacy_progress, read_progress  # noqa: F401 - read_progress: API
from .data import AugmentConfig, BatchView, RGBDImages, draw_augment, prepare_batch, scene_split_images, slice_augment
from .archs import arch_of, vit_mae_config
from .encoders import METHODS, method_kind  # noqa: F401 (METHODS: the registry's method names, re-exported)
from .model import SIZES, MaskedAutoencoderViT
from .viz import reconstruction_grid

#: Config fields that may change between an interrupted run and its resumption.
RESUMABLE_FIELDS = {"checkpoint_every", "log_every", "num_workers", "preload", "device", "viz_images"}


@dataclass
class PretrainConfig:
    """Everything that defines a pretraining run. Defaults: the paper's ViT-Base DE-MAE with MAE's recipe."""

    method: str = "demae"
    """``demae`` (RGB + depth heads, flip only), ``mae`` (no depth head), ``demae-crop`` (DE-MAE with
    random resized crop, Table III's "w/ crop"), ``resnet18-sup`` (supervised ResNet18 baseline)."""
    model: str = "vit_base"
    """Encoder size: ``vit_tiny`` / ``vit_small`` / ``vit_base`` (ignored by ``resnet18-sup``)."""
    patch_size: int = 16
    """ViT patch side, pixels (8 or 16)."""
    img_size: int = 224
    """Square input side, pixels; frames are resized to it."""
    mask_ratio: float = 0.75
    """Share of masked patches (MAE)."""
    norm_pix_loss: bool = False
    """Per-patch normalised RGB targets (off: the paper's loss is plain pixel MSE)."""
    depth_weight: float = 1.0
    """Weight of the depth MSE ("identical weights", §III-C)."""
    batch_size: int = 64
    """Images per process per micro-step."""
    accum_iter: int = 1
    """Micro-steps accumulated per optimiser step."""
    base_lr: float | None = None
    """Learning rate per 256 images; None: 1.5e-4 (MAE) for MAE methods, 1e-3 for ``resnet18-sup``."""
    min_lr: float = 0.0
    """Floor of the cosine schedule."""
    weight_decay: float = 0.05
    """AdamW weight decay (MAE: 0.05)."""
    betas: tuple[float, float] = (0.9, 0.95)
    """AdamW betas (MAE: 0.9, 0.95)."""
    epochs: int = 100
    """Passes over the train images (used when ``steps`` is None)."""
    steps: int | None = None
    """Total optimiser steps; overrides ``epochs``."""
    warmup_fraction: float = 0.05
    """Share of the steps spent in linear warm-up (MAE: 40 of 800 epochs)."""
    seed: int = 0
    """Seed of the initial weights, the epoch permutations and all augmentation / masking noise."""
    flip_prob: float = 0.5
    """Horizontal-flip probability (the only augmentation of DE-MAE, §III-C)."""
    crop_scale: tuple[float, float] = (0.2, 1.0)
    """Area range of the random resized crop (``demae-crop`` only)."""
    max_scenes: int | None = None
    """Use only the first N train scenes (None: all)."""
    preload: bool = True
    """Read all frames into memory (uint8 / float16) instead of streaming them from HDF5."""
    num_workers: int = 0
    """DataLoader worker processes reading batches (0: read in the training process)."""
    checkpoint_every: int = 500
    """Optimiser steps between checkpoints (also written at the end and on Ctrl-C)."""
    log_every: int = 10
    """Optimiser steps between TensorBoard / progress-bar updates."""
    viz_images: int = 6
    """Val images in the final reconstruction picture (0: none)."""
    device: str = "auto"
    """``auto`` (CUDA when present), ``cpu`` or ``cuda``."""

    def __post_init__(self) -> None:
        kind = method_kind(self.method)  # ValueError naming the methods
        if kind.arch == "vit" and self.model not in SIZES:
            raise ValueError(f"unknown model {self.model!r} (choose from {', '.join(SIZES)})")
        if self.batch_size < 1 or self.accum_iter < 1:
            raise ValueError("batch_size and accum_iter must be >= 1")
        if self.steps is not None and self.steps < 1:
            raise ValueError("steps must be >= 1")
        if kind.arch == "vit" and self.img_size % self.patch_size:
            raise ValueError(f"img_size {self.img_size} must be a multiple of patch {self.patch_size}")
        self.betas = tuple(self.betas)
        self.crop_scale = tuple(self.crop_scale)

    @property
    def resolved_base_lr(self) -> float:
        if self.base_lr is not None:
            return self.base_lr
        return method_kind(self.method).base_lr

    def to_dict(self) -> dict:
        d = asdict(self)
        d["betas"], d["crop_scale"] = list(self.betas), list(self.crop_scale)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "PretrainConfig":
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})


# ---------------------------------------------------------------------------------------------------------
# Model construction and saved encoders
# ---------------------------------------------------------------------------------------------------------


def model_config(cfg: PretrainConfig):
    """The :class:`MAEConfig` of a ViT method (None for other architectures, e.g. ``resnet18-sup``)."""
    if method_kind(cfg.method).arch != "vit":
        return None
    return vit_mae_config(cfg)


def _model_config_dict(cfg: PretrainConfig) -> dict:
    """The network's own config as saved in ``config.json`` ({} when its architecture has none)."""
    return arch_of(method_kind(cfg.method).arch).model_config(cfg)


def build_model(cfg: PretrainConfig) -> nn.Module:
    """The network a method trains (its encoder's architecture, :mod:`tsnav.pretrain.archs`), initialised from
    ``torch.manual_seed(cfg.seed)``."""
    torch.manual_seed(cfg.seed)
    return arch_of(method_kind(cfg.method).arch).build(cfg)


def encoder_metadata(model: nn.Module, method: str) -> dict[str, str]:
    """safetensors metadata that lets :func:`tsnav.pretrain.features.load_encoder` rebuild the encoder."""
    return arch_of(method_kind(method).arch).metadata(model, method)


def save_encoder(model: nn.Module, path: str | Path, method: str) -> None:
    """Write the encoder's weights (no decoder / head) with its architecture in the metadata."""
    save_tensors(path, model.encoder_state_dict(), encoder_metadata(model, method))


# ---------------------------------------------------------------------------------------------------------
# Schedule, sharding, distributed set-up
# ---------------------------------------------------------------------------------------------------------


def step_seed(seed: int, step: int) -> int:
    return int(np.random.SeedSequence([seed, step, 17]).generate_state(1)[0])


def epoch_permutation(n: int, seed: int, epoch: int) -> np.ndarray:
    g = torch.Generator().manual_seed(int(np.random.SeedSequence([seed, epoch, 29]).generate_state(1)[0]))
    return torch.randperm(n, generator=g).numpy()


def param_groups(model: nn.Module, weight_decay: float) -> tuple[list[dict], list[str]]:
    """AdamW groups: decay on weights of rank >= 2, none on biases, norms and tokens. Also the names."""
    decay, no_decay, dn, nn_ = [], [], [], []
    for name, p in model.named_parameters():
        if not p.requires_grad:
            continue
        if p.ndim <= 1 or name.endswith(("cls_token", "mask_token", "pos_embed")):
            no_decay.append(p)
            nn_.append(name)
        else:
            decay.append(p)
            dn.append(name)
    return ([{"params": no_decay, "weight_decay": 0.0}, {"params": decay, "weight_decay": weight_decay}], nn_ + dn)


# ---------------------------------------------------------------------------------------------------------
# The loop
# ---------------------------------------------------------------------------------------------------------


def compute_loss(
    model: nn.Module,
    method: str,
    rgb: torch.Tensor,
    depth: torch.Tensor,
    labels: torch.Tensor | None,
    noise: torch.Tensor | None,
) -> tuple[torch.Tensor, dict]:
    """Loss of one micro-batch and its parts for logging."""
    kind = method_kind(method)
    if kind.labels:  # supervised: the visible target categories of the frame
        logits = model(rgb)
        loss = F.binary_cross_entropy_with_logits(logits.float(), labels)
        return loss, {"bce": loss.detach()}
    out = model(rgb, depth if kind.depth else None, noise=noise)
    parts = {"rgb": out.loss_rgb.detach()}
    if kind.depth:
        parts["depth"] = out.loss_depth.detach()
    return out.loss, parts


def _candidates(out: Path) -> list[tuple[str, object]]:
    """Checkpoints to resume from, newest first: the ``checkpoints/`` folders, then the records of a legacy
    ``progress.json`` (its newest and ``previous``)."""
    found: list[tuple[str, object]] = [("folder", p) for p in list_checkpoints(out / CHECKPOINTS)[::-1]]
    legacy = read_legacy_progress(out)
    if legacy is not None:
        found += [("legacy", r) for r in (legacy, legacy.get("previous")) if r]
    return found


def _read_checkpoint(out: Path, c: tuple[str, object]) -> tuple[dict, dict, dict]:
    """(state, model tensors, optimizer tensors) of a resume candidate (:class:`BrokenCheckpoint` when a file
    is broken)."""
    kind, x = c
    if kind == "folder":
        return read_json(x / STATE_FILE), load_tensors(x / "model.safetensors")[0], load_tensors(optimizer_file(x))[0]
    return x, load_tensors(out / x["model_file"])[0], load_tensors(out / x["optim_file"])[0]


def _set_aside(out: Path, c: tuple[str, object]) -> None:
    kind, x = c
    if kind == "folder":
        set_aside(x)
        return
    for k in ("model_file", "optim_file"):
        p = out / x[k]
        if p.exists():
            os.replace(p, p.with_name(p.name + ".broken"))


def _label(c: tuple[str, object]) -> str:
    kind, x = c
    return x.name if kind == "folder" else f"{x['model_file']} (step {x['step']})"


def _check_config(out: Path, cfg: PretrainConfig, model_cfg: dict, write: bool) -> None:
    p = out / "config.json"
    new = {"pretrain": cfg.to_dict(), "model": model_cfg}
    if p.exists():
        old = json.loads(p.read_text())
        diffs = [
            k
            for k in set(old.get("pretrain", {})) | set(new["pretrain"])
            if k not in RESUMABLE_FIELDS and old.get("pretrain", {}).get(k) != new["pretrain"].get(k)
        ]
        if diffs:
            k = sorted(diffs)[0]
            raise ValueError(
                f"{out} holds a run with another config ({k}: {old['pretrain'].get(k)!r} there, "
                f"{new['pretrain'].get(k)!r} now); use a new --out folder"
            )
    if write:
        atomic_write_json(p, new)


def train(
    cfg: PretrainConfig,
    data: str | Path | RGBDImages,
    out: str | Path,
    *,
    stop_at: int | None = None,
    progress: bool = True,
) -> dict:
    """Pretrain and return the summary only; see :func:`train_model`."""
    return train_model(cfg, data, out, stop_at=stop_at, progress=progress)[0]


def train_model(
    cfg: PretrainConfig,
    data: str | Path | RGBDImages,
    out: str | Path,
    *,
    stop_at: int | None = None,
    progress: bool = True,
) -> tuple[dict, nn.Module | None]:
    """Pretrain per ``cfg`` on the train images of ``data`` into the run folder ``out``; resume if present.

    ``stop_at`` ends the call after that many optimiser steps (a simulated interruption; the checkpoint is
    written). Returns a summary ``{"step", "total_steps", "finished", "loss"}`` and this process's replica of
    the trained model (None when the run had already finished: a finished run is not retrained).
    """
    out = Path(out)
    device = resolve_device(cfg.device)
    di = init_distributed(device)
    # SIGTERM (a scheduler's pre-emption, `timeout`) and Ctrl-C stop the run at the end of the current step
    # with a checkpoint; a second signal stops at once (a checkpoint is written only if no update was
    # half-applied).
    stop = _StopRequest()
    old = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            old[sig] = signal.signal(sig, stop.handle)
    try:
        return _train(cfg, data, out, device, di, stop_at, progress, stop)
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)
        if di.owns_group:
            dist.destroy_process_group()


class _StopRequest:
    """Signal handler state: the first signal asks for a clean stop, the second interrupts at once."""

    def __init__(self) -> None:
        self.signum: int | None = None

    def handle(self, signum, frame) -> None:
        if self.signum is not None:
            raise KeyboardInterrupt(f"signal {signum}")
        self.signum = signum


def _train(cfg, data, out, device, di: DistInfo, stop_at, progress, stop: _StopRequest | None = None):
    """:func:`train_model` in this process: set up, resume, the loop of optimiser steps, the final files."""
    model_cfg = _model_config_dict(cfg)
    _check_config(out, cfg, model_cfg, write=False)
    prog = read_progress(out)
    if prog and prog.get("finished"):
        return _finished_summary(out, prog, say=di.rank == 0 and progress), None
    kind = method_kind(cfg.method)
    images = _train_images(cfg, data)
    model = build_model(cfg).to(device)
    if di.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        _check_config(out, cfg, model_cfg, write=True)

    b = _Batches.of(cfg, len(images), di.world)
    groups, names = param_groups(model, cfg.weight_decay)
    opt = torch.optim.AdamW(groups, lr=b.peak_lr, betas=cfg.betas, foreach=True)
    start = 0 if prog is None else _resume(out, prog, b, model, opt, names, device, di)
    ddp = (
        model
        if b.world == 1
        else nn.parallel.DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
    )
    aug_cfg = AugmentConfig(flip_prob=cfg.flip_prob, crop=kind.crop, crop_scale=cfg.crop_scale)
    L = model.config.num_patches if kind.arch == "vit" and not kind.labels else 0
    autocast = torch.autocast("cuda", dtype=torch.bfloat16) if device.type == "cuda" else contextlib.nullcontext()
    loader = _loader(images, b, cfg, start, di.rank)
    log = _PretrainLog(out, cfg, b, start, progress) if di.rank == 0 else None

    def save_checkpoint(step: int, finished: bool, loss_value: float | None) -> None:
        if di.rank == 0:
            _save_checkpoint(out, model, opt, names, model_cfg, cfg.method, b, step, finished, loss_value)

    step, last_loss, consistent = start, None, True
    end = b.total if stop_at is None else min(b.total, stop_at)
    model.train()
    try:
        while step < end:
            # one global batch: flips, crops and masking noise drawn for all of it (this process takes its
            # share), gradients accumulated over accum_iter micro-steps, one AdamW step at the scheduled rate
            gen = torch.Generator().manual_seed(step_seed(cfg.seed, step))
            aug = draw_augment(gen, b.global_batch, aug_cfg)
            noise = torch.rand(b.global_batch, L, generator=gen) if L else None
            for g in opt.param_groups:
                g["lr"] = warmup_cosine(step, b.total, b.peak_lr, b.warmup, cfg.min_lr)
            sums = _accumulate(ddp, cfg.method, loader, b, aug, noise, autocast, device, di.rank)
            if not all(torch.isfinite(v).all() for v in sums.values()):
                raise FloatingPointError(f"non-finite loss at step {step}; lower --base-lr")
            consistent = False  # weights / optimiser state are between steps until step += 1
            opt.step()
            opt.zero_grad(set_to_none=True)
            step += 1
            consistent = True

            # log, checkpoint, and stop when asked to (every process at the same step)
            losses = None
            if step % cfg.log_every == 0 or step == end:
                losses = _mean_losses(sums, b.world, device)
                last_loss = losses["total"]
            if log is not None:
                log.step(step, losses, opt.param_groups[0]["lr"])
            if step % cfg.checkpoint_every == 0 and step < end:
                save_checkpoint(step, False, last_loss)
                barrier(di)
            if _stop_requested(stop, b.world, device) and step < end:
                save_checkpoint(step, False, last_loss)
                raise KeyboardInterrupt("stop requested")
    except KeyboardInterrupt:
        if consistent:
            save_checkpoint(step, False, last_loss)
        raise
    finally:
        if log is not None:
            log.close()
    finished = step >= b.total
    if di.rank == 0:
        if finished:
            _write_final(out, model, model_cfg, cfg, images)
        save_checkpoint(step, finished, last_loss)
    barrier(di)
    return {"step": step, "total_steps": b.total, "finished": finished, "loss": last_loss}, model


def _finished_summary(out: Path, prog: dict, say: bool) -> dict:
    """The summary of a finished run (which is not retrained); ``say`` prints so in one line."""
    if say:
        print(f"{out}: pretraining already finished ({prog['step']} steps); nothing to do")
    return {"step": prog["step"], "total_steps": prog["total_steps"], "finished": True, "loss": prog.get("loss")}


def _train_images(cfg: PretrainConfig, data: str | Path | RGBDImages) -> RGBDImages:
    """The training images of ``data`` (a dataset folder, or images loaded already that must match ``cfg``)."""
    sup = method_kind(cfg.method).labels
    images = (
        data
        if isinstance(data, RGBDImages)
        else RGBDImages(data, "train", cfg.img_size, labels=sup, preload=cfg.preload, max_scenes=cfg.max_scenes)
    )
    if images.img_size != cfg.img_size or (sup and not images.with_labels):
        raise ValueError("the given RGBDImages do not match the config (img_size / labels)")
    return images


@dataclass(frozen=True)
class _Batches:
    """How a run cuts its training images into optimiser steps (see the module docstring)."""

    batch: int
    """Images per process and micro-step (``batch_size``)."""
    world: int
    """Processes."""
    accum: int
    """Micro-steps per optimiser step (``accum_iter``)."""
    images: int
    """Training images."""
    total: int
    """Optimiser steps of the whole run."""
    warmup: int
    """Warm-up steps of the learning rate."""
    peak_lr: float
    """``base_lr * global batch / 256``."""

    @property
    def global_batch(self) -> int:
        """Images per optimiser step."""
        return self.batch * self.world * self.accum

    @property
    def steps_per_epoch(self) -> int:
        return self.images // self.global_batch

    @classmethod
    def of(cls, cfg: PretrainConfig, n: int, world: int) -> "_Batches":
        B, W, A = cfg.batch_size, world, cfg.accum_iter
        G = B * W * A
        steps_per_epoch = n // G
        if steps_per_epoch < 1:
            raise ValueError(
                f"{n} train images are fewer than one global batch of {G} "
                f"(batch {B} x {W} processes x {A} accumulation)"
            )
        total = cfg.steps if cfg.steps is not None else cfg.epochs * steps_per_epoch
        warmup = max(1, int(round(cfg.warmup_fraction * total)))
        return cls(B, W, A, n, total, warmup, cfg.resolved_base_lr * G / 256)


def _resume(
    out: Path,
    prog: dict,
    b: _Batches,
    model: nn.Module,
    opt: torch.optim.Optimizer,
    names: list[str],
    device: torch.device,
    di: DistInfo,
) -> int:
    """Load model, optimiser and RNG state of the newest readable checkpoint of ``out`` (a broken newest one is
    set aside by rank 0); returns its step. The global batch and the image count must be the run's."""
    G, n = b.global_batch, b.images
    if int(prog.get("global_batch", G)) != G:
        raise ValueError(
            f"{out} was trained with a global batch of {prog['global_batch']} images "
            f"({prog.get('world_size')} processes); resume with the same number of processes"
        )
    if int(prog.get("images", n)) != n:
        raise ValueError(
            f"{out} was trained on {prog['images']} images, the dataset now has {n}; use a new --out folder"
        )
    c, (rec, sd, ot) = resume_newest(
        _candidates(out),
        lambda c: _read_checkpoint(out, c),
        on_broken=lambda c: _set_aside(out, c) if di.rank == 0 else None,
        label=_label,
    )
    legacy = read_legacy_progress(out) if c[0] == "legacy" else None
    if legacy is not None and rec.get("step") != legacy.get("step") and di.rank == 0:
        atomic_write_json(out / LEGACY_PROGRESS, rec)  # the legacy run now continues from its previous record
    model.load_state_dict(sd)
    optimizer_from_tensors(opt, names, {k: v.to(device) for k, v in ot.items()}, rec["optimizer"])
    torch.set_rng_state(torch.tensor(rec["rng"]["torch"], dtype=torch.uint8))
    return int(rec["step"])


def _micro_batches(b: _Batches, seed: int, first: int, rank: int):
    """Index arrays of process ``rank``, one per micro-step, from optimiser step ``first`` on: each global
    batch is the next block of its epoch's permutation, each micro-batch a slice of it, of which the process
    takes every ``world``-th image."""
    G, BW = b.global_batch, b.batch * b.world
    perm, perm_epoch = None, -1
    for s in range(first, b.total):
        epoch, k = divmod(s, b.steps_per_epoch)
        if epoch != perm_epoch:
            perm, perm_epoch = epoch_permutation(b.images, seed, epoch), epoch
        block = perm[k * G : (k + 1) * G]
        for m in range(b.accum):
            yield block[m * BW : (m + 1) * BW][rank :: b.world]


def _loader(images: RGBDImages, b: _Batches, cfg: PretrainConfig, first: int, rank: int):
    """This process's micro-batches from optimiser step ``first`` on (loaded by ``num_workers`` processes)."""
    if cfg.num_workers > 0:
        return iter(
            torch.utils.data.DataLoader(
                BatchView(images),
                sampler=_micro_batches(b, cfg.seed, first, rank),
                batch_size=None,
                num_workers=cfg.num_workers,
                persistent_workers=False,
            )
        )
    return (images.get(idx) for idx in _micro_batches(b, cfg.seed, first, rank))


def _accumulate(
    ddp: nn.Module,
    method: str,
    loader,
    b: _Batches,
    aug,
    noise: torch.Tensor | None,
    autocast,
    device: torch.device,
    rank: int,
) -> dict[str, torch.Tensor]:
    """Forward and backward of this process's share of one global batch over ``accum`` micro-steps (DDP
    all-reduces the gradients on the last); returns the loss parts averaged over the micro-steps."""
    sums: dict[str, torch.Tensor] = {}
    for m in range(b.accum):
        batch = next(loader)
        pos = np.arange(m * b.batch * b.world, (m + 1) * b.batch * b.world)[rank :: b.world]  # in the global batch
        rgb, depth = prepare_batch(batch, slice_augment(aug, torch.from_numpy(pos)), device)
        labels = batch["labels"].to(device) if method_kind(method).labels else None
        nz = noise[torch.from_numpy(pos)].to(device) if noise is not None else None
        sync = contextlib.nullcontext() if (b.world == 1 or m == b.accum - 1) else ddp.no_sync()
        with sync:
            with autocast:
                loss, parts = compute_loss(ddp, method, rgb, depth, labels, nz)
            (loss / b.accum).backward()
        for k, v in {"total": loss.detach(), **parts}.items():
            sums[k] = sums.get(k, 0) + v.float() / b.accum
    return sums


def _mean_losses(sums: dict[str, torch.Tensor], world: int, device: torch.device) -> dict[str, float]:
    """The step's loss parts averaged over the processes (an all-reduce every process takes part in)."""
    vals = torch.stack([sums[k] for k in sorted(sums)]).to(device)
    if world > 1:
        dist.all_reduce(vals)
        vals /= world
    return dict(zip(sorted(sums), vals.tolist()))


def _stop_requested(stop: _StopRequest | None, world: int, device: torch.device) -> bool:
    """Whether a signal asked any process to stop (every process gets the same answer)."""
    want_stop = stop is not None and stop.signum is not None
    if world > 1:  # every process stops at the same step, or the others would wait forever
        flag = torch.tensor([float(want_stop)], device=device)
        dist.all_reduce(flag, op=dist.ReduceOp.MAX)
        want_stop = bool(flag.item())
    return want_stop


class _PretrainLog:
    """Rank 0's TensorBoard scalars (``losses/...``, ``charts/lr``, ``charts/images_per_s``) and progress bar."""

    def __init__(self, out: Path, cfg: PretrainConfig, b: _Batches, start: int, progress: bool):
        # lazy: torch.utils.tensorboard takes about 2.3 s to import (`python -X importtime`); only logging runs need it
        from torch.utils.tensorboard import SummaryWriter

        self.writer = SummaryWriter(log_dir=str(out / "tb"), purge_step=start)
        self.bar = tqdm(
            total=b.total,
            initial=start,
            desc=f"pretrain {cfg.method}",
            unit="step",
            disable=not progress,
            dynamic_ncols=True,
        )
        self.images_per_step = b.global_batch
        self.t0, self.seen = time.perf_counter(), 0

    def step(self, step: int, losses: dict[str, float] | None, lr: float) -> None:
        """One optimiser step done; ``losses`` (on log steps) are written with the rate and images per second
        since the last log step."""
        self.seen += self.images_per_step
        if losses is not None:
            ips = self.seen / max(time.perf_counter() - self.t0, 1e-9)
            for k, v in losses.items():
                self.writer.add_scalar(f"losses/{k}", v, step)
            self.writer.add_scalar("charts/lr", lr, step)
            self.writer.add_scalar("charts/images_per_s", ips, step)
            self.bar.set_postfix(loss=f"{losses['total']:.4f}", img_s=f"{ips:.1f}")
            self.t0, self.seen = time.perf_counter(), 0
        self.bar.update(1)

    def close(self) -> None:
        self.bar.close()
        self.writer.close()


def _save_checkpoint(
    out: Path,
    model: nn.Module,
    opt: torch.optim.Optimizer,
    names: list[str],
    model_cfg: dict,
    method: str,
    b: _Batches,
    step: int,
    finished: bool,
    loss_value: float | None,
) -> None:
    """The checkpoint of ``step`` (state: progress, optimiser groups, the torch RNG state)."""
    ot, ometa = optimizer_to_tensors(opt, names)
    state = {
        "step": step,
        "epoch": step // b.steps_per_epoch,
        "total_steps": b.total,
        "finished": finished,
        "optimizer": ometa,
        "loss": loss_value,
        "world_size": b.world,
        "global_batch": b.global_batch,
        "images": b.images,
        "rng": {"torch": torch.get_rng_state().tolist()},
    }
    save_checkpoint_folder(
        out / CHECKPOINTS,
        step,
        model.state_dict(),
        {"config": json.dumps(model_cfg), "method": method, "step": str(step)},
        state,
        ot,
    )


def _write_final(out: Path, model: nn.Module, model_cfg: dict, cfg: PretrainConfig, images: RGBDImages) -> None:
    """A finished run's model and encoder files (and reconstructions of a few images, MAE methods)."""
    save_tensors(out / "model.safetensors", model.state_dict(), {"config": json.dumps(model_cfg), "method": cfg.method})
    save_encoder(model, out / "encoder.safetensors", cfg.method)
    if model_config(cfg) is not None and not method_kind(cfg.method).labels and cfg.viz_images > 0:
        write_reconstructions(model, cfg, out / "recon.png", images)


def write_reconstructions(
    model: MaskedAutoencoderViT, cfg: PretrainConfig, path: Path, train_images: RGBDImages
) -> None:
    """Reconstruction grid of a few val images (train images when the dataset has no val split)."""
    val = scene_split_images(train_images.root, "val", cfg.img_size, preload=False, max_scenes=1) or train_images
    idx = np.linspace(0, len(val) - 1, num=min(cfg.viz_images, len(val))).round().astype(np.int64)
    batch = val.get(idx)
    rgb, depth = prepare_batch(batch, None, next(model.parameters()).device)
    reconstruction_grid(model, rgb, depth, path, seed=cfg.seed)
