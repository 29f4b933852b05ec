"""Pretraining speed on this machine: DE-MAE vs MAE step time and images/s (paper §III-C).

A step = forward, backward and AdamW update on one batch of random images (no data loading), ViT-Tiny.
DE-MAE and MAE steps are interleaved so that load from other processes hits both alike; the median of
the timed steps is reported. Goal: DE-MAE costs at most 1.15x an MAE step (its extra cost is one linear
head and a loss over all patches).

    .venv/bin/python bench/bench_pretrain.py [--steps 12] [--batch 32] [--threads N]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from tsnav.pretrain.model import vit_tiny


def make(use_depth: bool, patch: int, size: int):
    torch.manual_seed(0)
    m = vit_tiny(patch_size=patch, img_size=size, use_depth=use_depth)
    return m, torch.optim.AdamW([p for p in m.parameters() if p.requires_grad], lr=1e-4, betas=(0.9, 0.95))


def step(model, opt, x, d):
    out = model(x, d if model.config.use_depth else None)
    out.loss.backward()
    opt.step()
    opt.zero_grad(set_to_none=True)


def main() -> None:
    ap = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, batch {args.batch}, ViT-Tiny")
    print(
        f"{'input':>8} {'patch':>5} {'MAE ms':>8} {'DE-MAE ms':>10} {'ratio':>6} {'MAE img/s':>10} {'DE-MAE img/s':>13}"
    )
    for size, patch in ((64, 16), (64, 8), (128, 16)):
        mae, mae_opt = make(False, patch, size)
        de, de_opt = make(True, patch, size)
        x = torch.randn(args.batch, 3, size, size)
        d = torch.randn(args.batch, 1, size, size)
        times = {"mae": [], "de": []}
        for i in range(args.warmup + args.steps):
            for key, m, o in (("mae", mae, mae_opt), ("de", de, de_opt)):
                t = time.perf_counter()
                step(m, o, x, d)
                if i >= args.warmup:
                    times[key].append(time.perf_counter() - t)
        tm, td = statistics.median(times["mae"]), statistics.median(times["de"])
        print(
            f"{size:>6}^2 {patch:>5} {tm * 1e3:>8.1f} {td * 1e3:>10.1f} {td / tm:>6.3f} "
            f"{args.batch / tm:>10.1f} {args.batch / td:>13.1f}"
        )


if __name__ == "__main__":
    main()
