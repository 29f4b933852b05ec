"""The Two-Stage Reward Mechanism and the rest of the paper's reward (paper sections III-B, III-D, IV-A).

Per step ``t`` (the action taken in frame ``t-1`` leads to frame ``t``), the reward is the sum of the terms

==============  ==============================================================================  =========
term            value                                                                           variants
==============  ==============================================================================  =========
``explore``     ``K_e * (Area(RG_t) - Area(RG_{t-1}))`` if the step was taken in the searching  explore,
                stage (eq. ExploreReward, K_e = 0.1; :mod:`tsnav.tsrm.area`)                     tsrm
``distance``    ``K_d * (d(p_{t-1}, g) - d(p_t, g))`` if the step was taken in the pathfinding  distance,
                stage (eq. DistanceReward, K_d = 0.15; :mod:`tsnav.tsrm.distance`)               tsrm
``collision``   -0.1 when a MoveAhead fails at a (position, rotation) where this episode         all but
                already had a failed MoveAhead; the first there is free (III-D (iii)). A LookUp  sparse
                at horizon 0 or LookDown at 30 also fails but is no collision (``sim.batch``)
``slack``       -0.01 at every step, the final one included (III-D (iv))                         all
``success``     +5 when Done succeeds (III-D (v)); ``failed_done`` (0: a deviation from the paper   all
                when not) when Done fails
``regret``      a deviation from the paper: ``K_r * (D(s_{t-1}) - D(s_t) - 1)`` for a movement   tsrm-
                action taken in the pathfinding stage, ``D`` the shortest action count to a      regret
                success state on the state graph (L*), ``K_r = k_regret`` (0.05): each action
                beyond a shortest path costs ``K_r`` (:class:`~tsnav.tsrm.terms.RegretTerm`)
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
both; ``sparse`` keeps slack and success only; ``tsrm-regret`` (not the paper's) adds the regret term to ``tsrm``.
Stages are tracked in every variant (the SSR / SSSPL / NSNPL metrics need them). Every term is always returned (zeros when switched off) for logging.

Each term is a class of :mod:`tsnav.tsrm.terms` holding its batched, scalar and reference code; a variant is a
list of term names (``VARIANT_TERMS``). :class:`TSRMReward` and :class:`TSRMRewardReference` only run the terms
of their variant, in registration order (``docs/howto/add-a-reward-term.md`` adds one).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..constants import C_TARGET
from ..sim.stage import PATHFINDING, SEARCHING, above_threshold  # noqa: F401 (the stages, re-exported)
from .area import AreaConfig
from .terms import (  # noqa: F401 (the registry, re-exported)
    TERM_CLASSES,
    TERMS,
    VARIANT_TERMS,
    VARIANTS,
    RewardTerm,
    register_term,
    register_variant,
)


@dataclass(frozen=True)
class RewardConfig:
    """Reward of the paper (III-B, III-D) with the constants of IV-A as defaults."""

    variant: str = "tsrm"
    """Which terms are on: 'baseline' (collision, slack, success), 'explore' (+ exploration), 'distance'
    (+ distance), 'tsrm' (the paper's reward), 'sparse' (slack, success); the ablation of Table II; 'tsrm-regret'
    (tsrm + the regret term, a deviation from the paper). Any variant registered with
    :func:`~tsnav.tsrm.terms.register_variant`."""
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
    failed_done: float = 0.0
    """Added when Done fails: a deviation from the paper when not 0 (the paper's failed Done only ends the episode,
    without the success reward). At most 0."""
    k_regret: float = 0.05
    """K_r of the ``regret`` term, a deviation from the paper that only the ``tsrm-regret`` variant switches on
    (:class:`~tsnav.tsrm.terms.RegretTerm`): a pathfinding step is charged ``K_r`` per action by which it
    lengthened the shortest remaining way to the target (0 along a shortest path, 1 for a wasted action, 2 for a
    turn the wrong way, more for a step away)."""
    area: AreaConfig = field(default_factory=AreaConfig)
    """Observable trapezoid (1/4 m at horizon 0, 0.25/3 m at horizon 30) and the fast raster's sample size."""
    exact_area: bool = False
    """Measure the searched region with shapely polygons (exact, one episode at a time, slow) instead of the
    packed raster (within 1% over an episode, batched)."""

    def __post_init__(self):
        if self.variant not in VARIANT_TERMS:
            raise ValueError(f"unknown reward variant {self.variant!r} (choose from {', '.join(VARIANTS)})")
        if not self.distance_increase_scale >= 0:
            raise ValueError(f"distance_increase_scale must be >= 0, got {self.distance_increase_scale}")
        if not self.k_regret >= 0:
            raise ValueError(f"k_regret must be >= 0, got {self.k_regret}")
        if not self.failed_done <= 0:
            raise ValueError(f"failed_done must be <= 0, got {self.failed_done}")
        if isinstance(self.area, dict):  # from a saved JSON config
            object.__setattr__(self, "area", AreaConfig(**self.area))

    def uses(self, term: str) -> bool:
        """Whether ``term`` is switched on in this variant."""
        return term in VARIANT_TERMS[self.variant]

    def make_terms(self) -> list[RewardTerm]:
        """New instances of this variant's terms, in registration order (the order they are summed)."""
        on = VARIANT_TERMS[self.variant]
        return [cls(self) for name, cls in TERM_CLASSES.items() if name in on]


class TSRMReward:
    """Batched reward of :class:`RewardConfig` over a :class:`~tsnav.sim.batch.SceneBank`; implements the
    ``RewardFn`` protocol of :mod:`tsnav.sim.batch` (``reset`` / ``step`` on ``(B,)`` arrays; ``reset_one`` /
    ``step_one``, the same for a batch of one in Python scalars, for the single Gymnasium env) with the stage
    as an input: ``uses_stage`` asks the env for the ``searching`` mask of its
    :class:`~tsnav.sim.stage.StageSwitch` (the env's :attr:`~tsnav.sim.batch.BatchEnv.stage` holds the stage,
    the switching step and the step counters; the reward reads nothing else of it). The arithmetic is the
    terms' (:mod:`tsnav.tsrm.terms`); this class sums them.

    Per-episode state, readable for logging and pictures: :attr:`searched_area` (m^2), and :attr:`coverage`
    (the raster of ``RG_t``, :meth:`~tsnav.tsrm.area.BatchCoverage.region_mask`) when the fast area is in use.
    """

    uses_stage = True
    """Take the env's ``searching`` mask in :meth:`reset` and :meth:`step` (:mod:`tsnav.sim.batch`)."""

    def __init__(self, bank, config: RewardConfig = RewardConfig()):
        self.bank = bank
        self.config = config
        self.terms = config.make_terms()
        self.term = {t.name: t for t in self.terms}
        for t in self.terms:
            t.bind(self)
        self._alloc(0)

    def _alloc(self, b: int) -> None:
        self.batch_size = b
        self.scene = np.zeros(b, dtype=np.int64)
        self.target = np.zeros(b, dtype=np.int64)
        for t in self.terms:
            t.alloc(b)

    # -- the terms' state, by the names it had before terms were objects --------------------------------------
    @property
    def dist(self) -> np.ndarray | None:
        """The distance term's ``(S, C)`` pose-graph distances (None without a distance term)."""
        t = self.term.get("distance")
        return t.dist if t is not None else None

    @dist.setter
    def dist(self, value: np.ndarray) -> None:
        self.term["distance"].dist = value

    @property
    def coverage(self):
        """The exploration term's raster of ``RG_t`` (None without one, or with ``exact_area``)."""
        t = self.term.get("explore")
        return t.coverage if t is not None else None

    @property
    def collided_at(self) -> np.ndarray:
        """``(B, pose nodes)``: where each episode already had a failed MoveAhead (collision term)."""
        t = self.term.get("collision")
        return t.collided_at if t is not None else np.zeros((self.batch_size, 0), dtype=bool)

    @property
    def viewed(self) -> np.ndarray:
        """``(B, states per scene)``: states whose view is in ``RG`` already (exploration term)."""
        t = self.term.get("explore")
        return t.viewed if t is not None else np.zeros((self.batch_size, 0), dtype=bool)

    @property
    def searched_area(self) -> np.ndarray:
        """``Area(RG_t)`` of every episode, m^2 (zeros when the variant has no exploration term)."""
        t = self.term.get("explore")
        return t.searched_area() if t is not None else np.zeros(self.batch_size)

    def reset(
        self,
        mask: np.ndarray,
        scene_idx: np.ndarray,
        target: np.ndarray,
        start_state: np.ndarray,
        searching: np.ndarray,
    ) -> None:
        """Start episodes where ``mask`` is True (``(B,)`` arrays; global start state ids); ``searching``: the
        env's stage of the start frames (False where the start frame already switched to pathfinding)."""
        mask = np.asarray(mask, dtype=bool)
        if len(mask) != self.batch_size:
            self._alloc(len(mask))
        rows = np.flatnonzero(mask)
        self.scene[rows] = np.asarray(scene_idx, dtype=np.int64)[rows]
        self.target[rows] = np.asarray(target, dtype=np.int64)[rows]
        start = np.asarray(start_state, dtype=np.int64)[rows]
        search = np.asarray(searching, dtype=bool)[rows]
        for t in self.terms:
            t.reset(mask, rows, start, search)

    def step(
        self, prev_state, action, new_state, collided, done, success, searching
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Reward of one step of every episode: ``(reward (B,) float32, {term: (B,) float32})``; ``searching``:
        the env's ``(B,)`` stage in which this step's action was chosen (before the switch sees the new frame)."""
        prev = np.asarray(prev_state, dtype=np.int64)
        new = np.asarray(new_state, dtype=np.int64)
        collided = np.asarray(collided, dtype=bool)
        success = np.asarray(success, dtype=bool)
        b = len(prev)
        if b != self.batch_size:
            raise ValueError(f"step got {b} episodes but reset was called with {self.batch_size}")
        searching = np.asarray(searching, dtype=bool)
        values = {t.name: t.step(prev, action, new, collided, done, success, searching) for t in self.terms}
        terms = {k: values[k] if k in values else np.zeros(b, dtype=np.float64) for k in TERMS}
        out = {k: v.astype(np.float32) for k, v in terms.items()}
        reward = sum(terms.values()).astype(np.float32)
        return reward, out

    # -- one episode in scalars (the single Gymnasium env; references: reset / step above) ---------------------
    def reset_one(self, scene_idx: int, target: int, start_state: int, searching: bool) -> None:
        """:meth:`reset` of a batch of one episode, in Python scalars: the same state as
        ``reset([True], [scene_idx], [target], [start_state], searching=[searching])``
        (``tests/sim/test_gym_fast.py`` holds them equal)."""
        if self.batch_size != 1:
            self._alloc(1)
        self.scene[0] = scene_idx
        self.target[0] = target
        for t in self.terms:
            t.reset_one(start_state, searching)

    def step_one(
        self, prev_state: int, action: int, new_state: int, collided: bool, done: bool, success: bool, searching: bool
    ) -> tuple[float, dict[str, float]]:
        """:meth:`step` of a batch of one episode, in Python scalars: ``(reward, {term: value})``, the float32
        values of ``step`` as Python floats, computed in the same order (terms in float64, their sum rounded to
        float32), so they are bit-identical (``tests/sim/test_gym_fast.py``)."""
        if self.batch_size != 1:
            raise ValueError(f"step_one needs a batch of one episode; reset was called with {self.batch_size}")
        if getattr(self, "_one_names", None) != len(TERM_CLASSES):  # per set of terms: slots, constants in float32
            self._one_names = len(TERM_CLASSES)
            self._one_names_list = tuple(TERMS)
            self._one_calls = [(self._one_names_list.index(t.name), t.step_one) for t in self.terms]
            self._one_f32 = {v: float(np.float32(v)) for t in self.terms for v in t.constants()}
        values = [0.0] * len(self._one_names_list)  # terms off in this variant stay 0.0
        for i, step_one in self._one_calls:
            values[i] = step_one(prev_state, action, new_state, collided, done, success, searching)
        reward = float(np.float32(sum(values)))
        f32 = self._one_f32
        # float32 of each term: the constants looked up, zeros kept (with their sign), the rest converted
        return reward, {
            k: (v if v == 0.0 else f32[v] if v in f32 else float(np.float32(v)))
            for k, v in zip(self._one_names_list, values)
        }


class TSRMRewardReference:
    """The reward of :class:`RewardConfig` written directly from the paper, one episode of one scene at a
    time: shapely unions for ``RG_t``, a Python breadth-first search for ``d``, a Python set of collision
    poses (each term's ``reference_*`` code). Slow; the reference that :class:`TSRMReward` is tested against.
    State ids are scene-local."""

    def __init__(
        self,
        scene,
        config: RewardConfig = RewardConfig(),
        confidence: np.ndarray | None = None,
        success_distance: float = 1.0,
        protocol: str = "paper",
        c_target: float = C_TARGET,
    ):
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
        self.terms = config.make_terms()
        self.term = {t.name: t for t in self.terms}
        for t in self.terms:
            t.bind_reference(self)

    def reset(self, target: int, start_state: int) -> None:
        self.target = int(target)
        self.pathfinding = bool(above_threshold(self.confidence[start_state, self.target], self.c_target))
        self.switch_step = 0 if self.pathfinding else -1
        self.steps = 0
        for t in self.terms:
            t.reference_reset(self.target, int(start_state), not self.pathfinding)

    def step(
        self, prev_state: int, action: int, new_state: int, collided: bool, done: bool, success: bool
    ) -> tuple[float, dict[str, float]]:
        self.steps += 1
        searching = not self.pathfinding
        terms = dict.fromkeys(TERMS, 0.0)
        for t in self.terms:
            terms[t.name] = t.reference_step(prev_state, action, new_state, collided, done, success, searching)
        if searching and above_threshold(self.confidence[new_state, self.target], self.c_target):
            self.pathfinding = True
            self.switch_step = self.steps
        return float(sum(terms.values())), terms
