"""The Gymnasium env's fast paths against their references, bit for bit (issue 26, "a frame path fit for other
learners").

* The single env's ``stepping="scalar"`` (``BatchEnv.step_one`` / ``reset_one``, ``TSRMReward.step_one``,
  ``StageSwitch.update_one``, ``BatchCoverage.add_one``, ``TrainingSampler.sample_one``, ``Observations.one``)
  against ``stepping="batch"``, the ``(1,)`` arrays of ``BatchEnv.step`` that the env stepped through before:
  the same seeds and actions give the same observations (values, dtypes, shapes), rewards, flags and ``info``
  (values and types), and leave the env, its stage switch and its reward in the same state.
* The vector env against a loop written from a bare ``BatchEnv`` and the per-key HDF5 reader: observations,
  rewards, flags, ``info`` and the final observations of ended episodes.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from tsnav.constants import NUM_CATEGORIES

ENV_ID = "tsnav.sim:tsnav/ObjectNav-v1"


@pytest.fixture(scope="module")
def world(tiny_world):
    from tsnav.pipeline.steps import ensure_oracle_detections

    ensure_oracle_detections(tiny_world, "oracle")
    return tiny_world


def _same_obs(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        if isinstance(a[k], np.ndarray):
            assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape and np.array_equal(a[k], b[k]), k
            assert not np.shares_memory(a[k], b[k])
        else:
            assert type(a[k]) is type(b[k]) and a[k] == b[k], k


def _same_info(a: dict, b: dict) -> None:
    assert list(a) == list(b)
    for k in a:
        assert type(a[k]) is type(b[k]) and a[k] == b[k], (k, a[k], b[k])
        if isinstance(a[k], float):
            assert np.signbit(a[k]) == np.signbit(b[k]), k


def _same_state(fast, ref) -> None:
    """The env's, its stage switch's and its reward's arrays after the same steps."""
    fb, rb = fast.batch, ref.batch
    for k in ("state", "start", "target", "scene", "steps", "path_length", "active"):
        assert np.array_equal(getattr(fb, k), getattr(rb, k)), k
    for k in ("target", "entered", "switch_step", "switch_length", "switch_state"):
        assert np.array_equal(getattr(fb.stage, k), getattr(rb.stage, k)), k
    fr, rr = fb.reward_fn, rb.reward_fn
    if hasattr(fr, "viewed"):
        for k in ("scene", "target", "collided_at", "viewed"):
            assert np.array_equal(getattr(fr, k), getattr(rr, k)), k
        if fr.coverage is not None:
            assert np.array_equal(fr.coverage._flat, rr.coverage._flat)
            assert np.array_equal(fr.coverage.samples, rr.coverage.samples)
        assert np.array_equal(fr.searched_area, rr.searched_area)
    assert fb.np_random.bit_generator.state == rb.np_random.bit_generator.state


def _run_pair(kw: dict, steps: int, seed: int, check_state: bool = True, episode=None) -> dict:
    fast = gym.make(ENV_ID, stepping="scalar", **kw)
    ref = gym.make(ENV_ID, stepping="batch", **kw)
    assert fast.unwrapped.stepping == "scalar" and ref.unwrapped.stepping == "batch"
    rng = np.random.default_rng(seed)
    seen = {"ends": 0, "explore": 0, "distance": 0, "collision": 0, "success": 0}
    o1, i1 = fast.reset(seed=seed)
    o2, i2 = ref.reset(seed=seed)
    _same_obs(o1, o2)
    _same_info(i1, i2)
    cache = fast.unwrapped.obs_source.cache
    for t in range(steps):
        a = int(rng.integers(0, 6))
        r1, r2 = fast.step(a), ref.step(a)
        _same_obs(r1[0], r2[0])
        if cache is not None:  # new arrays, not views of the frame cache
            assert not np.shares_memory(r1[0]["rgb"], cache.rgb) and not np.shares_memory(r1[0]["depth"], cache.depth)
        assert type(r1[1]) is float and r1[1] == r2[1] and np.signbit(r1[1]) == np.signbit(r2[1])
        assert r1[2:4] == r2[2:4] and all(type(x) is bool for x in r1[2:4])
        _same_info(r1[4], r2[4])
        info = r1[4]
        for k in ("explore", "distance", "collision", "success"):
            seen[k] += f"reward/{k}" in info and info[f"reward/{k}"] != 0.0
        if check_state:
            _same_state(fast.unwrapped, ref.unwrapped)
        if r1[2] or r1[3]:
            seen["ends"] += 1
            if seen["ends"] % 5 == 0:  # a step past the end first (frozen row, zero reward), then a reset
                _same_info(fast.step(0)[4], ref.step(0)[4])
            if episode is not None and seen["ends"] % 3 == 0:
                o1, i1 = fast.reset(options={"episode": episode})
                o2, i2 = ref.reset(options={"episode": episode})
            else:
                s = None if seen["ends"] % 4 else seed + t
                o1, i1 = fast.reset(seed=s)
                o2, i2 = ref.reset(seed=s)
            _same_obs(o1, o2)
            _same_info(i1, i2)
    fast.close()
    ref.close()
    return seen


@pytest.mark.parametrize("reward", ["tsrm", "explore", "distance", "baseline", "sparse"])
def test_single_env_scalar_path_equals_batch_path(world, reward):
    seen = _run_pair(
        dict(data=str(world), split=None, reward=reward, detections="oracle", max_steps=12), steps=600, seed=3
    )
    assert seen["ends"] > 20 and seen["success"] > 0 and (seen["collision"] > 0 or reward == "sparse")
    if reward in ("tsrm", "explore"):
        assert seen["explore"] > 0
    if reward in ("tsrm", "distance"):
        assert seen["distance"] > 0


@pytest.mark.parametrize("frames,layout", [("memory", "legacy"), ("hdf5", "standard")])
def test_single_env_scalar_path_other_frames_and_layouts(world, frames, layout):
    """The frame layouts and the per-key HDF5 frames, with episodes given by ``reset(options=)`` among them."""
    from tsnav.constants import TARGET_CATEGORIES
    from tsnav.sim.batch import SceneBank

    bank = SceneBank.from_root(world, None)
    target = int(np.flatnonzero(bank.present[0])[0])
    episode = (bank.names[0], TARGET_CATEGORIES[target], str(bank.scenes[0].keys[0]))
    _run_pair(
        dict(
            data=str(world),
            split=None,
            reward="tsrm",
            detections="oracle",
            max_steps=10,
            frames=frames,
            obs_layout=layout,
        ),
        steps=150,
        seed=5,
        episode=episode,
    )


def test_single_env_scalar_path_exact_area_and_lineage_protocol(world):
    """The shapely searched region (``exact_area``) and the lineage's success protocol through both paths."""
    from tsnav.tsrm.reward import RewardConfig

    _run_pair(
        dict(
            data=str(world),
            split=None,
            reward=RewardConfig(variant="tsrm", exact_area=True, distance_increase_scale=1.5),
            detections="oracle",
            max_steps=8,
        ),
        steps=60,
        seed=2,
    )
    _run_pair(
        dict(
            data=str(world),
            split=None,
            reward="tsrm",
            detections="oracle",
            protocol="lineage",
            c_target=0.5,
            max_steps=15,
        ),
        steps=200,
        seed=9,
    )


class _ArrayOnlyReward:
    """A reward with only the array interface (no ``step_one``): the scalar path calls its ``step``."""

    uses_stage = True

    def reset(self, mask, scene_idx, target, start_state, searching) -> None:
        self.calls = getattr(self, "calls", 0) + 1

    def step(self, prev_state, action, new_state, collided, done, success, searching):
        r = (0.5 * searching + 0.25 * collided + 1.0 * success - 0.1 * done).astype(np.float32)
        return r, {"shaped": r, "steps": np.ones_like(r)}


def test_batch_env_step_one_equals_step(world):
    """``BatchEnv.step_one`` / ``reset_one`` against ``step`` / ``reset`` directly: no reward, a reward with
    only the array interface, and auto-reset on."""
    from tsnav.sim.batch import BatchEnv, SceneBank
    from tsnav.sim.episodes import TrainingSampler

    bank = SceneBank.from_root(world, None)
    sampler = TrainingSampler(bank)
    for reward_fn, autoreset in ((None, False), ("array", False), ("array", True)):
        envs = [
            BatchEnv(
                bank,
                1,
                sampler=sampler,
                reward_fn=_ArrayOnlyReward() if reward_fn else None,
                max_steps=7,
                autoreset=autoreset,
                seed=4,
            )
            for _ in range(2)
        ]
        fast, ref = envs
        fast.reset_one()
        ref.reset()
        rng = np.random.default_rng(1)
        for _ in range(300):
            a = int(rng.integers(0, 6))
            r, term, trunc, info = fast.step_one(a)
            _, r2, term2, trunc2, info2 = ref.step(np.array([a]))
            assert r == float(r2[0]) and term == bool(term2[0]) and trunc == bool(trunc2[0])
            assert info["reward_terms"] == {k: float(v[0]) for k, v in info2["reward_terms"].items()}
            for k, v in info.items():
                if k != "reward_terms":
                    assert v == info2[k][0] and type(v) in (bool, int), k
            for k in ("state", "target", "scene", "steps", "path_length", "active"):
                assert np.array_equal(getattr(fast, k), getattr(ref, k)), k
            if not autoreset and (term or trunc) and rng.random() < 0.7:
                fast.reset_one()
                ref.reset()
        with pytest.raises(ValueError, match="actions must be in"):
            fast.step_one(6)
    with pytest.raises(ValueError, match="num_envs == 1"):
        BatchEnv(bank, 2, sampler=sampler).step_one(0)


def test_sampler_and_coverage_one_equal_their_batch(world):
    """``TrainingSampler.sample_one`` draws what ``sample(1)`` draws; ``BatchCoverage.add_one`` /
    ``reset_one`` keep the raster ``add`` / ``reset`` keep."""
    from tsnav.sim.batch import SceneBank
    from tsnav.sim.episodes import TrainingSampler
    from tsnav.tsrm.area import AreaIndex, BatchCoverage

    bank = SceneBank.from_root(world, None)
    sampler = TrainingSampler(bank)
    for seed in range(50):
        r1, r2 = np.random.default_rng(seed), np.random.default_rng(seed)
        for _ in range(5):
            one, batch = sampler.sample_one(r1), sampler.sample(1, r2)
            assert one == tuple(int(v[0]) for v in batch) and all(type(v) is int for v in one)
        assert r1.bit_generator.state == r2.bit_generator.state
    index = AreaIndex.from_scenes(bank.scenes)
    fast, ref = BatchCoverage(index, 3), BatchCoverage(index, 3)
    rng = np.random.default_rng(0)
    for t in range(400):
        b = int(rng.integers(0, 3))
        if t % 37 == 0:
            scene = int(rng.integers(0, bank.num_scenes))
            fast.reset_one(b, scene)
            mask = np.zeros(3, dtype=bool)
            mask[b] = True
            ref.reset(mask, np.full(3, scene))
        lo, hi = bank.offsets[int(fast.scene[b])], bank.offsets[int(fast.scene[b]) + 1]
        s = int(rng.integers(lo, hi))
        g = fast.add_one(b, s)
        assert type(g) is float and g == ref.add(np.array([b]), np.array([s]))[0]
        assert np.array_equal(fast._flat, ref._flat) and np.array_equal(fast.samples, ref.samples)


def test_vector_env_equals_a_loop_over_batch_env(world):
    """The vector env's step against what a bare ``BatchEnv`` (the same seed, sampler and reward) and the per-key
    HDF5 reader give: observations (the target a copy, not the env's own array), rewards, flags, ``info`` and
    the final observations and infos of ended episodes (Gymnasium's same-step auto-reset)."""
    from tsnav.sim.batch import BatchEnv
    from tsnav.sim.gym_env import Observations
    from tsnav.tsrm.reward import TERMS, RewardConfig, TSRMReward

    n = 16
    envs = gym.make_vec(
        ENV_ID,
        num_envs=n,
        vectorization_mode="vector_entry_point",
        data=str(world),
        split=None,
        reward="tsrm",
        detections="oracle",
        max_steps=9,
    )
    u = envs.unwrapped
    bank = u.bank
    ref = BatchEnv(bank, n, sampler=u.sampler, reward_fn=TSRMReward(bank, RewardConfig()), max_steps=9)
    frames = Observations(bank, frames="hdf5")
    obs, info = envs.reset(seed=6)
    ref.np_random = np.random.Generator(np.random.PCG64(6))
    ref.reset()

    def expected_obs(state, target):
        rgb, depth = frames.read_frames(state, frames.depth_dtype)
        det = bank.detections[state].reshape(len(state), NUM_CATEGORIES * 6)
        return {"rgb": rgb, "depth": depth[..., None], "target": np.asarray(target), "detections": det}

    def same(a, b):
        for k in b:
            assert np.array_equal(a[k], b[k]) and np.asarray(a[k]).dtype == np.asarray(b[k]).dtype, k

    same(obs, expected_obs(ref.state, ref.target))
    assert np.array_equal(info["state"], ref.state) and np.array_equal(info["scene"], ref.scene)
    rng = np.random.default_rng(2)
    ended = 0
    for _ in range(60):
        a = rng.integers(0, 6, n)
        held = obs
        target = ref.target.copy()
        obs, r, term, trunc, info = envs.step(a)
        _, r2, term2, trunc2, info2 = ref.step(a)
        same(obs, expected_obs(ref.state, ref.target))
        assert held["target"] is not obs["target"] and not np.shares_memory(obs["target"], u.batch.target)
        assert r.dtype == np.float64 and np.array_equal(r, r2.astype(np.float64))
        assert np.array_equal(term, term2) and np.array_equal(trunc, trunc2)
        want = {
            "state": ref.state,
            "scene": ref.scene,
            **{k: info2[k] for k in ("collided", "failed", "success", "steps", "path_length")},
            **{f"reward/{k}": info2["reward_terms"][k] for k in TERMS},
        }
        for k, v in want.items():
            assert np.array_equal(info[k], v) and info[k].dtype == v.dtype, k
            assert info[f"_{k}"].all()
        fin = term2 | trunc2
        assert ("final_obs" in info) == bool(fin.any())
        if fin.any():
            ended += int(fin.sum())
            assert np.array_equal(info["_final_obs"], fin) and np.array_equal(info["_final_info"], fin)
            last = expected_obs(info2["final_state"][fin], target[fin])
            for k, j in enumerate(np.flatnonzero(fin)):
                fo = info["final_obs"][j]
                assert fo["target"] == last["target"][k] and type(fo["target"]) is int
                for key in ("rgb", "depth", "detections"):
                    assert np.array_equal(fo[key], last[key][k]) and fo[key].dtype == last[key].dtype
            assert all(info["final_obs"][j] is None for j in np.flatnonzero(~fin))
            for k in ("success", "steps", "path_length"):
                assert np.array_equal(info["final_info"][k], np.where(fin, info2[k], 0)), k
            assert np.array_equal(info["final_info"]["state"], np.where(fin, info2["final_state"], 0))
            for k in ("state", "success", "steps", "path_length"):
                assert np.array_equal(info["final_info"][f"_{k}"], fin)
    assert ended > n
    frames.close()
    envs.close()


def test_scalar_path_calls_a_subclass_step_override(world):
    """A reward subclass that overrides only the array ``step`` / ``reset`` (shaping of its own) is called through
    them on the scalar path too: its inherited ``step_one`` / ``reset_one`` would skip the override."""
    from dataclasses import dataclass

    from tsnav.sim.batch import SceneBank, SparseReward, scalar_method
    from tsnav.sim.gym_env import ObjectNavEnv
    from tsnav.tsrm.reward import TSRMReward

    @dataclass
    class Shaped(SparseReward):
        def step(self, prev_state, action, new_state, collided, done, success):
            r, t = super().step(prev_state, action, new_state, collided, done, success)
            return r + np.float32(1.0), {**t, "bonus": np.ones_like(r)}

    class CountedResets(TSRMReward):
        def reset(self, *args, **kwargs):
            self.resets = getattr(self, "resets", 0) + 1
            return super().reset(*args, **kwargs)

    assert scalar_method(SparseReward(), "step_one", "step") is not None
    assert scalar_method(Shaped(), "step_one", "step") is None and scalar_method(None, "step_one", "step") is None
    bank = SceneBank.from_root(world, None)
    counted = CountedResets(bank)
    assert scalar_method(counted, "reset_one", "reset") is None
    assert scalar_method(counted, "step_one", "step") is not None
    for reward_fn in (Shaped, lambda: CountedResets(bank)):
        envs = [ObjectNavEnv(bank=bank, reward_fn=reward_fn(), stepping=m, max_steps=6) for m in ("scalar", "batch")]
        for env in envs:
            env.reset(seed=1)
        rng = np.random.default_rng(0)
        for _ in range(40):
            a = int(rng.integers(0, 6))
            (o1, r1, t1, u1, i1), (o2, r2, t2, u2, i2) = (env.step(a) for env in envs)
            assert (r1, t1, u1) == (r2, t2, u2)
            _same_info(i1, i2)
            if t1 or u1:
                for env in envs:
                    env.reset()
        if isinstance(envs[0].batch.reward_fn, Shaped):
            assert "reward/bonus" in i1 and r1 > 0.9
        else:
            assert envs[0].batch.reward_fn.resets == envs[1].batch.reward_fn.resets > 1


def test_tsrm_step_one_equals_step_on_any_input(world):
    """``TSRMReward.step_one`` against ``step`` on inputs the env's random walks seldom give: a distance table with
    unreachable entries (``step_one`` writes ``distance_delta``'s rule out again), arbitrary jumps, collisions
    and stages, and success; rewards, terms (their signs too) and the reward's state."""
    from tsnav.sim.batch import SceneBank
    from tsnav.sim.paths import UNREACHABLE
    from tsnav.tsrm.reward import RewardConfig, TSRMReward

    bank = SceneBank.from_root(world, None)
    lo, hi = int(bank.offsets[0]), int(bank.offsets[1])
    target = int(np.flatnonzero(bank.present[0])[0])
    for variant in ("tsrm", "distance", "baseline"):
        fast, ref = (TSRMReward(bank, RewardConfig(variant=variant)) for _ in range(2))
        rng = np.random.default_rng(7)
        if fast.dist is not None:
            dist = fast.dist.copy()
            dist[rng.random(dist.shape) < 0.3] = UNREACHABLE
            fast.dist = ref.dist = dist
        fast.reset_one(0, target, lo, searching=True)
        ref.reset(np.ones(1, dtype=bool), np.array([0]), np.array([target]), np.array([lo]), searching=np.array([True]))
        unreachable = 0
        for _ in range(400):
            prev, new = (int(v) for v in rng.integers(lo, hi, 2))
            a, collided, success, searching = int(rng.integers(0, 6)), *(bool(v) for v in rng.random(3) < 0.3)
            r1, t1 = fast.step_one(prev, a, new, collided, False, success, searching=searching)
            r2, t2 = ref.step(
                np.array([prev]),
                np.array([a]),
                np.array([new]),
                np.array([collided]),
                np.array([False]),
                np.array([success]),
                searching=np.array([searching]),
            )
            assert type(r1) is float and r1 == float(r2[0]) and np.signbit(r1) == np.signbit(r2[0])
            assert list(t1) == list(t2) and all(
                t1[k] == float(t2[k][0]) and np.signbit(t1[k]) == np.signbit(t2[k][0]) for k in t1
            )
            if fast.dist is not None and not searching:
                unreachable += UNREACHABLE in (int(fast.dist[prev, target]), int(fast.dist[new, target]))
        for k in ("collided_at", "viewed"):
            assert np.array_equal(getattr(fast, k), getattr(ref, k)), k
        assert np.array_equal(fast.searched_area, ref.searched_area)
        assert fast.dist is None or unreachable > 20
