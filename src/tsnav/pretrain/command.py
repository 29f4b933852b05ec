"""``tsnav pretrain``: DE-MAE / MAE / DE-MAE w/ crop / supervised ResNet18 pretraining (paper §III-C).

Examples::

    tsnav pretrain --data data/world --out runs/demae --method demae --model vit_tiny --patch 16 --img-size 64 --steps 2000
    torchrun --nproc_per_node 2 -m tsnav.cli pretrain --data data/world --out runs/demae ...

Running the same command again resumes an interrupted run; a finished run is not retrained.
"""

from __future__ import annotations

import argparse
import os

from ..errors import CommandError
from .model import SIZES
from .train import METHODS, PretrainConfig, train

_D = PretrainConfig()


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, help="dataset root (scene folders; train split is used)")
    parser.add_argument("--out", required=True, help="run folder (created; resumed when it exists)")
    parser.add_argument("--method", choices=METHODS, default=_D.method,
                        help="demae (paper), mae (no depth head), demae-crop (w/ crop ablation), "
                             "resnet18-sup (supervised ResNet18 baseline on visible categories)")
    parser.add_argument("--model", choices=sorted(SIZES), default=_D.model, help="ViT size (default %(default)s)")
    parser.add_argument("--patch", type=int, default=_D.patch_size, help="patch side in pixels (default %(default)s)")
    parser.add_argument("--img-size", type=int, default=_D.img_size, help="square input side (default %(default)s)")
    parser.add_argument("--epochs", type=int, default=_D.epochs, help="passes over the data (default %(default)s)")
    parser.add_argument("--steps", type=int, default=None, help="total optimiser steps (overrides --epochs)")
    parser.add_argument("--batch-size", type=int, default=_D.batch_size, help="images per process per micro-step")
    parser.add_argument("--accum-iter", type=int, default=_D.accum_iter, help="gradient accumulation steps")
    parser.add_argument("--base-lr", type=float, default=None,
                        help="lr per 256 images (default 1.5e-4 for MAE methods, 1e-3 for resnet18-sup)")
    parser.add_argument("--weight-decay", type=float, default=_D.weight_decay)
    parser.add_argument("--mask-ratio", type=float, default=_D.mask_ratio)
    parser.add_argument("--depth-weight", type=float, default=_D.depth_weight)
    parser.add_argument("--norm-pix-loss", action="store_true", help="normalise target RGB patches (MAE option)")
    parser.add_argument("--warmup-fraction", type=float, default=_D.warmup_fraction)
    parser.add_argument("--seed", type=int, default=_D.seed)
    parser.add_argument("--max-scenes", type=int, default=None, help="use only the first N train scenes")
    parser.add_argument("--no-preload", action="store_true", help="stream frames from HDF5 instead of memory")
    parser.add_argument("--workers", type=int, default=_D.num_workers, help="data-loading worker processes")
    parser.add_argument("--checkpoint-every", type=int, default=_D.checkpoint_every)
    parser.add_argument("--log-every", type=int, default=_D.log_every)
    parser.add_argument("--viz-images", type=int, default=_D.viz_images, help="val images in recon.png")
    parser.add_argument("--device", default=_D.device, help="auto, cpu or cuda")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def config_from_args(args: argparse.Namespace) -> PretrainConfig:
    try:
        return PretrainConfig(
            method=args.method, model=args.model, patch_size=args.patch, img_size=args.img_size,
            epochs=args.epochs, steps=args.steps, batch_size=args.batch_size, accum_iter=args.accum_iter,
            base_lr=args.base_lr, weight_decay=args.weight_decay, mask_ratio=args.mask_ratio,
            depth_weight=args.depth_weight, norm_pix_loss=args.norm_pix_loss,
            warmup_fraction=args.warmup_fraction, seed=args.seed, max_scenes=args.max_scenes,
            preload=not args.no_preload, num_workers=args.workers, checkpoint_every=args.checkpoint_every,
            log_every=args.log_every, viz_images=args.viz_images, device=args.device)
    except ValueError as e:
        raise CommandError(str(e)) from None


def run(args: argparse.Namespace) -> int:
    cfg = config_from_args(args)
    res = train(cfg, args.data, args.out, progress=not args.quiet)
    if res["finished"] and int(os.environ.get("RANK", "0")) == 0:
        loss = f"{res['loss']:.4f}" if res.get("loss") is not None else "n/a"
        print(f"pretraining done: {res['step']} steps, last loss {loss}; encoder at {args.out}/encoder.safetensors")
    return 0
