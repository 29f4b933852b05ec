"""Gymnasium interface: the single env ``tsnav/ObjectNav-v1`` and its native vector env over
:class:`~tsnav.sim.batch.BatchEnv` (paper III-A).

    import gymnasium as gym
    env = gym.make("tsnav.sim:tsnav/ObjectNav-v1", data="out/world", split="train", reward="tsrm",
                   detections="oracle")
    envs = gym.make_vec("tsnav.sim:tsnav/ObjectNav-v1", num_envs=64, vectorization_mode="vector_entry_point",
                        data="out/world", split="train", detections="oracle")
    obs, info = envs.reset(seed=0)   # obs["rgb"] (64, H, W, 3) uint8, obs["depth"] (64, H, W, 1), ...

The registered id builds these classes through :mod:`tsnav.tsrm.envs`, which adds the paper's reward
(``reward="tsrm" | "baseline" | "explore" | "distance" | "sparse"``, default ``"tsrm"``), the detector's
tables (``detections=NAME``) and ``c_target``. Constructed directly, the classes take any ``reward_fn``
(default: the sparse reward). Without ``data`` / ``scenes`` / ``bank`` the env runs on the analytic toy room
of ``tsnav.data.toy``.

| | |
| --- | --- |
| Action space | ``Discrete(6)``: 0 MoveAhead, 1 RotateLeft, 2 RotateRight, 3 LookUp, 4 LookDown, 5 Done (the lineage's order) |
| Observation (``obs_layout="standard"``, default) | ``Dict`` of images ``(H, W, C)`` and 1-D vectors only, what Stable-Baselines3's ``MultiInputPolicy``, RLlib and CleanRL-style encoders take unwrapped: ``rgb`` ``Box(0, 255, (H, W, 3), uint8)`` from ``images.hdf5`` (zeros when absent); ``depth`` ``Box(0, 1000, (H, W, 1))`` metres from ``depth.hdf5`` in the dtype the files store (float16 for the worlds of this project, float32 otherwise; zeros when absent); ``target`` ``Discrete(22)`` category id; ``detections`` ``Box(-1, 10000, (132,), float32)``: the 22 per-class rows (score, label, x0, y0, x1, y1) of the detector stage flattened row by row (``reshape(22, 6)`` restores them; zeros when absent) |
| Observation (``obs_layout="legacy"``) | the first release's: ``depth`` ``(H, W)`` float32, ``detections`` ``(22, 6)`` float32, ``rgb`` and ``target`` as above |
| Frames (``frames=``) | ``"memory"`` (default): each scene's frames are read once, on the first visit to one of its states, into two arrays indexed by state (:class:`FrameCache`; ``H * W * 5`` bytes a state with float16 depth: 80 KiB at 128 px, 20 KiB at 64 px; the 80 training rooms of ``ithor-real`` at 128 px hold 266 k states, 21.8 GB once all are visited); ``"hdf5"``: one HDF5 dataset read per state and frame, no cache (the slow reference, for little memory) |
| Stepping (``stepping=``, single env) | ``"scalar"`` (default): the batch of one is stepped in Python scalars (:meth:`BatchEnv.step_one <tsnav.sim.batch.BatchEnv.step_one>`, the reward's ``step_one``) and its observation read with :meth:`Observations.one`, since numpy costs about a microsecond per operation on ``(1,)`` arrays; ``"batch"``: through the ``(1,)`` arrays of :meth:`BatchEnv.step <tsnav.sim.batch.BatchEnv.step>` (the reference; the same observations, rewards and ``info`` bit for bit, ``tests/sim/test_gym_fast.py``) |
| Reward | a :class:`~tsnav.sim.batch.RewardFn`: through the registered id the paper's TSRM reward by default (:mod:`tsnav.tsrm.envs`); the classes alone default to :class:`~tsnav.sim.batch.SparseReward` (-0.01 per step, +5 on success) |
| Start | a random training episode (scene, a reachable target present in it, a start state at horizon 0 or 30 that is not a success state), or ``reset(options={"episode": (scene_name, target_name, start_key)})`` |
| Termination | the agent outputs Done (success when the target is in view within the success distance) |
| Truncation | ``max_steps`` actions without Done (paper: 100 at test time; the lineage trains with 30) |

``info`` carries ``state`` (global id), ``scene``, ``collided`` (a failed MoveAhead), ``failed`` (any failed
action, looks past the horizon limits included), ``success``, ``steps``, ``path_length`` and each reward term
of the step as ``reward/<term>``. The vector env auto-resets in the same step (``AutoresetMode.SAME_STEP``): the returned
observation of a finished sub-env is its next episode's first one, and ``info["final_obs"]`` /
``info["final_info"]`` hold the last ones, as Gymnasium's ``SyncVectorEnv`` does in that mode. Every array of
an observation or ``info`` is new at every step (none is a view of the env's own state or of the frame cache),
so a learner may keep them.

Version History

* v1: the ``standard`` observation layout (``depth`` ``(H, W, 1)`` in the stored dtype, ``detections`` ``(132,)``),
  what Stable-Baselines3, RLlib and CleanRL-style code take unwrapped (commit 33bb8c6, issue 26); frames from an
  in-memory cache; the single env stepped in Python scalars (the same observations, rewards and ``info``).
* v0: the first release (commit c07dbf9): ``depth`` ``(H, W)`` float32, ``detections`` ``(22, 6)``; still
  registered, as the same env with ``obs_layout="legacy"``. The id did not change when the layout did (between
  33bb8c6 and v1's registration, ``v0`` gave the standard layout).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import h5py
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from ..constants import C_TARGET, NUM_ACTIONS, NUM_CATEGORIES, SUCCESS_DISTANCE
from ..data.toy import toy_scene
from ..data.reader import read_stack
from . import ENV_ID, ENV_ID_V0  # noqa: F401 (the ids, defined once in the package)
from .batch import BatchEnv, RewardFn, SceneBank, SparseReward
from .episodes import EpisodeConfig, TrainingSampler


DEFAULT_IMAGE_SIZE = 64
#: Bounds of the Box spaces (finite, as Gymnasium's checker asks): depth in metres; detection rows hold a
#: score in [0, 1], a label in [0, 22) and pixel coordinates (-1 for padding).
MAX_DEPTH = 1000.0
MAX_PIXEL = 10000.0


def make_bank(
    bank: SceneBank | None = None,
    scenes=None,
    data: str | None = None,
    split: str | None = "train",
    success_distance: float = SUCCESS_DISTANCE,
    c_target: float = C_TARGET,
    protocol: str = "paper",
) -> SceneBank:
    """The env's bank: ``bank`` itself, else one over ``scenes``, else the scenes of ``split`` under ``data``,
    else the analytic toy room (success under ``protocol``, :mod:`tsnav.protocol`)."""
    if bank is not None:
        return bank
    kw = dict(success_distance=success_distance, c_target=c_target, protocol=protocol)
    if scenes is not None:
        return SceneBank(list(scenes), **kw)
    if data is not None:
        return SceneBank.from_root(data, split, **kw)
    return SceneBank([toy_scene()], **kw)


#: Where the env reads frames from: ``"memory"`` (default) keeps every scene's frames in two contiguous arrays
#: indexed by global state id, filled from the HDF5 files one scene at a time on first use, and gathers a batch
#: with one fancy index per array; ``"hdf5"`` reads one HDF5 dataset per state and frame (the original path,
#: kept as the slow reference: no memory beyond the open files).
FRAME_SOURCES = ("memory", "hdf5")
#: Observation layouts: ``"standard"`` (default) has only images ``(H, W, C)`` and 1-D vectors, what
#: Stable-Baselines3, RLlib and CleanRL-style code build a policy from unwrapped; ``"legacy"`` is the layout
#: of the first release (``depth`` ``(H, W)``, ``detections`` ``(22, 6)``).
OBS_LAYOUTS = ("standard", "legacy")
#: How the single env steps its batch of one: ``"scalar"`` (default) in Python scalars
#: (:meth:`BatchEnv.step_one <tsnav.sim.batch.BatchEnv.step_one>`, :meth:`Observations.one`); ``"batch"``
#: through the ``(1,)`` arrays of :meth:`BatchEnv.step <tsnav.sim.batch.BatchEnv.step>` and
#: :meth:`Observations.gather`, the reference (bit-identical, ``tests/sim/test_gym_fast.py``).
STEPPINGS = ("scalar", "batch")


def observation_space(
    height: int, width: int, layout: str = "standard", depth_dtype=np.float32, num_categories: int = NUM_CATEGORIES
) -> spaces.Dict:
    """The env's single observation space for frames of ``height`` x ``width`` in ``layout``
    (:data:`OBS_LAYOUTS`; the module docstring's table); ``depth_dtype`` applies to the standard layout
    (the legacy one is always float32); ``num_categories`` is the bank's class set's size (22 for ``ithor22``)."""
    if layout not in OBS_LAYOUTS:
        raise ValueError(f"unknown obs_layout {layout!r} (choose from {', '.join(OBS_LAYOUTS)})")
    depth = (height, width, 1) if layout == "standard" else (height, width)
    det = (num_categories * 6,) if layout == "standard" else (num_categories, 6)
    return spaces.Dict(
        {
            "rgb": spaces.Box(0, 255, (height, width, 3), np.uint8),
            "depth": spaces.Box(0.0, MAX_DEPTH, depth, np.dtype(depth_dtype) if layout == "standard" else np.float32),
            "target": spaces.Discrete(num_categories),
            "detections": spaces.Box(-1.0, MAX_PIXEL, det, np.float32),
        }
    )


def _first_dataset(f) -> Any:
    first = next(iter(f.keys()), None)
    return None if first is None else f[first]


def stored_depth_dtype(bank: SceneBank) -> np.dtype:
    """float16 when every ``depth.hdf5`` of the bank stores float16 (the worlds of this project), else float32
    (any other dtype, e.g. an imported lineage world, keeps full precision); float16 when no scene has depth."""
    for s in bank.scenes:
        p = s.depth_path()
        if p is not None:
            with h5py.File(p, "r") as f:
                d = _first_dataset(f)
                if d is not None and np.dtype(d.dtype) != np.float16:
                    return np.dtype(np.float32)
    return np.dtype(np.float16)


class FrameCache:
    """Every state's frame of a bank in two contiguous arrays indexed by global state id: ``rgb``
    ``(S, H, W, 3)`` uint8 and ``depth`` ``(S, H, W)`` in the dtype the files store (float16 for the worlds
    of this project, so the cache costs ``H * W * 5`` bytes a state: 80 KiB at 128 px).

    The arrays are allocated zeroed and untouched (the kernel commits a page only when it is written), and a
    scene's frames are read from its ``images.hdf5`` / ``depth.hdf5`` on the first gather that visits one
    of its states, so a bank's memory grows with the scenes actually visited; a scene without files stays
    zeros, as the reference path reads it. Compressed files (gzip / lzf / shuffle) are decompressed once, at
    that first read. :meth:`load` reads scenes up front (e.g. before timing).
    """

    def __init__(self, bank: SceneBank, height: int, width: int, depth_dtype=None):
        self.bank, self.height, self.width = bank, int(height), int(width)
        depth_dtype = stored_depth_dtype(bank) if depth_dtype is None else np.dtype(depth_dtype)
        self.rgb = np.zeros((bank.num_states, self.height, self.width, 3), np.uint8)
        self.depth = np.zeros((bank.num_states, self.height, self.width), depth_dtype)
        self.loaded = np.zeros(bank.num_scenes, dtype=bool)

    @property
    def nbytes(self) -> int:
        """Bytes the cache takes once every scene is loaded."""
        return self.rgb.nbytes + self.depth.nbytes

    def load(self, scenes=None) -> None:
        """Read the frames of ``scenes`` (indices; default every scene) that are not loaded yet."""
        for i in range(self.bank.num_scenes) if scenes is None else scenes:
            if not self.loaded[i]:
                self._load_scene(int(i))

    def _load_scene(self, i: int) -> None:
        scene = self.bank.scenes[i]
        off = int(self.bank.offsets[i])
        for path, out, shape in (
            (scene.images_path(), self.rgb, (self.height, self.width, 3)),
            (scene.depth_path(), self.depth, (self.height, self.width)),
        ):
            if path is None:
                continue
            with h5py.File(path, "r") as f:
                try:
                    frames = read_stack(f, scene.keys)
                except KeyError as e:
                    raise ValueError(f"{path}: no frame for a state of the scene ({e.args[0]})") from None
                if frames.shape[1:] != shape:
                    raise ValueError(f"{path}: frames of shape {frames.shape[1:]}, the env's frames are {shape}")
                out[off : off + len(frames)] = frames
        self.loaded[i] = True

    def gather(self, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``rgb`` ``(B, H, W, 3)`` uint8 and ``depth`` ``(B, H, W)`` (the cache's dtype) of global ``state``
        ids (new arrays)."""
        need = self.bank.scene_of[state]
        if not self.loaded[need].all():
            self.load(np.unique(need[~self.loaded[need]]))
        return self.rgb[state], self.depth[state]


class Observations:
    """Gathers the Dict observation for global state ids: frames from a :class:`FrameCache`
    (``frames="memory"``) or read per state key from each scene's ``images.hdf5`` / ``depth.hdf5``
    (``frames="hdf5"``, the reference; datasets named by state key, the lineage layout), detections from
    ``bank.detections``; laid out as ``layout`` (:data:`OBS_LAYOUTS`). HDF5 files are opened on first use and
    kept open."""

    def __init__(
        self, bank: SceneBank, image_size: int | None = None, frames: str = "memory", layout: str = "standard"
    ):
        if frames not in FRAME_SOURCES:
            raise ValueError(f"unknown frames source {frames!r} (choose from {', '.join(FRAME_SOURCES)})")
        self.bank, self.frames, self.layout = bank, frames, layout
        self._files: dict[tuple[int, str], Any] = {}
        self.height = self.width = None
        for i, s in enumerate(bank.scenes):
            if s.images_path() is not None:
                first = _first_dataset(self._file(i, "images"))
                if first is not None:
                    self.height, self.width = first.shape[:2]
                    break
        if self.height is None:
            side = image_size or max([s.image_size for s in bank.scenes] + [0]) or DEFAULT_IMAGE_SIZE
            self.height = self.width = int(side)
        # the standard layout hands depth over as stored: a float16 -> float32 conversion would cost more
        # than the whole gather (BENCHMARKS.md); the legacy layout converts to float32 as it always did
        self.depth_dtype = stored_depth_dtype(bank) if layout == "standard" else np.dtype(np.float32)
        self.space = observation_space(self.height, self.width, layout, self.depth_dtype, self.bank.num_categories)
        self.cache = FrameCache(bank, self.height, self.width) if frames == "memory" else None
        if self.cache is not None:
            self.close()  # the cache opens each file itself, once

    def _file(self, scene: int, kind: str):
        key = (scene, kind)
        if key not in self._files:
            s = self.bank.scenes[scene]
            p = s.images_path() if kind == "images" else s.depth_path()
            if p is None:
                self._files[key] = None
            else:
                self._files[key] = h5py.File(p, "r")
        return self._files[key]

    def read_frames(self, state: np.ndarray, depth_dtype=np.float32) -> tuple[np.ndarray, np.ndarray]:
        """Reference frame reader: ``rgb`` ``(B, H, W, 3)`` uint8 and ``depth`` ``(B, H, W)`` (``depth_dtype``) of
        global ``state`` ids, one HDF5 dataset read per state and kind (zeros where a scene has no file)."""
        state = np.asarray(state, dtype=np.int64)
        n = len(state)
        rgb = np.zeros((n, self.height, self.width, 3), dtype=np.uint8)
        depth = np.zeros((n, self.height, self.width), dtype=depth_dtype)
        scene = self.bank.scene_of[state]
        for kind, out in (("images", rgb), ("depth", depth)):
            for j in range(n):
                f = self._file(int(scene[j]), kind)
                if f is not None:
                    out[j] = f[str(self.bank.keys[state[j]])][()]
        return rgb, depth

    def gather(self, state: np.ndarray, target: np.ndarray) -> dict[str, np.ndarray]:
        """Batched observation in the env's layout: ``{"rgb": (B,H,W,3), "depth": (B,H,W,1), "target": (B,),
        "detections": (B,132)}`` (``"legacy"``: ``depth`` ``(B,H,W)`` float32, ``detections`` ``(B,22,6)``);
        every array new (``target`` a copy, so the env's own arrays never leak into an observation)."""
        state = np.asarray(state, dtype=np.int64)
        n = len(state)
        rgb, depth = self.cache.gather(state) if self.cache is not None else self.read_frames(state, self.depth_dtype)
        if depth.dtype != self.depth_dtype:
            depth = depth.astype(self.depth_dtype)
        det = (
            self.bank.detections[state]
            if self.bank.detections is not None
            else np.zeros((n, self.bank.num_categories, 6), dtype=np.float32)
        )
        if self.layout == "standard":
            depth, det = depth[..., None], det.reshape(n, self.bank.num_categories * 6)
        return {
            "rgb": rgb,
            "depth": depth,
            "target": np.array(target, dtype=np.int64),
            "detections": np.ascontiguousarray(det, dtype=np.float32),
        }

    def one(self, state: int, target: int) -> dict[str, Any]:
        """One env's observation of global ``state`` with ``target``: ``single(gather([state], [target]), 0)``
        in its values, dtypes and shapes (new arrays), read from the frame cache without the batch's index
        arrays; ``frames="hdf5"`` reads through :meth:`gather`, the reference."""
        cache = self.cache
        if cache is None:
            return self.single(self.gather(np.array([state]), np.array([target])), 0)
        if not cache.loaded[self.bank.scene_of[state]]:
            cache.load([self.bank.scene_of[state]])
        rgb = cache.rgb[state].copy()
        depth = cache.depth[state]
        depth = depth.copy() if depth.dtype == self.depth_dtype else depth.astype(self.depth_dtype)
        det = self.bank.detections
        det = (
            np.zeros((self.bank.num_categories, 6), dtype=np.float32) if det is None else det[state].astype(np.float32)
        )  # a new array (the bank's table is float32)
        if self.layout == "standard":
            depth, det = depth[..., None], det.reshape(self.bank.num_categories * 6)
        return {"rgb": rgb, "depth": depth, "target": int(target), "detections": det}

    def single(self, obs: dict[str, np.ndarray], j: int) -> dict[str, Any]:
        """Row ``j`` of a batched observation as one env's observation."""
        return {
            "rgb": obs["rgb"][j],
            "depth": obs["depth"][j],
            "target": int(obs["target"][j]),
            "detections": obs["detections"][j],
        }

    def close(self) -> None:
        for f in self._files.values():
            if f is not None:
                f.close()
        self._files.clear()


#: ``info`` keys of the vector env and their Gymnasium ``"_key"`` masks.
_MASK = {k: f"_{k}" for k in ("state", "scene", "collided", "failed", "success", "steps", "path_length")}


def _episode_option(bank: SceneBank, ep) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    try:
        scene_name, target, start_key = ep
    except (TypeError, ValueError):
        raise ValueError("options['episode'] must be (scene_name, target_name, start_key)") from None
    i = bank.scene_index(scene_name)
    if target not in bank.class_set.index:
        raise ValueError(f"unknown target category {target!r} (class set {bank.class_set.name})")
    return np.array([i]), np.array([bank.class_set.index[target]]), np.array([bank.global_state(i, start_key)])


class ObjectNavEnv(gym.Env):
    """One object-navigation episode at a time (see the module docstring for the spaces and dynamics): a
    :class:`BatchEnv` of one, stepped in scalars (``stepping="scalar"``) or through its arrays (``"batch"``,
    the reference)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(
        self,
        data: str | None = None,
        split: str | None = "train",
        scenes=None,
        bank: SceneBank | None = None,
        max_steps: int = 100,
        reward_fn: RewardFn | None = None,
        success_distance: float = SUCCESS_DISTANCE,
        image_size: int | None = None,
        episode_config: EpisodeConfig | None = None,
        render_mode: str | None = None,
        frames: str = "memory",
        obs_layout: str = "standard",
        stepping: str = "scalar",
    ):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']}, got {render_mode!r}")
        if stepping not in STEPPINGS:
            raise ValueError(f"unknown stepping {stepping!r} (choose from {', '.join(STEPPINGS)})")
        self.render_mode = render_mode
        self.stepping = stepping
        self.bank = make_bank(bank, scenes, data, split, success_distance)
        self.sampler = TrainingSampler(self.bank, episode_config)
        self.batch = BatchEnv(
            self.bank,
            1,
            sampler=self.sampler,
            reward_fn=reward_fn or SparseReward(),
            max_steps=max_steps,
            autoreset=False,
        )
        self.obs_source = Observations(self.bank, image_size, frames=frames, layout=obs_layout)
        self.observation_space = self.obs_source.space
        self.action_space = spaces.Discrete(NUM_ACTIONS)
        self._last_obs: dict | None = None
        self._term_keys: dict[str, str] = {}

    def _obs(self) -> dict[str, Any]:
        if self.stepping == "scalar":
            obs = self.obs_source.one(int(self.batch.state[0]), int(self.batch.target[0]))
        else:
            obs = self.obs_source.single(self.obs_source.gather(self.batch.state, self.batch.target), 0)
        self._last_obs = obs
        return obs

    def _info(self) -> dict[str, Any]:
        s = int(self.batch.state[0])
        return {
            "state": s,
            "scene": self.bank.names[int(self.batch.scene[0])],
            "target_name": self.bank.class_set.categories[int(self.batch.target[0])],
            "optimal_length": int(self.bank.dist[s, int(self.batch.target[0])]),
        }

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.batch.np_random = self.np_random
        if options and "episode" in options:
            self.batch.reset(episodes=_episode_option(self.bank, options["episode"]))
        elif self.stepping == "scalar":
            self.batch.reset_one()
        else:
            self.batch.reset()
        return self._obs(), self._info()

    def step(self, action):
        if not (type(action) is int and 0 <= action < NUM_ACTIONS) and not self.action_space.contains(action):
            raise ValueError(f"action must be an int in [0, {NUM_ACTIONS}), got {action!r}")
        if self.stepping == "scalar":
            return self._step_scalar(int(action))
        _, reward, term, trunc, info = self.batch.step(np.array([int(action)]))
        out = {
            "state": int(info["final_state"][0]),
            "scene": self.bank.names[int(self.batch.scene[0])],
            "collided": bool(info["collided"][0]),
            "failed": bool(info["failed"][0]),
            "success": bool(info["success"][0]),
            "steps": int(info["steps"][0]),
            "path_length": int(info["path_length"][0]),
        }
        out.update({f"reward/{k}": float(v[0]) for k, v in info["reward_terms"].items()})
        return self._obs(), float(reward[0]), bool(term[0]), bool(trunc[0]), out

    def _step_scalar(self, action: int):
        """:meth:`step` through :meth:`BatchEnv.step_one <tsnav.sim.batch.BatchEnv.step_one>` and
        :meth:`Observations.one`: the same observation, reward, flags and ``info`` as ``stepping="batch"``."""
        reward, term, trunc, info = self.batch.step_one(action)
        out = {
            "state": info["final_state"],
            "scene": self.bank.names[self.batch.scene[0]],
            "collided": info["collided"],
            "failed": info["failed"],
            "success": info["success"],
            "steps": info["steps"],
            "path_length": info["path_length"],
        }
        keys = self._term_keys
        for k, v in info["reward_terms"].items():
            if k not in keys:
                keys[k] = f"reward/{k}"
            out[keys[k]] = v
        return self._obs(), reward, term, trunc, out

    def render(self):
        if self.render_mode == "rgb_array":
            return None if self._last_obs is None else self._last_obs["rgb"].copy()
        return None

    def close(self):
        self.obs_source.close()


class ObjectNavVectorEnv(VectorEnv):
    """``num_envs`` episodes stepped together by one :class:`BatchEnv` (same-step auto-reset)."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(
        self,
        num_envs: int = 1,
        data: str | None = None,
        split: str | None = "train",
        scenes=None,
        bank: SceneBank | None = None,
        max_steps: int = 100,
        reward_fn: RewardFn | None = None,
        success_distance: float = SUCCESS_DISTANCE,
        image_size: int | None = None,
        episode_config: EpisodeConfig | None = None,
        frames: str = "memory",
        obs_layout: str = "standard",
    ):
        self.bank = make_bank(bank, scenes, data, split, success_distance)
        self.num_envs = int(num_envs)
        self.sampler = TrainingSampler(self.bank, episode_config)
        self.batch = BatchEnv(
            self.bank,
            self.num_envs,
            sampler=self.sampler,
            reward_fn=reward_fn or SparseReward(),
            max_steps=max_steps,
            autoreset=True,
        )
        self.obs_source = Observations(self.bank, image_size, frames=frames, layout=obs_layout)
        self.single_observation_space = self.obs_source.space
        self.single_action_space = spaces.Discrete(NUM_ACTIONS)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._term_keys: dict[str, tuple[str, str]] = {}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if self._np_random is None:
            self._np_random, self._np_random_seed = gym.utils.seeding.np_random(None)
        self.batch.np_random = self._np_random
        self.batch.reset()
        obs = self.obs_source.gather(self.batch.state, self.batch.target)
        return obs, {"state": self.batch.state.copy(), "scene": self.batch.scene.copy()}

    def step(self, actions):
        actions = np.asarray(actions)
        if actions.shape != (self.num_envs,) or not np.issubdtype(actions.dtype, np.integer):
            raise ValueError(f"actions must be {self.num_envs} ints, got {actions.dtype} {actions.shape}")
        target = self.batch.target.copy()  # auto-reset replaces the targets of finished rows
        _, reward, term, trunc, info = self.batch.step(actions)
        obs = self.obs_source.gather(self.batch.state, self.batch.target)
        every = np.ones(self.num_envs, dtype=bool)
        infos: dict[str, Any] = {
            "state": self.batch.state.copy(),
            "_state": every,
            "scene": self.batch.scene.copy(),
            "_scene": every,
        }
        for k in ("collided", "failed", "success", "steps", "path_length"):
            infos[k], infos[_MASK[k]] = info[k], every
        keys = self._term_keys
        for k, v in info["reward_terms"].items():
            if k not in keys:
                keys[k] = (f"reward/{k}", f"_reward/{k}")
            infos[keys[k][0]], infos[keys[k][1]] = v, every
        fin = term | trunc
        if fin.any():
            # Gymnasium's SAME_STEP convention: final_obs is an object array of single observations,
            # final_info a dict of arrays with "_key" masks.
            rows = np.flatnonzero(fin)
            last = self.obs_source.gather(info["final_state"][rows], target[rows])
            final_obs = np.full(self.num_envs, None, dtype=object)
            rgb, depth, det, tgt = last["rgb"], last["depth"], last["detections"], last["target"].tolist()
            for k, j in enumerate(rows.tolist()):  # Observations.single, row by row
                final_obs[j] = {"rgb": rgb[k], "depth": depth[k], "target": tgt[k], "detections": det[k]}
            final_info: dict[str, Any] = {}
            for k, v in (
                ("state", info["final_state"]),
                ("success", info["success"]),
                ("steps", info["steps"]),
                ("path_length", info["path_length"]),
            ):
                out = np.zeros_like(v)
                out[rows] = v[rows]
                final_info[k], final_info[_MASK[k]] = out, fin.copy()
            infos["final_obs"], infos["_final_obs"] = final_obs, fin.copy()
            infos["final_info"], infos["_final_info"] = final_info, fin.copy()
        return obs, reward.astype(np.float64), term, trunc, infos

    def close_extras(self, **kwargs):
        self.obs_source.close()
