"""The Gymnasium frame path, as another learner sees it: ``gym.make`` / ``gym.make_vec`` of
``tsnav/ObjectNav-v0`` stepped with random actions, rgb + depth + detections observations, the paper's TSRM
reward. Prints steps/s of today's frame path (``frames="memory"``, ``obs_layout="standard"``) against the
first release's (``frames="hdf5"``: one HDF5 dataset read per state and frame; ``obs_layout="legacy"``)
in one run, and their ratio. Goals (issue 26): >= 20 k env-steps/s with 64 envs and >= 5 k steps/s for the
single env, on one core, on the demo's rooms.

The loops use only ``gymnasium`` and ``numpy`` (the ``"tsnav.sim:"`` prefix of the id makes Gymnasium import
the package that registers it), as a user of another RL library would.

    tsnav world --preset demo-real --out W && tsnav detect --data W --detector shipped
    .venv/bin/python bench/bench_gym.py --data W [--split train] [--detections learned] [--seconds 5]
"""

from __future__ import annotations

import argparse
import os
import resource
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym
import numpy as np

ENV_ID = "tsnav.sim:tsnav/ObjectNav-v0"
PATHS = {"before": {"frames": "hdf5", "obs_layout": "legacy"}, "after": {"frames": "memory", "obs_layout": "standard"}}


def single(kw: dict, seconds: float, warmup: int) -> tuple[float, float]:
    """(steps/s, warm-up seconds) of one env stepped with random actions, reset when an episode ends."""
    t0 = time.perf_counter()
    env = gym.make(ENV_ID, **kw)
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    n, t, start = 0, t0, None
    while True:
        obs, r, term, trunc, info = env.step(int(rng.integers(0, 6)))
        if term or trunc:
            env.reset()
        n += 1
        if n == warmup:
            start, warm = time.perf_counter(), time.perf_counter() - t0
        elif n > warmup and n % 100 == 0 and time.perf_counter() - start >= seconds:
            t = time.perf_counter()
            break
    env.close()
    return (n - warmup) / (t - start), warm


def vector(kw: dict, num_envs: int, seconds: float, warmup: int) -> tuple[float, float]:
    """(env-steps/s, warm-up seconds) of ``num_envs`` envs of one vector env (same-step auto-reset)."""
    t0 = time.perf_counter()
    envs = gym.make_vec(ENV_ID, num_envs=num_envs, vectorization_mode="vector_entry_point", **kw)
    rng = np.random.default_rng(0)
    envs.reset(seed=0)
    n, t, start = 0, t0, None
    while True:
        obs, r, term, trunc, info = envs.step(rng.integers(0, 6, num_envs))
        n += 1
        if n == warmup:
            start, warm = time.perf_counter(), time.perf_counter() - t0
        elif n > warmup and n % 10 == 0 and time.perf_counter() - start >= seconds:
            t = time.perf_counter()
            break
    envs.close()
    return (n - warmup) * num_envs / (t - start), warm


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="a built world with detection tables (e.g. demo-real)")
    ap.add_argument("--split", default="train")
    ap.add_argument("--detections", default="learned", help="table name detections_<name>.hdf5")
    ap.add_argument("--reward", default="tsrm")
    ap.add_argument("--num-envs", type=int, default=64)
    ap.add_argument("--seconds", type=float, default=5.0, help="timed seconds per measurement")
    ap.add_argument("--warmup", type=int, default=200, help="untimed steps first (the memory path reads the "
                    "visited scenes' frames then; their time is printed as warm-up)")
    args = ap.parse_args()
    common = dict(data=args.data, split=args.split, reward=args.reward, detections=args.detections)
    print(f"{args.data} split {args.split}, reward {args.reward}, detections {args.detections}; load average "
          f"{os.getloadavg()[0]:.1f}")
    rows = []
    for what, fn in (("single env", lambda kw: single(kw, args.seconds, args.warmup)),
                     (f"vector env, {args.num_envs} envs",
                      lambda kw: vector(kw, args.num_envs, args.seconds, max(1, args.warmup // 4)))):
        rate = {}
        for name, kw in PATHS.items():
            rate[name], warm = fn({**common, **kw})
            print(f"  {what:22s} {name:6s} ({kw['frames']}, {kw['obs_layout']}): {rate[name]:10,.0f} steps/s "
                  f"(construction + warm-up {warm:.1f} s)", flush=True)
        rows.append((what, rate["before"], rate["after"]))
    print("\n| env | before steps/s | after steps/s | ratio |\n| --- | --- | --- | --- |")
    for what, b, a in rows:
        print(f"| {what} | {b:,.0f} | {a:,.0f} | {a / b:.1f}x |")
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB; load average "
          f"{os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
