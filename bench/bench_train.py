"""Training throughput: A3C (paper III-D; N worker processes, one episode each) vs the batched A2C trainer, same
network (agent preset), reward (TSRM) and feature cache, on this machine's CPU cores.

Each trainer runs for a fixed wall time in a temporary run folder through its real code path (tsnav.rl.a3c /
tsnav.rl.batched). Reported per trainer: environment steps per second in steady state (log windows after the
first, so start-up is excluded) and overall (start-up included), mean training episode length, episodes per
second, and the projected wall time of the paper's 1.5 M training episodes at that rate.

The batched trainer runs once per ``--procs`` value (data-parallel processes sharing each update's episodes,
``TrainConfig.procs``; with ``--ranks split staggered``, N > 1 processes also run in the mode where each steps
``--num-envs`` episodes of its own and a round applies their gradients in turn, ``TrainConfig.ranks``); each row
also gives its env steps per CPU-second of all its processes (how it would run with an idle core per process: on a
shared machine the wall-clock rate of N processes is capped by the cores left free), the load average over its run,
and, for N > 1, the ratio of its steps/s to the same setting with one process, measured in the same session. "idle
x" = N x (steps per CPU-second of N processes) / (that of one): the speed-up projected for an idle core per process
(all-reduce waits excluded; on a busy machine CPU time is itself inflated by the other jobs' use of the caches, so
compare ratios measured in one session).

    .venv/bin/python bench/bench_train.py --data /tmp/demo --features NAME [--seconds 60] [--workers 2]
        [--num-envs 64 256] [--preset cpu] [--precision fp32 bf16] [--threads 1] [--no-a3c] [--procs 1 2]
        [--ranks split staggered] [--log-every 5]

Without --data a tiny world is built in a temporary folder with pooled-pixel features.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

PAPER_EPISODES = 1_500_000


def training_world(tmp: Path, data: str | None, features: str | None, detections: str) -> tuple[Path, str]:
    """The benchmarks' training data: ``data`` (default: the ``tiny`` world built in ``tmp``), its feature cache
    ``features`` (default: pooled pixels, cached here) and, for ``oracle``, its oracle detection tables."""
    from tsnav.pipeline.steps import ensure_detections
    from tsnav.pretrain.pixels import cache_pixel_features

    if data is None:
        from tsnav.world.build import build_dataset

        data = tmp / "world"
        build_dataset(data, "tiny", workers=1, progress=False)
    if features is None:
        features = "bench_pixels"
        cache_pixel_features(data, features, grid=4, split="train")
    if detections == "oracle":
        ensure_detections(data, "oracle")
    return Path(data), features


def _summary(name: str, run: Path, progress: dict, wall: float) -> dict:
    from tsnav.rl.logger import read_log

    log = read_log(run)
    steady = [r for r in log[1:] if r.get("steps_per_s")]
    sps_steady = (sum(r["steps_per_s"] for r in steady) / len(steady)) if steady else float("nan")
    cpu = [r["steps_per_cpu_s"] for r in steady if r.get("steps_per_cpu_s")]
    n = sum(r.get("n_episodes", 0) for r in log)
    length = sum(r.get("length", 0) * r.get("n_episodes", 0) for r in log) / max(n, 1)
    sps_all = progress["env_steps"] / wall
    eps_s = sps_steady / length if length else float("nan")
    return {
        "trainer": name,
        "env_steps": progress["env_steps"],
        "episodes": progress["episodes"],
        "updates": progress["update"],
        "wall_s": wall,
        "steps_per_s_steady": sps_steady,
        "steps_per_s_overall": sps_all,
        "episode_length": length,
        "episodes_per_s": eps_s,
        "steps_per_cpu_s": sum(cpu) / len(cpu) if cpu else float("nan"),
        "hours_for_1.5M_episodes": PAPER_EPISODES / eps_s / 3600 if eps_s == eps_s and eps_s > 0 else float("nan"),
    }


def main() -> None:
    from tsnav.rl.config import PRECISIONS

    ap = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None, help="dataset root (default: a temporary tiny world)")
    ap.add_argument("--features", default=None, help="feature cache name (default: pooled pixels, built here)")
    ap.add_argument(
        "--detections",
        default="oracle",
        help="detection tables the agent reads (named explicitly; oracle tables are computed here)",
    )
    ap.add_argument("--seconds", type=float, default=60.0, help="wall time per trainer")
    ap.add_argument("--workers", type=int, default=2, help="A3C worker processes")
    ap.add_argument("--num-envs", type=int, nargs="+", default=[64, 256], help="batched trainer batch sizes")
    ap.add_argument("--rollout-steps", type=int, default=30)
    ap.add_argument("--preset", default="cpu", help="agent preset (cpu or paper)")
    ap.add_argument(
        "--precision",
        nargs="+",
        default=["fp32"],
        choices=PRECISIONS,
        help="batched trainer: forward passes in float32 and / or bfloat16 autocast (each is run)",
    )
    ap.add_argument("--threads", type=int, default=1, help="torch threads of the batched trainer's process (default 1)")
    ap.add_argument(
        "--procs",
        type=int,
        nargs="+",
        default=[1],
        help="batched trainer: data-parallel processes (each value is run; e.g. 1 2 for the ratio)",
    )
    ap.add_argument(
        "--ranks",
        nargs="+",
        default=["split"],
        choices=("split", "staggered"),
        help="how N > 1 processes share the work (TrainConfig.ranks; default split)",
    )
    ap.add_argument(
        "--no-a3c", action="store_true", help="batched trainer only (ratios are then to the first batch size)"
    )
    ap.add_argument(
        "--log-every",
        type=int,
        default=5,
        help="updates per log window (the steady rate averages the windows after the first)",
    )
    ap.add_argument("--out", default=None, help="write the figures as JSON here")
    args = ap.parse_args()

    from tsnav.agent import agent_config
    from tsnav.rl.a3c import train_a3c
    from tsnav.rl.batched import train_batched
    from tsnav.rl.config import TrainConfig

    tmp = Path(tempfile.mkdtemp(prefix="bench_train_"))
    try:
        data, features = training_world(tmp, args.data, args.features, args.detections)
        agent = agent_config(args.preset)
        minutes = args.seconds / 60.0
        base = dict(
            data=str(data),
            features=features,
            detections=args.detections,
            reward="tsrm",
            preset=args.preset,
            lr=1e-4,
            rollout_steps=args.rollout_steps,
            max_steps=30,
            minutes=minutes,
            log_every=args.log_every,
            checkpoint_every=10**9,
            device="cpu",
        )
        results = []
        t = time.perf_counter()
        if not args.no_a3c:
            run = tmp / "a3c"
            p = train_a3c(
                TrainConfig(algo="a3c", workers=args.workers, threads=1, **base), agent, run, progress_bar=False
            )
            results.append(_summary(f"A3C, {args.workers} workers x 1 episode", run, p, time.perf_counter() - t))
        for b in args.num_envs:
            for prec in args.precision:
                one = None
                for n, mode in [(n, m) for n in args.procs for m in (args.ranks if n > 1 else ["split"])]:
                    t = time.perf_counter()
                    run = tmp / f"batched{b}_{prec}_p{n}_{mode}"
                    load0 = os.getloadavg()[0]
                    every = -(-args.log_every // n) * n if mode == "staggered" else args.log_every
                    p = train_batched(
                        TrainConfig(
                            algo="batched",
                            num_envs=b,
                            precision=prec,
                            threads=args.threads,
                            procs=n,
                            ranks=mode,
                            **{**base, "log_every": every},
                        ),
                        agent,
                        run,
                        progress_bar=False,
                    )
                    rows = f"{b} episodes each, staggered" if mode == "staggered" else f"{b // n} episodes"
                    r = _summary(f"batched A2C, {n} proc x {rows}, {prec}", run, p, time.perf_counter() - t)
                    r["load_1min"] = [load0, os.getloadavg()[0]]
                    r["procs"] = n
                    r["ranks"] = mode
                    if n == 1:
                        one = r
                    r["x_1_proc"] = r["steps_per_s_steady"] / one["steps_per_s_steady"] if one else float("nan")
                    r["cpu_x_1_proc"] = r["steps_per_cpu_s"] / one["steps_per_cpu_s"] if one else float("nan")
                    r["projected_x_1_proc"] = n * r["cpu_x_1_proc"]  # with an idle core per process
                    results.append(r)

        ref = results[0]["steps_per_s_steady"]
        print(
            f"data {data}, features {features}, agent preset {args.preset}, reward tsrm, "
            f"rollout {args.rollout_steps} steps, {args.threads} thread(s), {args.seconds:.0f} s per trainer"
        )
        head = (
            f"{'trainer':<62} {'steps/s':>9} {'(overall)':>10} {'x A3C':>6} {'x 1 proc':>8} {'steps/CPU-s':>11} "
            f"{'(x 1 proc)':>10} {'idle x':>6} {'load':>9} {'ep len':>7} {'ep/s':>7} {'h for 1.5M ep':>14}"
        )
        print(head)
        print("-" * len(head))
        for r in results:
            load = "-" if "load_1min" not in r else "{:.1f}-{:.1f}".format(*r["load_1min"])
            print(
                f"{r['trainer']:<62} {r['steps_per_s_steady']:9.0f} {r['steps_per_s_overall']:10.0f} "
                f"{r['steps_per_s_steady'] / ref:6.1f} {r.get('x_1_proc', float('nan')):8.2f} "
                f"{r.get('steps_per_cpu_s', float('nan')):11.0f} {r.get('cpu_x_1_proc', float('nan')):10.2f} "
                f"{r.get('projected_x_1_proc', float('nan')):6.2f} "
                f"{load:>9} {r['episode_length']:7.1f} {r['episodes_per_s']:7.1f} "
                f"{r['hours_for_1.5M_episodes']:14.1f}"
            )
        if args.out:
            Path(args.out).write_text(json.dumps(results, indent=1) + "\n")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
