"""The Gymnasium frame path, as another learner sees it: ``gym.make`` / ``gym.make_vec`` of
``tsnav/ObjectNav-v0`` stepped with random actions, rgb + depth + detections observations, the paper's TSRM
reward. Prints steps/s of today's frame path (``frames="memory"``, ``obs_layout="standard"``) against the
first release's (``frames="hdf5"``: one HDF5 dataset read per state and frame; ``obs_layout="legacy"``)
in one run, and their ratio. Goals (issue 26): >= 20 k env-steps/s with 64 envs and >= 5 k steps/s for the
single env, on one core, on the demo's rooms.

The loops use only ``gymnasium`` and ``numpy`` (the ``"tsnav.sim:"`` prefix of the id makes Gymnasium import
the package that registers it), as a user of another RL library would; only the timing fills the new path's
frame cache before the timed loop (its time is printed). Rates are given per wall second and per CPU second
of this process: on a shared machine the second is what one core of its own would deliver.

    tsnav world --preset demo-real --out W && tsnav detect --data W --detector shipped
    .venv/bin/python bench/bench_gym.py --data W [--split train] [--detections learned] [--seconds 5]
    .venv/bin/python bench/bench_gym.py --data W --memory   # peak RSS of a 64-env vector env, cache filled

With ``--memory`` it only builds the new path's vector env, fills its frame cache, steps it, and prints the
peak RSS against the cache's size, and that size for the 80 training rooms of ``ithor-real`` (266,288
states) at the world's frame size.
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
TRAIN_STATES_ITHOR_REAL = 266_288
PATHS = {"before": {"frames": "hdf5", "obs_layout": "legacy"}, "after": {"frames": "memory", "obs_layout": "standard"}}


def _fill(env) -> None:
    """Fill the frame cache of the new path before timing (the loops time the steady state; construction and
    this fill are printed as warm-up). The one call outside gymnasium / numpy, and only for the timing."""
    cache = getattr(getattr(env.unwrapped, "obs_source", None), "cache", None)
    if cache is not None:
        cache.load()


def _timed(step, seconds: float, warmup: int, check_every: int) -> tuple[float, float]:
    """(steps per wall second, steps per CPU second of this process) of ``step()`` after ``warmup`` calls."""
    for _ in range(warmup):
        step()
    n, t0, c0 = 0, time.perf_counter(), time.process_time()
    while True:
        step()
        n += 1
        if n % check_every == 0 and time.perf_counter() - t0 >= seconds:
            return n / (time.perf_counter() - t0), n / (time.process_time() - c0)


def single(kw: dict, seconds: float, warmup: int) -> tuple[float, float, float]:
    """(steps/s wall, steps/s CPU, warm-up seconds) of one env stepped with random actions, reset when an
    episode ends."""
    t0 = time.perf_counter()
    env = gym.make(ENV_ID, **kw)
    _fill(env)
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    warm = time.perf_counter() - t0

    def step():
        obs, r, term, trunc, info = env.step(int(rng.integers(0, 6)))
        if term or trunc:
            env.reset()

    wall, cpu = _timed(step, seconds, warmup, 100)
    env.close()
    return wall, cpu, warm


def vector(kw: dict, num_envs: int, seconds: float, warmup: int) -> tuple[float, float, float]:
    """(env-steps/s wall, env-steps/s CPU, warm-up seconds) of ``num_envs`` envs of one vector env (same-step
    auto-reset)."""
    t0 = time.perf_counter()
    envs = gym.make_vec(ENV_ID, num_envs=num_envs, vectorization_mode="vector_entry_point", **kw)
    _fill(envs)
    rng = np.random.default_rng(0)
    envs.reset(seed=0)
    warm = time.perf_counter() - t0

    def step():
        envs.step(rng.integers(0, 6, num_envs))

    wall, cpu = _timed(step, seconds, warmup, 10)
    envs.close()
    return wall * num_envs, cpu * num_envs, warm


def _rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def memory(args) -> None:
    base = _rss_gib()
    t = time.perf_counter()
    envs = gym.make_vec(ENV_ID, num_envs=args.num_envs, vectorization_mode="vector_entry_point", data=args.data,
                        split=args.split, reward=args.reward, detections=args.detections)
    built = _rss_gib()
    cache = envs.unwrapped.obs_source.cache
    cache.load()
    filled = time.perf_counter() - t
    rng = np.random.default_rng(0)
    envs.reset(seed=0)
    for _ in range(200):
        envs.step(rng.integers(0, 6, args.num_envs))
    peak = _rss_gib()
    states = envs.unwrapped.bank.num_states
    per = cache.nbytes / states
    print(f"{args.data} split {args.split}: {envs.unwrapped.bank.num_scenes} scenes, {states:,} states, frames "
          f"{cache.height}x{cache.width}, depth {cache.depth.dtype}; load average {os.getloadavg()[0]:.1f}")
    print(f"peak RSS: {base:.2f} GiB after imports, {built:.2f} GiB with the env built (cache untouched), "
          f"{peak:.2f} GiB with every scene's frames cached and 200 steps of {args.num_envs} envs "
          f"(cache {cache.nbytes / 2**30:.2f} GiB = {per:,.0f} B a state; filled in {filled:.0f} s)")
    other = peak - cache.nbytes / 2**30
    big = TRAIN_STATES_ITHOR_REAL * per / 2**30
    print(f"80 training rooms of ithor-real at {cache.height} px ({TRAIN_STATES_ITHOR_REAL:,} states): cache "
          f"{big:.1f} GiB; peak RSS between {big + other:.1f} GiB (this run's other memory as is) and "
          f"{big + other * TRAIN_STATES_ITHOR_REAL / states:.1f} GiB (all of it growing with the states)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="a built world with detection tables (e.g. demo-real)")
    ap.add_argument("--split", default="train")
    ap.add_argument("--detections", default="learned", help="table name detections_<name>.hdf5")
    ap.add_argument("--reward", default="tsrm")
    ap.add_argument("--num-envs", type=int, default=64)
    ap.add_argument("--seconds", type=float, default=5.0, help="timed seconds per measurement")
    ap.add_argument("--warmup", type=int, default=200, help="untimed steps first")
    ap.add_argument("--memory", action="store_true", help="measure peak RSS of the new path only")
    args = ap.parse_args()
    if args.memory:
        return memory(args)
    common = dict(data=args.data, split=args.split, reward=args.reward, detections=args.detections)
    print(f"{args.data} split {args.split}, reward {args.reward}, detections {args.detections}; load average "
          f"{os.getloadavg()[0]:.1f}")
    rows = []
    for what, fn in (("single env", lambda kw: single(kw, args.seconds, args.warmup)),
                     (f"vector env, {args.num_envs} envs",
                      lambda kw: vector(kw, args.num_envs, args.seconds, max(1, args.warmup // 4)))):
        rate = {}
        for name, kw in PATHS.items():
            wall, cpu, warm = fn({**common, **kw})
            rate[name] = (wall, cpu)
            print(f"  {what:22s} {name:6s} ({kw['frames']}, {kw['obs_layout']}): {wall:10,.0f} steps/s wall, "
                  f"{cpu:10,.0f} per CPU second (construction + cache fill {warm:.1f} s)", flush=True)
        rows.append((what, rate["before"], rate["after"]))
    print("\n| env | before steps/s (wall / CPU) | after steps/s (wall / CPU) | ratio (wall / CPU) |")
    print("| --- | --- | --- | --- |")
    for what, (bw, bc), (aw, ac) in rows:
        print(f"| {what} | {bw:,.0f} / {bc:,.0f} | {aw:,.0f} / {ac:,.0f} | {aw / bw:.1f}x / {ac / bc:.1f}x |")
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB; load average "
          f"{os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
