"""One batched-A2C update (rollout with gradients, GAE, loss, backward, Adam step), with the trainer's fast paths
and with their slow references, alternated in one process so that a shared, noisy machine affects both alike.

Fast path measured against its reference: the memory attention (``TargetMemoryAggregator.attend``, key and value
projections moved to the query side) vs ``nn.MultiheadAttention`` (``attend_reference``).

    .venv/bin/python bench/bench_update.py [--preset cpu|paper] [--num-envs 256] [--rounds 6]

Without --data a tiny world is built in a temporary folder with pooled-pixel features; the TSRM reward and the
oracle detection table are used. Prints env steps/s of each variant (median over rounds) and their ratio.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path


def main() -> None:
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_train import training_world  # the same training data as the training benchmark

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--features", default=None)
    ap.add_argument("--detections", default="oracle", help="detection tables the agent reads (named explicitly)")
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--num-envs", type=int, default=256)
    ap.add_argument("--rollout-steps", type=int, default=30)
    ap.add_argument("--updates", type=int, default=3, help="updates per variant and round")
    ap.add_argument("--rounds", type=int, default=6)
    args = ap.parse_args()

    import torch

    from tsnav.agent import agent_config
    from tsnav.agent.memory import TargetMemoryAggregator
    from tsnav.rl.assemble import load_bank, make_model, make_observer, make_train_env
    from tsnav.rl.config import TrainConfig
    from tsnav.rl.rollout import RolloutCollector, collect_and_loss

    torch.set_num_threads(1)
    tmp = Path(tempfile.mkdtemp(prefix="bench_update_"))
    try:
        data, features = training_world(tmp, args.data, args.features, args.detections)
        cfg = TrainConfig(data=str(data), features=features, detections=args.detections, reward="tsrm",
                          algo="batched", num_envs=args.num_envs,
                          rollout_steps=args.rollout_steps, device="cpu")
        bank, det = load_bank(cfg)
        observer = make_observer(bank, cfg, det_features=det)
        model = make_model(agent_config(args.preset), observer, 0)
        opt = torch.optim.Adam(model.parameters(), lr=1e-4, amsgrad=True)
        collector = RolloutCollector(make_train_env(bank, cfg, args.num_envs, seed=0), observer, model)
        collector.start()
        fast = TargetMemoryAggregator.attend

        def update_rate(reference: bool) -> float:
            TargetMemoryAggregator.attend = TargetMemoryAggregator.attend_reference if reference else fast
            t = time.perf_counter()
            for _ in range(args.updates):
                _, loss, _ = collect_and_loss(collector, cfg)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
            return args.updates * args.num_envs * args.rollout_steps / (time.perf_counter() - t)

        update_rate(False)  # warm-up
        rates = {"fast": [], "reference": []}
        for r in range(args.rounds):
            for name in (("fast", "reference") if r % 2 == 0 else ("reference", "fast")):
                rates[name].append(update_rate(name == "reference"))
        TargetMemoryAggregator.attend = fast
        f, ref = statistics.median(rates["fast"]), statistics.median(rates["reference"])
        print(f"preset {args.preset}, {args.num_envs} envs x {args.rollout_steps} steps, {args.rounds} rounds of "
              f"{args.updates} updates each, load average {os.getloadavg()[0]:.1f}")
        print(f"fast paths      {f:9.0f} env steps/s")
        print(f"references      {ref:9.0f} env steps/s")
        print(f"ratio           {f / ref:9.2f}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
