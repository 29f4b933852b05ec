"""The Gymnasium frame path, as another learner sees it: ``gym.make`` / ``gym.make_vec`` of
``tsnav/ObjectNav-v1`` stepped with random actions, rgb + depth + detections observations, the paper's TSRM
reward. Prints steps/s of this checkout's default path ("after") against a "before" in one run, and their
ratio. Goals (issue 26): >= 20 k env-steps/s with 64 envs and >= 5 k steps/s for the single env, on one
core, on the demo's rooms.

"before" is another checkout's default path with ``--before-src OTHER/src`` (e.g. the main branch: the same
loops, that code), else this checkout's first-release path (``frames="hdf5"``: one HDF5 dataset read per
state and frame; ``obs_layout="legacy"``; the single env with ``stepping="batch"``). Every measurement runs in
its own process (``PYTHONPATH`` = the src folder it measures), in the order before, after, after, before
(``--rounds 2``, the default; 1: before, after), so that a load that drifts during the run weighs on both
alike; the table gives the mean of each path's rounds.

The loops use only ``gymnasium`` and ``numpy`` (the ``"tsnav.sim:"`` prefix of the id makes Gymnasium import
the package that registers it), as a user of another RL library would; the single env's random actions are
drawn in advance (a list of ints), the vector env's per step. Only the timing fills the frame cache before
the timed loop (its time is printed). Rates are given per wall second and per CPU second of the measuring
process: on a shared machine the second is what one core of its own would deliver.

    tsnav world --preset demo-real --out W && tsnav detect --data W --detector shipped
    .venv/bin/python bench/bench_gym.py --data W [--before-src OTHER/src] [--split train] [--seconds 5]
    .venv/bin/python bench/bench_gym.py --data W --memory   # peak RSS of a 64-env vector env, cache filled

With ``--memory`` it only builds the new path's vector env, fills its frame cache, steps it, and prints the
peak RSS against the cache's size, and that size for the 80 training rooms of ``ithor-real`` (266,288
states) at the world's frame size.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym
import numpy as np

ENV_ID = "tsnav.sim:tsnav/ObjectNav-v1"
TRAIN_STATES_ITHOR_REAL = 266_288
SRC = str(Path(__file__).resolve().parents[1] / "src")
#: The first release's frame path, this checkout's "before" without --before-src (the single env also steps
#: through the (1,) arrays, as the first release did).
FIRST_RELEASE = {"frames": "hdf5", "obs_layout": "legacy"}
FIRST_RELEASE_SINGLE = {**FIRST_RELEASE, "stepping": "batch"}


def _fill(env) -> None:
    """Fill the frame cache before timing (the loops time the steady state; construction and this fill are
    printed as warm-up). The one call outside gymnasium / numpy, and only for the timing."""
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
    it = itertools.cycle(np.random.default_rng(0).integers(0, 6, 1 << 16).tolist())
    env.reset(seed=0)
    warm = time.perf_counter() - t0

    def step():
        obs, r, term, trunc, info = env.step(next(it))
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


def child(args) -> None:
    """One measurement (``--child single|vector``) in this process; prints one JSON line."""
    kw = {
        "data": args.data,
        "split": args.split,
        "reward": args.reward,
        "detections": args.detections,
        **json.loads(args.kwargs),
    }
    if args.child == "single":
        wall, cpu, warm = single(kw, args.seconds, args.warmup)
    else:
        wall, cpu, warm = vector(kw, args.num_envs, args.seconds, max(1, args.warmup // 4))
    import tsnav  # imported by gymnasium through the env id; which checkout answered

    print(json.dumps({"wall": wall, "cpu": cpu, "warm": warm, "src": str(Path(tsnav.__file__).resolve().parents[1])}))


def measure(args, kind: str, src: str, kwargs: dict) -> dict:
    """Run one measurement in a child process with ``src`` first on its ``PYTHONPATH``."""
    cmd = [
        sys.executable,
        __file__,
        "--child",
        kind,
        "--kwargs",
        json.dumps(kwargs),
        "--data",
        args.data,
        "--split",
        args.split,
        "--reward",
        args.reward,
        "--detections",
        args.detections,
        "--num-envs",
        str(args.num_envs),
        "--seconds",
        str(args.seconds),
        "--warmup",
        str(args.warmup),
    ]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([src] + [p for p in [os.environ.get("PYTHONPATH")] if p])}
    out = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True).stdout
    got = json.loads(out.strip().splitlines()[-1])
    if Path(got["src"]) != Path(src).resolve():  # e.g. a --before-src without tsnav: the installed one answers
        raise SystemExit(f"bench_gym: the measurement meant for {src} imported tsnav from {got['src']}")
    return got


def _rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def memory(args) -> None:
    base = _rss_gib()
    t = time.perf_counter()
    envs = gym.make_vec(
        ENV_ID,
        num_envs=args.num_envs,
        vectorization_mode="vector_entry_point",
        data=args.data,
        split=args.split,
        reward=args.reward,
        detections=args.detections,
    )
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
    print(
        f"{args.data} split {args.split}: {envs.unwrapped.bank.num_scenes} scenes, {states:,} states, frames "
        f"{cache.height}x{cache.width}, depth {cache.depth.dtype}; load average {os.getloadavg()[0]:.1f}"
    )
    print(
        f"peak RSS: {base:.2f} GiB after imports, {built:.2f} GiB with the env built (cache untouched), "
        f"{peak:.2f} GiB with every scene's frames cached and 200 steps of {args.num_envs} envs "
        f"(cache {cache.nbytes / 2**30:.2f} GiB = {per:,.0f} B a state; filled in {filled:.0f} s)"
    )
    other = peak - cache.nbytes / 2**30
    big = TRAIN_STATES_ITHOR_REAL * per / 2**30
    print(
        f"80 training rooms of ithor-real at {cache.height} px ({TRAIN_STATES_ITHOR_REAL:,} states): cache "
        f"{big:.1f} GiB; peak RSS between {big + other:.1f} GiB (this run's other memory as is) and "
        f"{big + other * TRAIN_STATES_ITHOR_REAL / states:.1f} GiB (all of it growing with the states)"
    )


def main() -> None:
    ap = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="a built world with detection tables (e.g. demo-real)")
    ap.add_argument("--split", default="train")
    ap.add_argument("--detections", default="learned", help="table name detections_<name>.hdf5")
    ap.add_argument("--reward", default="tsrm")
    ap.add_argument("--num-envs", type=int, default=64)
    ap.add_argument("--seconds", type=float, default=5.0, help="timed seconds per measurement")
    ap.add_argument("--warmup", type=int, default=200, help="untimed steps first")
    ap.add_argument(
        "--before-src",
        default=None,
        help="another checkout's src folder: its default path is 'before' (default: this checkout's "
        "first-release path, frames='hdf5', obs_layout='legacy')",
    )
    ap.add_argument(
        "--rounds",
        type=int,
        default=2,
        choices=(1, 2),
        help="2: before, after, after, before (the default); 1: before, after",
    )
    ap.add_argument("--memory", action="store_true", help="measure peak RSS of the new path only")
    ap.add_argument("--child", choices=("single", "vector"), help=argparse.SUPPRESS)
    ap.add_argument("--kwargs", default="{}", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args)
    if args.memory:
        return memory(args)
    if args.before_src and not (Path(args.before_src) / "tsnav" / "__init__.py").is_file():
        raise SystemExit(f"bench_gym: --before-src {args.before_src} holds no tsnav package (give a checkout's src)")
    paths = {"before": (args.before_src, {}) if args.before_src else (SRC, FIRST_RELEASE), "after": (SRC, {})}
    print(
        f"{args.data} split {args.split}, reward {args.reward}, detections {args.detections}; before: "
        f"{args.before_src + ' (its default path)' if args.before_src else 'this checkout, ' + str(FIRST_RELEASE)}"
        f"; after: {SRC} (default path); load average {os.getloadavg()[0]:.1f}",
        flush=True,
    )
    order = ["before", "after"] + (["after", "before"] if args.rounds == 2 else [])
    rows = []
    for what, kind in (("single env", "single"), (f"vector env, {args.num_envs} envs", "vector")):
        got: dict[str, list] = {"before": [], "after": []}
        for name in order:
            src, kw = paths[name]
            r = measure(args, kind, src, FIRST_RELEASE_SINGLE if kw is FIRST_RELEASE and kind == "single" else kw)
            got[name].append((r["wall"], r["cpu"]))
            print(
                f"  {what:22s} {name:6s}: {r['wall']:10,.0f} steps/s wall, {r['cpu']:10,.0f} per CPU second "
                f"(construction + cache fill {r['warm']:.1f} s; load average {os.getloadavg()[0]:.1f})",
                flush=True,
            )
        rows.append((what, *(tuple(float(np.mean(v)) for v in zip(*got[n])) for n in ("before", "after"))))
    print("\n| env | before steps/s (wall / per CPU s) | after steps/s (wall / per CPU s) | ratio (wall / per CPU s) |")
    print("| --- | --- | --- | --- |")
    for what, (bw, bc), (aw, ac) in rows:
        print(f"| {what} | {bw:,.0f} / {bc:,.0f} | {aw:,.0f} / {ac:,.0f} | {aw / bw:.1f}x / {ac / bc:.1f}x |")
    print(f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
