"""Batched object-navigation simulator over offline scenes (paper III-A; DESIGN.md "The offline dataset").

Two pieces:

* :class:`SceneBank` concatenates several :class:`~tsnav.data.reader.Scene` objects into one global state
  space (scene ``i`` owns global ids ``offsets[i] .. offsets[i+1]-1``), so that a single ``next_state``
  array ``(total_S, 6)`` serves every scene, plus per-state, per-category tables (success masks, optimal
  distance fields, target-in-frame flags, detector confidences).
* :class:`BatchEnv` steps ``B`` episodes at once with array operations only.

Observations are global state ids and target category ids; callers gather features, detections or
images for those ids themselves.

Episode semantics (used by every stage of tsnav):

* ``steps`` counts every action output, Done included; the episode is *truncated* when ``steps`` reaches
  ``max_steps`` without a Done (paper: 100 at test time; the lineage trains with 30).
* Done always ends the episode (*terminated*); it is a *success* when the state is a success state of the
  target category under the bank's success protocol (:mod:`tsnav.protocol`; ``paper``: an instance in view
  and within ``success_distance``, 1.0 m; ``lineage``: listed in ``visible_object_map_1.5.json``).
* A movement action whose target equals the current state failed (AI2-THOR's ``lastActionSuccess`` is
  False): ``failed`` is set. Only a failed MoveAhead is a *collision* (``collided``): the lineage's offline
  controller (``OfflineControllerWithSmallRotation.step``) also fails LookUp at horizon 0 and LookDown at 30
  (horizons 0 and 30 only, so the graph has no such edge), and real AI2-THOR fails a look past the camera's
  limits, but neither moves the agent into anything; the paper's collision penalty (III-D (iii)) is about
  bumping into obstacles, and IOM's episode penalises a failed action only when it is a MoveAhead.
* ``path_length`` counts the movement actions (every non-Done action, failed ones included), the same
  quantity as the optimal length L* of :mod:`tsnav.sim.paths` (Done not counted).

Reward plug-in (stable interface; the TSRM reward of :mod:`tsnav.tsrm` implements it)::

    class RewardFn(Protocol):
        def reset(self, mask, scene_idx, target, start_state) -> None: ...
        def step(self, prev_state, action, new_state, collided, done, success)
            -> tuple[np.ndarray, dict[str, np.ndarray]]: ...

    # a reward that reads the stage also sets ``uses_stage = True`` and takes ``searching=`` in both

* ``reset`` is called by :meth:`BatchEnv.reset` (``mask`` all True) and after every auto-reset (``mask``
  marks the rows that start a new episode). All arguments are full ``(B,)`` arrays: ``mask`` bool,
  ``scene_idx`` int64 index into ``bank.scenes``, ``target`` int64 category id, ``start_state`` int64 global
  state id; only the rows where ``mask`` is True are new.
* ``step`` is called once per :meth:`BatchEnv.step`, *before* auto-reset, with ``(B,)`` arrays:
  ``prev_state`` / ``new_state`` int64 global ids, ``action`` int64, ``collided`` / ``done`` / ``success``
  bool (``done`` = terminated or truncated at this step). It returns the reward ``(B,)`` float32 and named
  terms ``{name: (B,) float32}`` (e.g. ``slack``, ``success``) that the env passes on in ``info``. Rows whose
  episode had already finished before this step (only without auto-reset) are passed with
  ``new_state == prev_state`` and ``done`` True; the env zeroes their reward and terms.
* Optionally, for a batch of one (the single Gymnasium env, :meth:`BatchEnv.step_one`), the same in Python
  scalars: ``reset_one(scene_idx, target, start_state)`` and ``step_one(prev_state, action, new_state,
  collided, done, success) -> (float, {name: float})``, the float32 values of ``step`` as Python floats (with
  ``searching=`` a bool where the reward uses the stage). A reward without them is called through ``step``
  with ``(1,)`` arrays, and so is one whose class overrides ``step`` (``reset``) below the class that defines
  ``step_one`` (``reset_one``), e.g. a subclass of :class:`SparseReward` that shapes ``step``: the inherited
  scalar method would skip the override (:func:`scalar_method`). The TSRM reward and :class:`SparseReward`
  have them; ``tests/sim/test_gym_fast.py`` holds them equal to ``reset`` / ``step``.
* A reward that follows the two stages (paper III-B) declares it with ``uses_stage = True`` (as habitat-lab's
  measures declare the measures they depend on); the env then passes the stage of its one
  :class:`~tsnav.sim.stage.StageSwitch` (:attr:`BatchEnv.stage`) as a keyword ``searching``, a ``(B,)`` bool
  array: in ``reset`` the stage of the start frames (the switch was reset first), in ``step`` the stage in
  which this step's action was chosen (the switch is updated after the reward). The env is the only owner of
  the switch: it resets and updates it; rewards only read the mask they are handed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Sequence, runtime_checkable

import numpy as np

from ..constants import C_TARGET, DONE, GRID_SIZE, MOVE_AHEAD, NUM_ACTIONS, SUCCESS_DISTANCE
from ..data.detections import Detections, load_scene_detections
from ..data.reader import Scene, list_scenes, load_scene
from ..protocol import DEFAULT_PROTOCOL, check_protocol
from .paths import distance_fields, scene_distance_fields
from .stage import StageSwitch, above_threshold


@runtime_checkable
class RewardFn(Protocol):
    """Pluggable reward of :class:`BatchEnv` (see the module docstring for the exact contract)."""

    def reset(self, mask: np.ndarray, scene_idx: np.ndarray, target: np.ndarray, start_state: np.ndarray) -> None: ...

    def step(
        self,
        prev_state: np.ndarray,
        action: np.ndarray,
        new_state: np.ndarray,
        collided: np.ndarray,
        done: np.ndarray,
        success: np.ndarray,
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]: ...


def scalar_method(fn, one: str, reference: str):
    """``fn``'s scalar method ``one`` (``"step_one"`` / ``"reset_one"``) when the class that defines it also
    defines its array ``reference`` (``"step"`` / ``"reset"``), else None: a subclass that overrides only the
    array method must be called through it, or its override would be skipped (the scalar path's fallback)."""

    def owner(name):
        return next((k for k in type(fn).__mro__ if name in vars(k)), None)

    found = owner(one)
    return getattr(fn, one) if found is not None and found is owner(reference) else None


@runtime_checkable
class EpisodeSampler(Protocol):
    """Draws new episodes for :class:`BatchEnv`: ``sample(n, rng) -> (scene_idx, target, start_state)``,
    three ``(n,)`` int64 arrays (scene index into the bank, category id, global start state id)."""

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


@dataclass
class SimConfig:
    """Simulator settings in one place (paper III-A, IV-A); :func:`tsnav.sim.episodes.make_env` builds a bank and env from it."""

    success_distance: float = SUCCESS_DISTANCE
    """Done succeeds with an instance of the target in view within this many metres (the ``paper``
    protocol's radius: 1.0)."""
    protocol: str = DEFAULT_PROTOCOL
    """Success protocol (:mod:`tsnav.protocol`): ``paper`` (in view within ``success_distance``) or
    ``lineage`` (the visibility map, as the lineage's evaluator reads it; ``success_distance`` unused)."""
    max_steps: int = 100
    """Actions per episode before truncation (paper: 100 at test time; the lineage trains with 30)."""
    autoreset: bool = True
    """Finished rows immediately start a new episode from the sampler (training); off for evaluation."""


@dataclass
class SparseReward:
    """The plain reward of the lineage without shaping (paper III-D (iv), (v)): ``slack`` every step,
    plus ``success`` when Done succeeds. Implements :class:`RewardFn`."""

    slack: float = -0.01
    """Reward added at every step (paper: -0.01)."""
    success: float = 5.0
    """Reward added when the episode succeeds (paper: +5)."""

    def reset(self, mask, scene_idx, target, start_state) -> None:
        return None

    def step(self, prev_state, action, new_state, collided, done, success):
        n = len(prev_state)
        slack = np.full(n, self.slack, dtype=np.float32)
        win = np.where(success, np.float32(self.success), np.float32(0.0)).astype(np.float32)
        return slack + win, {"slack": slack, "success": win}

    def reset_one(self, scene_idx: int, target: int, start_state: int) -> None:
        """:meth:`reset` of one episode (nothing to keep)."""
        return None

    def step_one(
        self, prev_state: int, action: int, new_state: int, collided: bool, done: bool, success: bool
    ) -> tuple[float, dict[str, float]]:
        """:meth:`step` of one episode in Python scalars (the float32 values of ``step``, as Python floats)."""
        slack = np.float32(self.slack)
        win = np.float32(self.success) if success else np.float32(0.0)
        return float(slack + win), {"slack": float(slack), "success": float(win)}


class SceneBank:
    """Several scenes as one global state space with per-state, per-category tables.

    Attributes (``N`` scenes, ``S`` = total states, ``C`` = the class set's target categories, 22 or 12):
        scenes: the :class:`Scene` objects; names, room_types: per scene.
        class_set: the :class:`~tsnav.constants.ClassSet` every scene declares (``ithor22`` or ``robothor12``;
            scenes of different class sets cannot share a bank); ``num_categories`` = ``C``.
        offsets: ``(N+1,)`` int64; scene ``i`` owns global ids ``offsets[i]:offsets[i+1]``.
        scene_of: ``(S,)`` int32 scene index of each global state.
        next_state: ``(S, 6)`` int32 global successor per action (the state itself when it fails / Done).
        keys, x, z, rotation, horizon: ``(S,)`` concatenated state descriptions (metres, degrees).
        position: ``(S,)`` int32 global position id (same scene and grid cell, any rotation / horizon).
        success: ``(S, C)`` bool, Done succeeds here for the category under ``protocol``
            (:meth:`~tsnav.data.reader.Scene.success_table`; ``paper``: III-A, within ``success_distance``).
        protocol: the success protocol (:mod:`tsnav.protocol`), ``paper`` by default.
        dist: ``(S, C)`` int32 optimal path length L* to the nearest success state (movement actions, Done
            not counted); :data:`~tsnav.sim.paths.UNREACHABLE` when none can be reached.
        in_frame: ``(S, C)`` bool, an instance of the category shows at least the scene's minimum number of
            pixels in the frame (ground-truth visibility, any distance).
        present: ``(N, C)`` bool, the category has an instance in the scene.
        confidence: ``(S, C)`` float32 detector confidence of each target category, or None (filled by the
            detector stage); :attr:`stage_confidence` falls back to ``in_frame`` as 1.0 / 0.0.
        detections: ``(S, C, 6)`` float32 rows (score, label, x0, y0, x1, y1) or None.
        c_target: the stage-switch threshold C_target (paper IV-A: 0.7); its one home below the user's
            configs (``TrainConfig.c_target``, ``EvalConfig.c_target``): :attr:`stage_mask`, the env's
            :class:`~tsnav.sim.stage.StageSwitch` and the searching lengths read it here.
    """

    def __init__(
        self,
        scenes: Sequence[Scene],
        success_distance: float = SUCCESS_DISTANCE,
        confidence: np.ndarray | None = None,
        detections: np.ndarray | None = None,
        c_target: float = C_TARGET,
        cache: bool = True,
        protocol: str = DEFAULT_PROTOCOL,
    ):
        if len(scenes) == 0:
            raise ValueError("SceneBank needs at least one scene")
        if not success_distance > 0:
            raise ValueError(f"success_distance must be positive, got {success_distance}")
        self.protocol = check_protocol(protocol)
        self.scenes = list(scenes)
        sets = sorted({s.class_set.name for s in self.scenes})
        if len(sets) > 1:
            raise ValueError(f"scenes of different class sets ({', '.join(sets)}) cannot share a bank")
        self.class_set = self.scenes[0].class_set
        self.num_categories = self.class_set.size
        self.success_distance = float(success_distance)
        if not 0.0 <= c_target <= 1.0:
            raise ValueError(f"c_target must be in [0, 1], got {c_target}")
        self.c_target = float(c_target)
        sizes = np.array([s.num_states for s in self.scenes], dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        total = int(self.offsets[-1])
        self.num_states = total
        self.names = [s.name for s in self.scenes]
        self.room_types = [s.room_type for s in self.scenes]
        self.scene_of = np.repeat(np.arange(len(self.scenes), dtype=np.int32), sizes)
        self.next_state = np.concatenate(
            [s.next_state.astype(np.int64) + o for s, o in zip(self.scenes, self.offsets[:-1])]
        ).astype(np.int32)
        self.keys = np.concatenate([s.keys for s in self.scenes])
        self.x = np.concatenate([s.x for s in self.scenes]).astype(np.float32)
        self.z = np.concatenate([s.z for s in self.scenes]).astype(np.float32)
        self.rotation = np.concatenate([s.rotation for s in self.scenes]).astype(np.int16)
        self.horizon = np.concatenate([s.horizon for s in self.scenes]).astype(np.int16)
        cells = np.stack(
            [
                self.scene_of.astype(np.int64),
                np.round(self.x / GRID_SIZE).astype(np.int64),
                np.round(self.z / GRID_SIZE).astype(np.int64),
            ],
            axis=1,
        )
        _, pos = np.unique(cells, axis=0, return_inverse=True)
        self.position = pos.reshape(-1).astype(np.int32)
        self.success = np.concatenate([s.success_table(self.protocol, success_distance) for s in self.scenes])
        self.dist = np.concatenate(
            [scene_distance_fields(s, success_distance, cache=cache, protocol=self.protocol) for s in self.scenes]
        )
        self.in_frame = np.concatenate([_in_frame(s) for s in self.scenes])
        self.present = np.zeros((len(self.scenes), self.num_categories), dtype=bool)
        for i, s in enumerate(self.scenes):
            self.present[i, s.categories_present()] = True
        self.confidence: np.ndarray | None = None
        self.detections: np.ndarray | None = None
        self._search_dist: np.ndarray | None = None
        if confidence is not None:
            self.set_confidence(confidence)
        if detections is not None:
            self.set_detections(detections)

    @classmethod
    def from_root(cls, root, split: str | None = None, **kwargs) -> "SceneBank":
        """Load every complete scene folder of a dataset root (optionally one split) into a bank."""
        paths = list_scenes(root, split)
        if not paths:
            raise ValueError(f"{root}: no complete scenes" + (f" in split {split!r}" if split else ""))
        return cls([load_scene(p) for p in paths], **kwargs)

    @property
    def num_scenes(self) -> int:
        return len(self.scenes)

    def set_confidence(self, confidence: np.ndarray) -> None:
        """Install the ``(S, C)`` detector confidences (values in [0, 1]); clears the searching-length cache."""
        conf = np.asarray(confidence, dtype=np.float32)
        if conf.shape != (self.num_states, self.num_categories):
            raise ValueError(f"confidence must have shape ({self.num_states}, {self.num_categories}), got {conf.shape}")
        self.confidence = conf
        self._search_dist = None

    def set_detections(self, detections: np.ndarray) -> None:
        """Install the ``(S, C, 6)`` per-class detection rows (score, label, x0, y0, x1, y1)."""
        det = np.asarray(detections, dtype=np.float32)
        if det.shape != (self.num_states, self.num_categories, 6):
            raise ValueError(
                f"detections must have shape ({self.num_states}, {self.num_categories}, 6), got {det.shape}"
            )
        self.detections = det

    def install_detections(self, name: str) -> Detections:
        """Load ``detections_<name>.hdf5`` of every scene in bank order and install it: its scores drive the
        stage switch (paper III-B), its rows become :attr:`detections`. Returns the concatenated table (its
        ``features`` are row-aligned with the bank's global state ids)."""
        det = load_scene_detections(self.scenes, name)
        self.set_confidence(det.scores)
        self.set_detections(det.rows())
        return det

    @property
    def stage_confidence(self) -> np.ndarray:
        """``(S, C)`` float32 target confidence used for the stage switch (paper III-B, "Dividing point"):
        the detector's when installed, else the ground-truth in-frame flag as 1.0 / 0.0."""
        if self.confidence is not None:
            return self.confidence
        return self.in_frame.astype(np.float32)

    @property
    def stage_mask(self) -> np.ndarray:
        """``(S, C)`` bool: the frame of this state switches the episode to the pathfinding stage
        (confidence > C_target)."""
        return above_threshold(self.stage_confidence, self.c_target)

    @property
    def search_dist(self) -> np.ndarray:
        """``(S, C)`` int32 optimal searching length L*^Search (paper IV-A, SSSPL): movement actions from each
        state to the nearest state whose frame switches to the pathfinding stage. Computed on first use."""
        if self._search_dist is None:
            self._search_dist = distance_fields(self.next_state, self.stage_mask)
        return self._search_dist

    def global_state(self, scene_idx: int, key: str) -> int:
        """Global state id of ``key`` in scene ``scene_idx``."""
        return int(self.offsets[scene_idx]) + self.scenes[scene_idx].index(key)

    def scene_index(self, name: str) -> int:
        """Index of the scene called ``name``; ``KeyError`` naming it when absent."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"scene {name!r} is not in this bank") from None

    def local_state(self, state: np.ndarray) -> np.ndarray:
        """Scene-local state ids of global ids."""
        state = np.asarray(state, dtype=np.int64)
        return state - self.offsets[self.scene_of[state]]


def _in_frame(scene: Scene) -> np.ndarray:
    """``(S, C)`` bool: an instance of the category is visible in the frame (pixels >= the scene's minimum)."""
    vis = scene.visible_at_any_range()
    out = np.zeros((scene.num_states, scene.num_categories), dtype=bool)
    tgt = scene.object_category >= 0
    if tgt.any():
        onehot = np.zeros((int(tgt.sum()), scene.num_categories), dtype=np.int32)
        onehot[np.arange(int(tgt.sum())), scene.object_category[tgt]] = 1
        out = (vis[:, tgt].astype(np.int32) @ onehot) > 0
    return out


class BatchEnv:
    """``num_envs`` object-navigation episodes stepped together (paper III-A).

    Observation (dict of ``(B,)`` arrays): ``state`` global state id (int64), ``target`` category id (int64),
    ``scene`` scene index (int64), ``step`` actions taken so far in the episode (int32).

    :meth:`step` returns ``(obs, reward, terminated, truncated, info)`` with ``info`` arrays (all ``(B,)``,
    describing the step just taken, before any auto-reset): ``collided`` (a failed MoveAhead), ``failed`` (any
    failed movement action, looks past the horizon limits included), ``success``, ``steps``,
    ``path_length``, ``final_state`` (the state reached), ``active`` (the row was in an episode),
    ``reward_terms`` (dict), and the two-stage state of the episode after this step (paper III-B):
    ``entered`` (in the pathfinding stage), ``switch_length`` (movement actions before the switching frame)
    and ``switch_state`` (the switching frame's state). The stage is kept by :attr:`stage`, a
    :class:`~tsnav.sim.stage.StageSwitch` (``stage`` when given, e.g. an evaluation's at its own C_target, else
    one over the bank's confidence and C_target) that only the env resets and updates; a reward with
    ``uses_stage`` is handed its ``searching`` mask (module docstring). With ``autoreset`` (default) finished
    rows immediately start a new episode from ``sampler`` and ``obs`` shows its first state ("same-step"
    auto-reset); without it finished rows stay frozen (``active`` False) until :meth:`reset`.

    :meth:`step_one` / :meth:`reset_one` are :meth:`step` / :meth:`reset` for ``num_envs`` = 1 in Python
    scalars (the single Gymnasium env), with the same outcome bit for bit.
    """

    def __init__(
        self,
        bank: SceneBank,
        num_envs: int,
        sampler: EpisodeSampler | None = None,
        reward_fn: RewardFn | None = None,
        max_steps: int = 100,
        autoreset: bool = True,
        seed: int | None = None,
        stage: StageSwitch | None = None,
    ):
        """``stage``: the stage switch to keep (e.g. an evaluation's at its own C_target); default: one over
        the bank's rule (``bank.stage_mask``)."""
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        self.bank = bank
        self.num_envs = int(num_envs)
        self.sampler = sampler
        self.reward_fn = reward_fn
        self.max_steps = int(max_steps)
        self.autoreset = bool(autoreset)
        self.np_random = np.random.default_rng(seed)
        b = self.num_envs
        self.state = np.zeros(b, dtype=np.int64)
        self.start = np.zeros(b, dtype=np.int64)
        self.target = np.zeros(b, dtype=np.int64)
        self.scene = np.zeros(b, dtype=np.int64)
        self.steps = np.zeros(b, dtype=np.int32)
        self.path_length = np.zeros(b, dtype=np.int32)
        self.active = np.zeros(b, dtype=bool)
        self._ns = bank.next_state.astype(np.int64).reshape(-1)  # flat (S*6,)
        self._succ = bank.success.reshape(-1)  # flat (S*C,)
        self._arange = np.arange(b, dtype=np.int64)
        self.stage: StageSwitch = stage or StageSwitch(bank, num_envs=b)
        self._reward_uses_stage = bool(getattr(reward_fn, "uses_stage", False))
        self._reward_reset_one = scalar_method(reward_fn, "reset_one", "reset")
        self._reward_step_one = scalar_method(reward_fn, "step_one", "step")

    # -- episodes -----------------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, episodes: tuple | None = None) -> dict[str, np.ndarray]:
        """Start a new episode in every row and return the observation.

        ``episodes`` = ``(scene_idx, target, start_state)`` (three ``(B,)`` arrays, global start ids) sets the
        episodes explicitly (evaluation); otherwise they are drawn from ``sampler``. ``seed`` reseeds
        :attr:`np_random`.
        """
        if seed is not None:
            self.np_random = np.random.default_rng(seed)
        mask = np.ones(self.num_envs, dtype=bool)
        self._start_rows(mask, episodes)
        return self._obs()

    def _start_rows(self, mask: np.ndarray, episodes: tuple | None = None) -> None:
        n = int(np.count_nonzero(mask))
        if episodes is None:
            if self.sampler is None:
                raise ValueError("BatchEnv has no episode sampler: pass episodes= to reset()")
            scene_idx, target, start = self.sampler.sample(n, self.np_random)
        else:
            scene_idx, target, start = (np.asarray(a, dtype=np.int64).reshape(-1) for a in episodes)
            if not len(scene_idx) == len(target) == len(start) == n:
                raise ValueError(f"episodes must be three arrays of length {n}")
            if n and (
                (start < 0).any()
                or (start >= self.bank.num_states).any()
                or (self.bank.scene_of[start] != scene_idx).any()
            ):
                raise ValueError("episode start states must be global state ids of their scenes")
            if n and ((target < 0).any() or (target >= self.bank.num_categories).any()):
                raise ValueError(f"episode targets must be category ids in [0, {self.bank.num_categories})")
        rows = np.flatnonzero(mask)
        self.scene[rows] = scene_idx
        self.target[rows] = target
        self.state[rows] = start
        self.start[rows] = start
        self.steps[rows] = 0
        self.path_length[rows] = 0
        self.active[rows] = True
        self.stage.reset(mask, self.state, self.target)
        if self.reward_fn is not None:
            kw = {"searching": self.stage.searching} if self._reward_uses_stage else {}
            self.reward_fn.reset(mask.copy(), self.scene.copy(), self.target.copy(), self.state.copy(), **kw)

    def _obs(self) -> dict[str, np.ndarray]:
        return {
            "state": self.state.copy(),
            "target": self.target.copy(),
            "scene": self.scene.copy(),
            "step": self.steps.copy(),
        }

    # -- stepping -----------------------------------------------------------------------------------------
    def step(self, actions) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray, dict]:
        """Apply one action per row (``(B,)`` ints in ``[0, 6)``, order of ``constants.ACTIONS``)."""
        a = np.asarray(actions)
        if a.shape != (self.num_envs,):
            raise ValueError(f"actions must have shape ({self.num_envs},), got {a.shape}")
        a = a.astype(np.int64, copy=False)
        if (a.view(np.uint64) >= NUM_ACTIONS).any():  # negative ids wrap to huge unsigned values
            raise ValueError(f"actions must be in [0, {NUM_ACTIONS})")
        active = self.active
        prev = self.state
        moved = self._ns[prev * NUM_ACTIONS + a]
        new = np.where(active, moved, prev)
        is_done = a == DONE
        moving = active & ~is_done
        failed = moving & (moved == prev)  # lastActionSuccess False
        # A collision is a failed MoveAhead only; a look past the horizon limits fails without bumping into
        # anything (module docstring), so the collision penalty of III-D (iii) does not apply to it.
        collided = failed & (a == MOVE_AHEAD)
        self.steps += active
        self.path_length += moving
        terminated = active & is_done
        success = terminated & self._succ[new * self.bank.num_categories + self.target]
        truncated = moving & (self.steps >= self.max_steps)
        finished = terminated | truncated
        if self.reward_fn is not None:
            kw = {"searching": self.stage.searching} if self._reward_uses_stage else {}  # before this step's update
            reward, terms = self.reward_fn.step(prev, a, new, collided, finished | ~active, success, **kw)
            reward = np.where(active, np.asarray(reward, dtype=np.float32), np.float32(0.0))
            terms = {k: np.where(active, np.asarray(v, dtype=np.float32), np.float32(0.0)) for k, v in terms.items()}
        else:
            reward = np.zeros(self.num_envs, dtype=np.float32)
            terms = {}
        self.stage.update(new, self.steps, self.path_length, active=active)
        stage = self.stage
        info = {
            "collided": collided,
            "failed": failed,
            "success": success,
            "steps": self.steps.copy(),
            "path_length": self.path_length.copy(),
            "final_state": new,
            "active": active.copy(),
            "reward_terms": terms,
            "entered": stage.entered.copy(),
            "switch_length": stage.switch_length.copy(),
            "switch_state": stage.switch_state.copy(),
        }
        self.state = new.copy()  # auto-reset writes into self.state; info keeps the final states
        self.active = active & ~finished
        if self.autoreset and finished.any():
            self._start_rows(finished)
        return self._obs(), reward, terminated, truncated, info

    # -- one episode in scalars ---------------------------------------------------------------------------
    # The single Gymnasium env's path (tsnav.sim.gym_env): a batch of one stepped in Python scalars, where the
    # array code above costs a microsecond per operation on (1,) arrays. reset / step above are the
    # references; tests/sim/test_gym_fast.py holds them equal, state and outputs, bit for bit.
    def reset_one(self) -> None:
        """:meth:`reset` of a batch of one (``num_envs`` = 1) with an episode from the sampler: the same draws,
        the same episode and the same state of the env, its stage switch and its reward."""
        if self.num_envs != 1:
            raise ValueError(f"reset_one needs num_envs == 1, got {self.num_envs}")
        if self.sampler is None:
            raise ValueError("BatchEnv has no episode sampler: pass episodes= to reset()")
        sample_one = getattr(self.sampler, "sample_one", None)
        if sample_one is not None:
            scene, target, start = sample_one(self.np_random)
        else:
            scene, target, start = (int(v[0]) for v in self.sampler.sample(1, self.np_random))
        self.scene[0], self.target[0], self.state[0], self.start[0] = scene, target, start, start
        self.steps[0] = 0
        self.path_length[0] = 0
        self.active[0] = True
        searching = self.stage.reset_one(start, target)
        if self.reward_fn is not None:
            kw = {"searching": searching} if self._reward_uses_stage else {}
            if self._reward_reset_one is not None:
                self._reward_reset_one(scene, target, start, **kw)
            else:
                kw = {"searching": np.array([searching])} if self._reward_uses_stage else {}
                self.reward_fn.reset(
                    np.ones(1, dtype=bool), self.scene.copy(), self.target.copy(), self.state.copy(), **kw
                )

    def step_one(self, action: int) -> tuple[float, bool, bool, dict]:
        """:meth:`step` of a batch of one (``num_envs`` = 1) in Python scalars: ``(reward, terminated,
        truncated, info)`` with every ``(1,)`` array of :meth:`step` as its Python scalar (the reward and its
        terms as the Python float of their float32 value); no observation dict (read :attr:`state`,
        :attr:`target`). The same state afterwards as ``step(np.array([action]))``."""
        if self.num_envs != 1:
            raise ValueError(f"step_one needs num_envs == 1, got {self.num_envs}")
        a = int(action)
        if not 0 <= a < NUM_ACTIONS:
            raise ValueError(f"actions must be in [0, {NUM_ACTIONS})")
        active = bool(self.active[0])
        prev = int(self.state[0])
        moved = int(self._ns[prev * NUM_ACTIONS + a])
        new = moved if active else prev
        is_done = a == DONE
        moving = active and not is_done
        failed = moving and moved == prev  # lastActionSuccess False
        collided = failed and a == MOVE_AHEAD  # a failed MoveAhead only (step)
        steps = int(self.steps[0]) + active
        path_length = int(self.path_length[0]) + moving
        self.steps[0] = steps
        self.path_length[0] = path_length
        terminated = active and is_done
        success = terminated and bool(self._succ[new * self.bank.num_categories + int(self.target[0])])
        truncated = moving and steps >= self.max_steps
        finished = terminated or truncated
        stage = self.stage
        if self.reward_fn is not None:
            searching = not stage.entered[0]  # before this step's update
            if self._reward_step_one is not None:
                kw = {"searching": searching} if self._reward_uses_stage else {}
                reward, terms = self._reward_step_one(prev, a, new, collided, finished or not active, success, **kw)
            else:
                kw = {"searching": np.array([searching])} if self._reward_uses_stage else {}
                r, t = self.reward_fn.step(
                    np.array([prev]),
                    np.array([a]),
                    np.array([new]),
                    np.array([collided]),
                    np.array([finished or not active]),
                    np.array([success]),
                    **kw,
                )
                reward = float(np.asarray(r, dtype=np.float32)[0])
                terms = {k: float(np.asarray(v, dtype=np.float32)[0]) for k, v in t.items()}
            if not active:
                reward, terms = 0.0, dict.fromkeys(terms, 0.0)
        else:
            reward, terms = 0.0, {}
        stage.update_one(new, steps, path_length, active)
        info = {
            "collided": collided,
            "failed": failed,
            "success": success,
            "steps": steps,
            "path_length": path_length,
            "final_state": new,
            "active": active,
            "reward_terms": terms,
            "entered": bool(stage.entered[0]),
            "switch_length": int(stage.switch_length[0]),
            "switch_state": int(stage.switch_state[0]),
        }
        self.state[0] = new
        self.active[0] = active and not finished
        if self.autoreset and finished:
            self._start_rows(np.ones(1, dtype=bool))
        return reward, terminated, truncated, info
