"""One batched-A2C update (rollout with gradients, GAE, loss, backward, Adam step), with the trainer's fast paths
and with their slow references, alternated in one process so that a shared, noisy machine affects both alike.

Variants (each fast path is bit for bit its reference, except the attention's, which is the same function):
- ``fast``: today's paths: the memory attention with key and value projections moved to the query side
  (``TargetMemoryAggregator.attend``) written as batched products, the collector's ``Policy``, and in bf16 the
  weights cast once per rollout (``RolloutCollector(cast_once=True)``);
- ``einsum``: the paths before session 26: the same attention through ``torch.einsum`` (``attend_einsum``),
  ``torch.distributions.Categorical``, autocast's per-step weight casts;
- ``reference``: ``nn.MultiheadAttention``'s own forward (``attend_reference``) with ``einsum``'s other paths.

    .venv/bin/python bench/bench_update.py [--preset cpu|paper] [--precision fp32|bf16] [--num-envs 256]
        [--rounds 6]

Without --data a tiny world is built in a temporary folder with pooled-pixel features; the TSRM reward and the
oracle detection table are used. Prints env steps/s of each variant (median over rounds) and their ratios.
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

    ap = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--features", default=None)
    ap.add_argument("--detections", default="oracle", help="detection tables the agent reads (named explicitly)")
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--precision", default="fp32", choices=("fp32", "bf16"))
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
    from tsnav.rl import rollout
    from tsnav.rl.rollout import Policy, RolloutCollector, collect_and_loss

    class CategoricalPolicy:
        """``Policy`` through ``torch.distributions.Categorical`` (the collector's path before session 26)."""

        def __init__(self, logits):
            self.dist = torch.distributions.Categorical(logits=logits)

        @property
        def probs(self):
            return self.dist.probs

        def sample(self, generator=None):
            if generator is None:
                return self.dist.sample()
            return torch.multinomial(self.dist.probs.detach(), 1, generator=generator)[:, 0]

        def log_prob(self, action):
            return self.dist.log_prob(action)

        def entropy(self):
            return self.dist.entropy()

    torch.set_num_threads(1)
    tmp = Path(tempfile.mkdtemp(prefix="bench_update_"))
    try:
        data, features = training_world(tmp, args.data, args.features, args.detections)
        cfg = TrainConfig(
            data=str(data),
            features=features,
            detections=args.detections,
            reward="tsrm",
            algo="batched",
            num_envs=args.num_envs,
            precision=args.precision,
            rollout_steps=args.rollout_steps,
            device="cpu",
        )
        bank, det = load_bank(cfg)
        observer = make_observer(bank, cfg, det_features=det)
        model = make_model(agent_config(args.preset), observer, 0)
        opt = torch.optim.Adam(model.parameters(), lr=1e-4, amsgrad=True)
        collector = RolloutCollector(
            make_train_env(bank, cfg, args.num_envs, seed=0), observer, model, precision=args.precision
        )
        collector.start()
        attend = {
            "fast": TargetMemoryAggregator.attend,
            "einsum": TargetMemoryAggregator.attend_einsum,
            "reference": TargetMemoryAggregator.attend_reference,
        }

        def use(name: str) -> None:
            TargetMemoryAggregator.attend = attend[name]
            rollout.Policy = Policy if name == "fast" else CategoricalPolicy
            collector.cast_once = name == "fast"

        def update_rate(name: str) -> float:
            use(name)
            t = time.perf_counter()
            for _ in range(args.updates):
                _, loss, _ = collect_and_loss(collector, cfg)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
            return args.updates * args.num_envs * args.rollout_steps / (time.perf_counter() - t)

        for name in attend:  # warm-up
            update_rate(name)
        rates = {name: [] for name in attend}
        for r in range(args.rounds):
            for name in list(attend) if r % 2 == 0 else list(attend)[::-1]:
                rates[name].append(update_rate(name))
        use("fast")
        med = {name: statistics.median(v) for name, v in rates.items()}
        print(
            f"preset {args.preset}, {args.precision}, {args.num_envs} envs x {args.rollout_steps} steps, "
            f"{args.rounds} rounds of {args.updates} updates each, load average {os.getloadavg()[0]:.1f}"
        )
        for name, v in med.items():
            print(f"{name:<10} {v:9.0f} env steps/s   x einsum {v / med['einsum']:5.2f}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
