"""Which reward term makes the agent stop taking Done (docs/RESULTS.md, "Training stability").

Trains one short batched run per reward variant with one fixed seed and prints, per log line, the policy's
mean Done probability, training SR, return, exploration reward per episode, entropy and episode length.

    tsnav analyze done-collapse --data REAL128 --features demae-16fd32e89d --detections learned \\
        --out collapse baseline distance explore tsrm tsrm_ent05
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from ..agent import agent_config
from ..rl.config import TrainConfig
from ..rl.train import train_run

#: TrainConfig fields each variant changes.
VARIANTS = {
    "tsrm": {},
    "baseline": {"reward": "baseline"},
    "explore": {"reward": "explore"},
    "distance": {"reward": "distance"},
    "tsrm_ent05": {"entropy_coef": 0.05},
}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze done-collapse", description=__doc__.splitlines()[0]
    )
    p.add_argument("--data", required=True)
    p.add_argument("--features", required=True)
    p.add_argument("--detections", required=True)
    p.add_argument("--out", required=True, help="folder of the runs (one sub-folder per variant; resumed)")
    p.add_argument("--updates", type=int, default=60, help="budget; extend a finished run by raising it")
    p.add_argument(
        "--checkpoint-every",
        type=int,
        default=60,
        help="updates between checkpoints (each starts fresh episodes: part of the run's identity)",
    )
    p.add_argument("--num-envs", type=int, default=256)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("variants", nargs="+", choices=sorted(VARIANTS))
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    for name in a.variants:
        base = TrainConfig(
            data=str(Path(a.data).resolve()),
            features=a.features,
            detections=a.detections,
            algo="batched",
            reward="tsrm",
            preset="cpu",
            lr=a.lr,
            num_envs=a.num_envs,
            seed=a.seed,
            updates=a.updates,
            checkpoint_every=a.checkpoint_every,
        )
        cfg = TrainConfig.from_dict({**base.to_dict(), **VARIANTS[name]})
        out = Path(a.out) / name
        train_run(cfg, agent_config("cpu"), out, progress_bar=False)
        print("variant update done_prob SR return explore entropy length")
        for line in open(out / "log.jsonl"):
            d = json.loads(line)
            print(
                name,
                d["update"],
                round(d["done_prob"], 4),
                round(d["SR"], 3),
                round(d["return"], 2),
                round(d.get("reward/explore", 0.0), 2),
                round(d["entropy"], 3),
                round(d["length"], 1),
                flush=True,
            )
    return 0
