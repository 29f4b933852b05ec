"""Gymnasium env and vector env: check_env, registration, seeding, observations from HDF5, auto-reset."""

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import tsnav.sim  # noqa: F401  (registers the env id)
from sim_helpers import toy_scenes, write_scene_folder
from tsnav.constants import DONE, ROTATE_LEFT
from tsnav.sim.batch import SceneBank
from tsnav.sim.gym_env import ENV_ID, ObjectNavEnv, ObjectNavVectorEnv


@pytest.fixture(scope="module")
def bank():
    return SceneBank(toy_scenes(), cache=False)


def test_check_env_passes(bank):
    env = ObjectNavEnv(bank=bank, max_steps=20)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the checker's warnings are failures too
        check_env(env, skip_render_check=True)
    check_env(ObjectNavEnv(), skip_render_check=True)  # default toy room


def test_registered_and_seeded(bank):
    env = gym.make(ENV_ID, bank=bank, max_steps=10)
    o1, i1 = env.reset(seed=11)
    o2, i2 = env.reset(seed=11)
    assert i1 == i2 and o1["target"] == o2["target"]
    assert env.observation_space.contains(o1)
    assert o1["rgb"].shape == (64, 64, 3) and not o1["rgb"].any() and not o1["detections"].any()
    seq = []
    for seed in (3, 3):
        env.reset(seed=seed)
        rs = [env.step(int(a))[:4] for a in np.random.default_rng(0).integers(0, 5, 10)]
        seq.append([(r, t, u) for _, r, t, u in rs])
    assert seq[0] == seq[1]


def test_truncation_and_termination_single(bank):
    env = ObjectNavEnv(bank=bank, max_steps=3)
    env.reset(seed=0, options={"episode": ("ToyB", "GarbageCan", "0.00|0.00|225|0")})
    _, r, term, trunc, info = env.step(DONE)
    assert term and not trunc and info["success"] and r == pytest.approx(4.99)
    env.reset(options={"episode": ("ToyB", "Sink", "0.00|0.00|0|0")})
    flags = [env.step(ROTATE_LEFT)[2:4] for _ in range(3)]
    assert flags == [(False, False), (False, False), (False, True)]
    with pytest.raises(ValueError):
        env.step(7)


@pytest.mark.parametrize("frames,layout", [("memory", "standard"), ("hdf5", "standard"), ("memory", "legacy")])
def test_observations_from_hdf5(tmp_path, frames, layout):
    root = tmp_path / "data"
    write_scene_folder(toy_scenes()[2], root / "ToyC", images=8)  # the smallest scene: HDF5 writes are slow
    with pytest.raises(ValueError, match="name the detection table"):
        gym.make(ENV_ID, data=str(root), split="test")  # no silent fallback to ground truth
    env = gym.make(ENV_ID, bank=SceneBank.from_root(root, "test"), frames=frames, obs_layout=layout)
    obs, info = env.reset(seed=1)
    s = int(env.unwrapped.bank.local_state(info["state"]))  # the pattern follows the scene-local index
    assert obs["rgb"].shape == (8, 8, 3) and (obs["rgb"] == s % 251).all()
    assert obs["depth"].shape == ((8, 8, 1) if layout == "standard" else (8, 8))
    assert obs["depth"].dtype == np.float32 and (obs["depth"] == 0.5 + s % 7).all()
    b = env.unwrapped.bank
    det = np.zeros((b.num_states, 22, 6), np.float32)
    det[:, :, 0] = np.arange(b.num_states)[:, None]
    det[:, :, 1] = np.arange(22)[None, :]
    b.set_detections(det)
    obs, _, _, _, info = env.step(0)
    assert env.observation_space.contains(obs)
    rows = obs["detections"].reshape(22, 6)  # standard: the (22, 6) table flattened row by row
    assert (rows[:, 0] == info["state"]).all() and (rows[:, 1] == np.arange(22)).all()
    env.close()


def test_standard_layout_is_images_and_vectors(bank):
    """Every Box of the standard layout is an image (H, W, C) or a 1-D vector (what Stable-Baselines3's and
    RLlib's default encoders accept); rgb is the uint8 [0, 255] image their CNNs expect."""
    space = ObjectNavEnv(bank=bank).observation_space
    for key, sub in space.spaces.items():
        if isinstance(sub, gym.spaces.Box):
            assert len(sub.shape) in (1, 3), key
    rgb = space["rgb"]
    assert rgb.dtype == np.uint8 and (rgb.low == 0).all() and (rgb.high == 255).all() and rgb.shape[-1] == 3
    assert space["depth"].shape[-1] == 1 and space["detections"].shape == (22 * 6,)
    with pytest.raises(ValueError, match="obs_layout"):
        ObjectNavEnv(bank=bank, obs_layout="channels-first")
    with pytest.raises(ValueError, match="frames source"):
        ObjectNavEnv(bank=bank, frames="disk")


def test_vector_env(bank):
    envs = gym.make_vec(ENV_ID, num_envs=8, bank=bank, max_steps=6)
    assert isinstance(envs.unwrapped, ObjectNavVectorEnv)
    assert envs.num_envs == 8 and envs.single_action_space == gym.spaces.Discrete(6)
    assert envs.single_observation_space["target"] == gym.spaces.Discrete(22)
    obs, info = envs.reset(seed=5)
    assert envs.observation_space.contains(obs)
    obs_again, _ = envs.reset(seed=5)
    assert np.array_equal(obs["target"], obs_again["target"])
    envs.action_space.seed(0)
    ended = 0
    for _ in range(30):
        prev_target = obs["target"].copy()
        obs, r, term, trunc, info = envs.step(envs.action_space.sample())
        assert envs.observation_space.contains(obs)
        assert not (term & trunc).any()
        assert (info["steps"][trunc] == 6).all() and (info["steps"] <= 6).all()
        fin = term | trunc
        ended += fin.sum()
        if fin.any():
            assert np.array_equal(info["_final_obs"], fin)
            for j in np.flatnonzero(fin):
                assert info["final_obs"][j]["target"] == prev_target[j]
            assert (info["final_info"]["success"] <= term).all()
    assert ended > 8
    envs.close()


def _reference(env):
    from tsnav.sim.gym_env import Observations

    return Observations(env.unwrapped.bank, frames="hdf5")


def test_frame_cache_equals_reference_reader(tiny_world, tmp_path):
    """The in-memory frame cache gathers exactly what the per-key HDF5 reader reads, for rendered frames
    stored gzip-compressed (the writers' default) and raw (worlds written before compression), in any order
    and with repeats; scenes are read on first use only."""
    from tsnav.sim.gym_env import Observations
    from sim_helpers import write_scene_folder

    raw = tmp_path / "raw"
    write_scene_folder(toy_scenes()[2], raw / "ToyC", images=8)  # raw float32 depth, as old or imported worlds
    for bank, layout in (
        (SceneBank.from_root(tiny_world, None), "standard"),
        (SceneBank.from_root(tiny_world, None), "legacy"),
        (SceneBank.from_root(raw, None), "standard"),
    ):
        fast, ref = Observations(bank, frames="memory", layout=layout), Observations(bank, frames="hdf5", layout=layout)
        assert not fast.cache.loaded.any()
        rng = np.random.default_rng(0)
        for n in (1, 64, 300):
            state = rng.integers(0, bank.num_states, n)
            state[-1] = state[0]
            target = rng.integers(0, 22, n)
            a, b = fast.gather(state, target), ref.gather(state, target)
            for k in a:
                assert a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k]), k
        assert fast.cache.loaded.all() and fast.cache.rgb.any()
        ref.close()


def test_gymnasium_numpy_loop_sees_the_stored_frames(tiny_world):
    """A user's loop that imports only gymnasium and numpy (the id's ``tsnav.sim:`` prefix imports the env)
    steps the vector env and the single env; every observation equals the frames the reference reader
    takes from the HDF5 files for the state in ``info``, final observations of ended episodes included."""
    import subprocess
    import sys

    from tsnav.pipeline.steps import ensure_oracle_detections

    ensure_oracle_detections(tiny_world, "oracle")
    code = (
        "import gymnasium as gym, numpy as np\n"
        f"envs = gym.make_vec('tsnav.sim:tsnav/ObjectNav-v1', num_envs=16, vectorization_mode='vector_entry_point', "
        f"data={str(tiny_world)!r}, split=None, detections='oracle', max_steps=8)\n"
        "obs, info = envs.reset(seed=0)\n"
        "for _ in range(20):\n"
        "    obs, r, term, trunc, info = envs.step(np.random.default_rng(0).integers(0, 6, 16))\n"
        "print(obs['rgb'].shape, obs['depth'].shape, obs['detections'].shape, float(obs['rgb'].mean()))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split("\n")
    assert out[0].startswith("(16, 64, 64, 3) (16, 64, 64, 1) (16, 132)") and float(out[0].split()[-1]) > 0
    # the same loop in this process, checked frame by frame against the reference reader
    envs = gym.make_vec(
        "tsnav.sim:" + ENV_ID,
        num_envs=16,
        vectorization_mode="vector_entry_point",
        data=str(tiny_world),
        split=None,
        detections="oracle",
        max_steps=8,
    )
    ref = _reference(envs)
    obs, info = envs.reset(seed=0)
    rng = np.random.default_rng(0)
    ended = 0
    for _ in range(20):
        obs, r, term, trunc, info = envs.step(rng.integers(0, 6, 16))
        rgb, depth = ref.read_frames(info["state"])
        assert np.array_equal(obs["rgb"], rgb) and np.array_equal(obs["depth"][..., 0], depth)
        for j in np.flatnonzero(term | trunc):
            ended += 1
            rgb, depth = ref.read_frames([info["final_info"]["state"][j]])
            assert np.array_equal(info["final_obs"][j]["rgb"], rgb[0])
            assert np.array_equal(info["final_obs"][j]["depth"][..., 0], depth[0])
    assert ended > 0
    env = gym.make("tsnav.sim:" + ENV_ID, data=str(tiny_world), split=None, detections="oracle")
    obs, info = env.reset(seed=3)
    for a in rng.integers(0, 5, 30):
        rgb, depth = ref.read_frames([info["state"]])
        assert np.array_equal(obs["rgb"], rgb[0]) and np.array_equal(obs["depth"][..., 0], depth[0])
        obs, r, term, trunc, info = env.step(int(a))
        if term or trunc:
            obs, info = env.reset()
    ref.close()


def test_v0_keeps_the_first_layout_and_v1_is_today_s():
    """Both ids are registered (ENV_ID defined once, in tsnav.sim): v1 the standard observation layout, v0 the first
    release's (depth (H, W), detections (22, 6)), single and vector env alike."""
    import tsnav.sim as sim

    assert ENV_ID == sim.ENV_ID == "tsnav/ObjectNav-v1" and sim.ENV_ID_V0 == "tsnav/ObjectNav-v0"
    v1, v0 = gym.make(ENV_ID), gym.make(sim.ENV_ID_V0)
    h = v1.observation_space["rgb"].shape[0]
    assert v1.observation_space["depth"].shape == (h, h, 1) and v1.observation_space["detections"].shape == (132,)
    assert v0.observation_space["depth"].shape == (h, h) and v0.observation_space["detections"].shape == (22, 6)
    obs, _ = v0.reset(seed=0)
    assert obs["depth"].shape == (h, h) and obs["detections"].shape == (22, 6)
    vec = gym.make_vec("tsnav.sim:" + sim.ENV_ID_V0, num_envs=2, vectorization_mode="vector_entry_point")
    assert vec.single_observation_space["detections"].shape == (22, 6)
