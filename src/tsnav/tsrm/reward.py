"""The Two-Stage Reward Mechanism and the rest of the paper's reward (paper sections III-B, III-D, IV-A).

Per step ``t`` (the action taken in frame ``t-1`` leads to frame ``t``), the reward is the sum of the terms

==============  ==============================================================================  =========
term            value                                                                           variants
==============  ==============================================================================  =========
``explore``     ``K_e * (Area(RG_t) - Area(RG_{t-1}))`` if the step was taken in the searching  explore,
                stage (eq. ExploreReward, K_e = 0.1; :mod:`tsnav.tsrm.area`)                     tsrm
``distance``    ``K_d * (d(p_{t-1}, g) - d(p_t, g))`` if the step was taken in the pathfinding  distance,
                stage (eq. DistanceReward, K_d = 0.15; :mod:`tsnav.tsrm.distance`)               tsrm
``collision``   -0.1 when a MoveAhead fails at a (position, rotation) where this episode         all
                already had a failed MoveAhead; the first there is free (III-D (iii)). A LookUp
                at horizon 0 or LookDown at 30 also fails but is no collision (``sim.batch``)
``slack``       -0.01 at every step, the final one included (III-D (iv))                         all
``success``     +5 when Done succeeds (III-D (v))                                                all
==============  ==============================================================================  =========

Stages (III-B, "Dividing point"): an episode starts in the searching stage and enters the pathfinding stage,
for good, at the first frame whose detector confidence for the target exceeds ``C_target = 0.7``; the start
frame counts (:class:`tsnav.sim.stage.StageSwitch` holds the rule and the per-episode stage). The reward keeps
no stage of its own: the env that owns the switch (:class:`~tsnav.sim.batch.BatchEnv`) hands it the
``searching`` mask in ``reset`` and ``step`` (``TSRMReward.uses_stage``). A step is
*taken in* the stage of the frame where its action was chosen, so the step that reaches the switching frame
still earns the exploration reward (it is the searching action that found the target) and every later step
earns the distance reward. An episode whose start frame already shows the
target gets distance rewards from its first step.

Searched region: ``RG`` starts as the start frame's trapezoid clipped to the floor, without reward (no
action produced that view; the paper's "RG_0 is initially null" is the region before the first frame), and
grows only during the searching stage. A step that leaves the state unchanged (a failed action, Done) adds
nothing, because ``T_t = T_{t-1}`` is already in ``RG_{t-1}``.

Variants (Table II of the paper): ``baseline`` keeps collision, slack and success - the paper's baseline is
the lineage's reward with "the two-stage reward mechanism not applied", and the collision penalty is part of
the common reward of III-D, not of TSRM; ``explore`` and ``distance`` add one TSRM term each; ``tsrm`` adds
both. Stages are tracked in every variant (the SSR / SSSPL / NSNPL metrics need them). Every term is always
returned (zeros when switched off) for logging.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..constants import C_TARGET
from ..sim.stage import PATHFINDING, SEARCHING, above_threshold  # noqa: F401 (the stages, re-exported)
from ..sim.paths import UNREACHABLE
from .area import AreaConfig, AreaIndex, BatchCoverage, ExactSearchedRegion, scene_floor
from .distance import bank_pose_distance, distance_delta, pose_distance_reference, pose_nodes


VARIANTS = ("baseline", "explore", "distance", "tsrm")
TERMS = ("explore", "distance", "collision", "slack", "success")
#: Terms each variant switches on.
VARIANT_TERMS = {
    "baseline": ("collision", "slack", "success"),
    "explore": ("explore", "collision", "slack", "success"),
    "distance": ("distance", "collision", "slack", "success"),
    "tsrm": TERMS,
}


@dataclass(frozen=True)
class RewardConfig:
    """Reward of the paper (III-B, III-D) with the constants of IV-A as defaults."""

    variant: str = "tsrm"
    """Which terms are on: 'baseline' (collision, slack, success), 'explore' (+ exploration), 'distance'
    (+ distance), 'tsrm' (all); the ablation of Table II."""
    k_explore: float = 0.1
    """K_e, reward per square metre of newly searched floor (eq. ExploreReward)."""
    k_distance: float = 0.15
    """K_d, reward per pose-graph action of progress towards the nearest success pose (eq. DistanceReward)."""
    distance_increase_scale: float = 1.0
    """A deviation from the paper when not 1.0 (the paper's eq. DistanceReward is symmetric): the distance term of a
    step that *increases* ``d`` is multiplied by this. With 1.0 the term is a difference of potentials, so a turn
    the long way round (six 45-degree turns instead of two) earns the same sum as the short way and costs only the
    slack; with a scale above 1 every step off a shortest path costs ``(scale - 1) * K_d`` more, while every shortest
    path keeps its full reward (along one, ``d`` never increases). Measured at 2: no gain (docs/RESULTS.md)."""
    collision_penalty: float = -0.1
    """Added when an action fails again at a (position, rotation) where one already failed (III-D (iii))."""
    slack: float = -0.01
    """Added at every step (III-D (iv))."""
    success_reward: float = 5.0
    """Added when Done succeeds (III-D (v))."""
    area: AreaConfig = field(default_factory=AreaConfig)
    """Observable trapezoid (1/4 m at horizon 0, 0.25/3 m at horizon 30) and the fast raster's sample size."""
    exact_area: bool = False
    """Measure the searched region with shapely polygons (exact, one episode at a time, slow) instead of the
    packed raster (within 1% over an episode, batched)."""

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown reward variant {self.variant!r} (choose from {', '.join(VARIANTS)})")
        if not self.distance_increase_scale >= 0:
            raise ValueError(f"distance_increase_scale must be >= 0, got {self.distance_increase_scale}")
        if isinstance(self.area, dict):  # from a saved JSON config
            object.__setattr__(self, "area", AreaConfig(**self.area))

    def uses(self, term: str) -> bool:
        """Whether ``term`` is switched on in this variant."""
        return term in VARIANT_TERMS[self.variant]


class TSRMReward:
    """Batched reward of :class:`RewardConfig` over a :class:`~tsnav.sim.batch.SceneBank`; implements the
    ``RewardFn`` protocol of :mod:`tsnav.sim.batch` (``reset`` / ``step`` on ``(B,)`` arrays; ``reset_one`` /
    ``step_one``, the same for a batch of one in Python scalars, for the single Gymnasium env) with the stage
    as an input: ``uses_stage`` asks the env for the ``searching`` mask of its
    :class:`~tsnav.sim.stage.StageSwitch` (the env's :attr:`~tsnav.sim.batch.BatchEnv.stage` holds the stage,
    the switching step and the step counters; the reward reads nothing else of it).

    Per-episode state, readable for logging and pictures: :attr:`searched_area` (m^2), and :attr:`coverage`
    (the raster of ``RG_t``, :meth:`~tsnav.tsrm.area.BatchCoverage.region_mask`) when the fast area is in use.
    """

    uses_stage = True
    """Take the env's ``searching`` mask in :meth:`reset` and :meth:`step` (:mod:`tsnav.sim.batch`)."""

    def __init__(self, bank, config: RewardConfig = RewardConfig()):
        self.bank = bank
        self.config = config
        self.dist = bank_pose_distance(bank) if config.uses("distance") else None
        node_of, _ = pose_nodes(bank.x, bank.z, bank.rotation, bank.scene_of)
        # Pose nodes are numbered scene by scene; the collision memory indexes them per scene.
        first = np.full(bank.num_scenes, np.iinfo(np.int64).max, dtype=np.int64)
        np.minimum.at(first, bank.scene_of.astype(np.int64), node_of)
        self.node_local = node_of - first[bank.scene_of]
        self.nodes_per_scene = int(self.node_local.max()) + 1
        self.state_local = np.arange(bank.num_states, dtype=np.int64) - bank.offsets[bank.scene_of]
        self.states_per_scene = int(np.diff(bank.offsets).max())
        self.area_index = None
        self._floors: dict[int, object] = {}
        if config.uses("explore") and not config.exact_area:
            self.area_index = AreaIndex([scene_floor(s) for s in bank.scenes],
                                        [(s.x, s.z) for s in bank.scenes], bank.rotation, bank.horizon, config.area)
        self._alloc(0)

    def _alloc(self, b: int) -> None:
        self.batch_size = b
        self.scene = np.zeros(b, dtype=np.int64)
        self.target = np.zeros(b, dtype=np.int64)
        self.collided_at = np.zeros((b, self.nodes_per_scene), dtype=bool)
        # States whose view is already in RG (exploration only): revisiting one adds no area, skip its stencil.
        self.viewed = np.zeros((b, self.states_per_scene if self.config.uses("explore") else 0), dtype=bool)
        self.coverage = BatchCoverage(self.area_index, b) if self.area_index is not None else None
        self._exact: list[ExactSearchedRegion | None] = [None] * b

    @property
    def searched_area(self) -> np.ndarray:
        """``Area(RG_t)`` of every episode, m^2 (zeros when the variant has no exploration term)."""
        if self.coverage is not None:
            return self.coverage.area()
        return np.array([r.area if r is not None else 0.0 for r in self._exact])

    def _exact_region(self, scene: int) -> ExactSearchedRegion:
        if scene not in self._floors:
            self._floors[scene] = scene_floor(self.bank.scenes[scene])
        return ExactSearchedRegion(self._floors[scene], self.config.area)

    def _add_views(self, rows: np.ndarray, states: np.ndarray) -> np.ndarray:
        """Add the trapezoids of ``states`` to episodes ``rows``; gained area per row, m^2."""
        if self.coverage is not None:
            return self.coverage.add(rows, states)
        bank = self.bank
        return np.array([self._exact[b].add(float(bank.x[s]), float(bank.z[s]), int(bank.rotation[s]),
                                            int(bank.horizon[s])) for b, s in zip(rows, states)])

    def reset(self, mask: np.ndarray, scene_idx: np.ndarray, target: np.ndarray, start_state: np.ndarray,
              searching: np.ndarray) -> None:
        """Start episodes where ``mask`` is True (``(B,)`` arrays; global start state ids); ``searching``: the
        env's stage of the start frames (False where the start frame already switched to pathfinding)."""
        mask = np.asarray(mask, dtype=bool)
        if len(mask) != self.batch_size:
            self._alloc(len(mask))
        rows = np.flatnonzero(mask)
        scene_idx = np.asarray(scene_idx, dtype=np.int64)[rows]
        target = np.asarray(target, dtype=np.int64)[rows]
        start = np.asarray(start_state, dtype=np.int64)[rows]
        self.scene[rows] = scene_idx
        self.target[rows] = target
        at_start = ~np.asarray(searching, dtype=bool)[rows]
        self.collided_at[rows] = False
        if self.config.uses("explore"):
            if self.coverage is not None:
                self.coverage.reset(mask, self.scene)
            else:
                for b, s in zip(rows, scene_idx):
                    self._exact[b] = self._exact_region(int(s))
            search = ~at_start
            self.viewed[rows] = False
            self.viewed[rows[search], self.state_local[start[search]]] = True
            self._add_views(rows[search], start[search])  # the start view, without reward

    def step(self, prev_state, action, new_state, collided, done, success, searching
             ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Reward of one step of every episode: ``(reward (B,) float32, {term: (B,) float32})``; ``searching``:
        the env's ``(B,)`` stage in which this step's action was chosen (before the switch sees the new frame)."""
        cfg = self.config
        prev = np.asarray(prev_state, dtype=np.int64)
        new = np.asarray(new_state, dtype=np.int64)
        collided = np.asarray(collided, dtype=bool)
        success = np.asarray(success, dtype=bool)
        b = len(prev)
        if b != self.batch_size:
            raise ValueError(f"step got {b} episodes but reset was called with {self.batch_size}")
        searching = np.asarray(searching, dtype=bool)
        terms = {k: np.zeros(b, dtype=np.float64) for k in TERMS}
        if cfg.uses("explore"):
            fresh = np.zeros(b, dtype=bool)
            fresh[searching] = ~self.viewed[np.flatnonzero(searching), self.state_local[new[searching]]]
            rows = np.flatnonzero(fresh)
            self.viewed[rows, self.state_local[new[rows]]] = True
            terms["explore"][rows] = cfg.k_explore * self._add_views(rows, new[rows])
        if cfg.uses("distance"):
            rows = np.flatnonzero(~searching)
            delta = distance_delta(self.dist, prev[rows], new[rows], self.target[rows])
            if cfg.distance_increase_scale != 1.0:
                delta = np.where(delta < 0, cfg.distance_increase_scale * delta, delta)
            terms["distance"][rows] = cfg.k_distance * delta
        rows = np.flatnonzero(collided)
        if len(rows):
            nodes = self.node_local[prev[rows]]
            repeat = self.collided_at[rows, nodes]
            self.collided_at[rows, nodes] = True
            terms["collision"][rows] = np.where(repeat, cfg.collision_penalty, 0.0)
        terms["slack"][:] = cfg.slack
        terms["success"][success] = cfg.success_reward
        for k in TERMS:
            if not cfg.uses(k):
                terms[k][:] = 0.0
        out = {k: v.astype(np.float32) for k, v in terms.items()}
        reward = sum(terms.values()).astype(np.float32)
        return reward, out


    # -- one episode in scalars (the single Gymnasium env; references: reset / step above) ---------------------
    def _add_view_one(self, state: int) -> float:
        if self.coverage is not None:
            return self.coverage.add_one(0, state)
        bank = self.bank
        return self._exact[0].add(float(bank.x[state]), float(bank.z[state]), int(bank.rotation[state]),
                                  int(bank.horizon[state]))

    def reset_one(self, scene_idx: int, target: int, start_state: int, searching: bool) -> None:
        """:meth:`reset` of a batch of one episode, in Python scalars: the same state as
        ``reset([True], [scene_idx], [target], [start_state], searching=[searching])``
        (``tests/test_gym_fast.py`` holds them equal)."""
        if self.batch_size != 1:
            self._alloc(1)
        self.scene[0] = scene_idx
        self.target[0] = target
        self.collided_at[0] = False
        if self.config.uses("explore"):
            if self.coverage is not None:
                self.coverage.reset_one(0, scene_idx)
            else:
                self._exact[0] = self._exact_region(int(scene_idx))
            self.viewed[0] = False
            if searching:
                self.viewed[0, self.state_local[start_state]] = True
                self._add_view_one(start_state)  # the start view, without reward

    def step_one(self, prev_state: int, action: int, new_state: int, collided: bool, done: bool, success: bool,
                 searching: bool) -> tuple[float, dict[str, float]]:
        """:meth:`step` of a batch of one episode, in Python scalars: ``(reward, {term: value})``, the float32
        values of ``step`` as Python floats, computed in the same order (terms in float64, their sum rounded to
        float32), so they are bit-identical (``tests/test_gym_fast.py``)."""
        if self.batch_size != 1:
            raise ValueError(f"step_one needs a batch of one episode; reset was called with {self.batch_size}")
        cfg = self.config
        if getattr(self, "_one_config", None) is not cfg:  # per config: which terms are on, constants in float32
            self._one_config = cfg
            self._one_on = tuple(cfg.uses(k) for k in TERMS)
            self._one_f32 = {v: float(np.float32(v)) for v in (cfg.slack, cfg.success_reward, cfg.collision_penalty)}
        explore = distance = collision = 0.0
        on_explore, on_distance, _, _, _ = self._one_on
        if on_explore and searching:
            local = self.state_local[new_state]
            if not self.viewed[0, local]:
                self.viewed[0, local] = True
                explore = cfg.k_explore * self._add_view_one(new_state)
        if on_distance and not searching:
            target = int(self.target[0])
            d0, d1 = int(self.dist[prev_state, target]), int(self.dist[new_state, target])
            delta = float(d0 - d1) if d0 != UNREACHABLE and d1 != UNREACHABLE else 0.0  # distance_delta
            if delta < 0 and cfg.distance_increase_scale != 1.0:
                delta = cfg.distance_increase_scale * delta
            distance = cfg.k_distance * delta
        if collided:
            node = self.node_local[prev_state]
            repeat = bool(self.collided_at[0, node])
            self.collided_at[0, node] = True
            collision = cfg.collision_penalty if repeat else 0.0
        values = [v if on else 0.0 for v, on in zip((explore, distance, collision, cfg.slack,
                                                     cfg.success_reward if success else 0.0), self._one_on)]
        reward = float(np.float32(sum(values)))
        f32 = self._one_f32
        # float32 of each term: the constants looked up, zeros kept (with their sign), the rest converted
        return reward, {k: (v if v == 0.0 else f32[v] if v in f32 else float(np.float32(v)))
                        for k, v in zip(TERMS, values)}


class TSRMRewardReference:
    """The reward of :class:`RewardConfig` written directly from the paper, one episode of one scene at a
    time: shapely unions for ``RG_t``, a Python breadth-first search for ``d``, a Python set of collision
    poses. Slow; the reference that :class:`TSRMReward` is tested against. State ids are scene-local."""

    def __init__(self, scene, config: RewardConfig = RewardConfig(), confidence: np.ndarray | None = None,
                 success_distance: float = 1.0, protocol: str = "paper", c_target: float = C_TARGET):
        """``confidence``: ``(S, C)`` of this scene; defaults to 1.0 where the target category is in frame.
        The reference follows its own stages (the rule of III-B at ``c_target``), independently of any env."""
        self.scene = scene
        self.config = config
        self.c_target = c_target
        if confidence is None:
            seen = scene.visible_at_any_range()
            confidence = np.zeros((scene.num_states, scene.num_categories), dtype=np.float32)
            for o, c in enumerate(scene.object_category):
                if c >= 0:
                    confidence[seen[:, o], c] = 1.0
        self.confidence = np.asarray(confidence)
        self.success_distance = success_distance
        self.protocol = protocol
        self.floor = scene_floor(scene) if config.uses("explore") else None
        self._dist_cache: dict[int, np.ndarray] = {}

    def _pose(self, s: int) -> tuple[float, float, int]:
        sc = self.scene
        return round(float(sc.x[s]), 2), round(float(sc.z[s]), 2), int(sc.rotation[s]) % 360

    def _d(self, s: int) -> int:
        return int(self._dist_cache[self.target][s])

    def reset(self, target: int, start_state: int) -> None:
        self.target = int(target)
        if self.config.uses("distance") and self.target not in self._dist_cache:  # BFS once per target
            sc = self.scene
            self._dist_cache[self.target] = pose_distance_reference(
                sc.next_state, sc.x, sc.z, sc.rotation,
                sc.success_table(self.protocol, self.success_distance)[:, self.target])
        self.pathfinding = bool(above_threshold(self.confidence[start_state, self.target], self.c_target))
        self.switch_step = 0 if self.pathfinding else -1
        self.steps = 0
        self.collision_poses: set = set()
        self.region = ExactSearchedRegion(self.floor, self.config.area) if self.floor is not None else None
        if self.region is not None and not self.pathfinding:
            sc = self.scene
            self.region.add(sc.x[start_state], sc.z[start_state], sc.rotation[start_state], sc.horizon[start_state])

    def step(self, prev_state: int, action: int, new_state: int, collided: bool, done: bool, success: bool
             ) -> tuple[float, dict[str, float]]:
        cfg = self.config
        sc = self.scene
        self.steps += 1
        terms = dict.fromkeys(TERMS, 0.0)
        if not self.pathfinding:
            if cfg.uses("explore"):
                before = self.region.area
                self.region.add(sc.x[new_state], sc.z[new_state], sc.rotation[new_state], sc.horizon[new_state])
                terms["explore"] = cfg.k_explore * (self.region.area - before)
            if above_threshold(self.confidence[new_state, self.target], self.c_target):
                self.pathfinding = True
                self.switch_step = self.steps
        elif cfg.uses("distance"):
            d0, d1 = self._d(prev_state), self._d(new_state)
            if d0 != UNREACHABLE and d1 != UNREACHABLE:
                scale = cfg.distance_increase_scale if d1 > d0 else 1.0  # an increase may cost more (a deviation)
                terms["distance"] = cfg.k_distance * scale * (d0 - d1)
        if collided:
            pose = self._pose(prev_state)
            if pose in self.collision_poses:
                terms["collision"] = cfg.collision_penalty
            self.collision_poses.add(pose)
        terms["slack"] = cfg.slack
        if success:
            terms["success"] = cfg.success_reward
        terms = {k: (v if cfg.uses(k) else 0.0) for k, v in terms.items()}
        return float(sum(terms.values())), terms
