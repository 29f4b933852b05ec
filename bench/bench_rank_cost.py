"""What bounds the data-parallel batched trainer (``TrainConfig.procs``): the CPU time of one update (rollout with
gradients, GAE, loss, backward, Adam step) over B episode rows against B / N rows, the share each of N ranks
computes, alternated in one process so that a shared machine affects both alike.

With an idle core per rank, N ranks take ``cost(B / N)`` per update (plus one all-reduce of the gradients) where
one process takes ``cost(B)``: the speed-up is at most ``cost(B) / cost(B / N)``, below N by the share of an
update that does not shrink with the rows (per-step Python and operator dispatch, the weights' bfloat16 casts,
the Adam step). CPU time (``time.process_time``) is reported, not wall time, so that other jobs' use of the
cores does not count; it is still inflated a little by their use of the caches.

    .venv/bin/python bench/bench_rank_cost.py [--preset cpu|paper] [--precision fp32|bf16] [--num-envs 256]
        [--procs 2] [--rounds 5] [--per-step-cast]

In bf16 the trainer casts the weights to bfloat16 once per rollout (``RolloutCollector(cast_once=True)``);
``--per-step-cast`` also measures autocast's cast at every step (the path before, bit for bit the same results),
alternated with it in the same rounds.

Without --data a tiny world is built in a temporary folder with pooled-pixel features; the TSRM reward and the
oracle detection table are used, one torch thread.
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
    ap.add_argument("--procs", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--updates", type=int, default=3, help="updates per round and batch size")
    ap.add_argument(
        "--per-step-cast",
        action="store_true",
        help="bf16: also measure autocast's per-step weight casts (the path before cast-once)",
    )
    args = ap.parse_args()

    import torch

    from tsnav.agent import agent_config
    from tsnav.rl.assemble import load_bank, make_model, make_observer, make_train_env
    from tsnav.rl.config import TrainConfig
    from tsnav.rl.rollout import RolloutCollector, collect_and_loss

    torch.set_num_threads(1)
    tmp = Path(tempfile.mkdtemp(prefix="bench_rank_cost_"))
    try:
        data, features = training_world(tmp, args.data, args.features, args.detections)
        cfg = TrainConfig(
            data=str(data),
            features=features,
            detections=args.detections,
            algo="batched",
            preset=args.preset,
            precision=args.precision,
            device="cpu",
        )
        bank, det = load_bank(cfg)
        observer = make_observer(bank, cfg, det_features=det)
        sizes = (args.num_envs, args.num_envs // args.procs)
        if args.per_step_cast and args.precision != "bf16":
            raise SystemExit("--per-step-cast compares bfloat16 weight casts: use it with --precision bf16")
        variants = (
            {"cast once per rollout": True, "autocast's per-step cast": False} if args.per_step_cast else {"": True}
        )
        runs = {}
        for v, once in variants.items():
            for b in sizes:
                model = make_model(agent_config(args.preset), observer, 0)
                opt = torch.optim.Adam(model.parameters(), lr=1e-4, amsgrad=True)
                col = RolloutCollector(
                    make_train_env(bank, cfg, b, seed=0), observer, model, precision=args.precision, cast_once=once
                )
                runs[v, b] = (model, opt, col)

        def update(key) -> None:
            model, opt, col = runs[key]
            _, loss, _ = collect_and_loss(col, cfg)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.max_grad_norm)
            opt.step()

        for key in runs:  # warm-up
            update(key)
        per_step = {key: [] for key in runs}
        load0 = os.getloadavg()[0]
        for _ in range(args.rounds):
            for key in runs:
                t = time.process_time()
                for _ in range(args.updates):
                    update(key)
                per_step[key].append((time.process_time() - t) / (args.updates * cfg.rollout_steps))
        print(
            f"preset {args.preset}, {args.precision}, rollout {cfg.rollout_steps} steps, 1 thread, "
            f"load {load0:.1f}-{os.getloadavg()[0]:.1f}; median CPU ms per rollout step over {args.rounds} rounds"
        )
        for v in variants:
            big, small = (statistics.median(per_step[v, b]) for b in sizes)
            if v:
                print(f"{v}:")
            print(f"  1 process x {sizes[0]} rows: {1e3 * big:7.2f} ms  ({sizes[0] / big:8.0f} env steps per CPU-s)")
            print(
                f"  1 rank    x {sizes[1]} rows: {1e3 * small:7.2f} ms  ({sizes[1] / small:8.0f} env steps per CPU-s)"
            )
            print(
                f"  bound on the speed-up of {args.procs} ranks with idle cores: {big / small:.2f}x; rows-independent "
                f"cost per step (linear fit): {1e3 * (args.procs * small - big) / (args.procs - 1):.2f} ms"
            )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
