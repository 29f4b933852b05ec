"""Reward terms: one class per term, owning its batched, scalar and reference code (paper III-B, III-D).

A term is a small measure in habitat-lab's sense (``habitat/tasks/nav/nav.py``: ``reset_metric`` /
``update_metric``, one class per quantity): everything one term of the reward needs lives in one class, in
three forms that tests hold together:

============================  ================================================================================
methods                       used by
============================  ================================================================================
``bind``, ``alloc``,          :class:`~tsnav.tsrm.reward.TSRMReward` (the trainers, the vector env): a batch of
``reset``, ``step``           ``(B,)`` episodes over a :class:`~tsnav.sim.batch.SceneBank`, global state ids
``reset_one``, ``step_one``   the same reward for a batch of one in Python scalars (the single Gymnasium env);
                              bit-identical to ``step`` (``tests/sim/test_gym_fast.py``)
``bind_reference``,           :class:`~tsnav.tsrm.reward.TSRMRewardReference`: one episode of one scene, written
``reference_reset``,          directly from the paper (shapely, Python BFS, Python sets), scene-local state ids;
``reference_step``            the slow reference the fast code is tested against (``tests/tsrm/test_tsrm_reward.py``)
============================  ================================================================================

Every ``step`` gets the env's stage as ``searching``: the stage in which the step's action was chosen (the
reward keeps no stage of its own; :mod:`tsnav.sim.stage`). A term reads its constants from the
:class:`~tsnav.tsrm.reward.RewardConfig` it is made with, or from its own class attributes.

A variant is a list of term names (:data:`VARIANT_TERMS`); :func:`register_term` and :func:`register_variant`
add new ones (``docs/howto/add-a-reward-term.md``). Terms are summed in the order they were registered; the
reward reports every registered term (zeros for those its variant leaves out).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from ..constants import DONE
from ..sim.paths import UNREACHABLE, bfs_reference
from .area import AreaIndex, BatchCoverage, ExactSearchedRegion, scene_floor
from .distance import bank_pose_distance, distance_delta, pose_distance_reference, pose_nodes


class RewardTerm:
    """One term of the reward. Subclasses set :attr:`name` and override ``step`` / ``step_one`` /
    ``reference_step`` (and the resets when the term keeps per-episode state). ``owner`` is the reward that
    holds the term: ``owner.bank``, ``owner.target`` / ``owner.scene`` (``(B,)``, global ids) for the batched
    forms; ``owner.scene`` (a :class:`~tsnav.data.reader.Scene`) and ``owner.target`` for the reference."""

    name: ClassVar[str] = ""
    """The term's name: the key of ``info["reward_terms"]`` / ``info["reward/<name>"]`` and of variants."""

    def __init__(self, config):
        self.config = config

    def constants(self) -> tuple[float, ...]:
        """Values the term often returns as they are (their float32 is cached by ``TSRMReward.step_one``)."""
        return ()

    # -- batched: (B,) arrays, global state ids ------------------------------------------------------------
    def bind(self, owner) -> None:
        """Precompute what the term needs of ``owner.bank`` (once per reward)."""
        self.owner = owner

    def alloc(self, b: int) -> None:
        """Per-episode state for a batch of ``b`` episodes."""

    def reset(self, mask: np.ndarray, rows: np.ndarray, start: np.ndarray, searching: np.ndarray) -> None:
        """Episodes ``rows`` (``np.flatnonzero(mask)``) start at global states ``start``; ``searching``: their
        start frame's stage. ``owner.scene`` / ``owner.target`` already hold the new episodes'."""

    def step(self, prev, action, new, collided, done, success, searching) -> np.ndarray:
        """The term of one step of every episode, ``(B,)`` float64."""
        raise NotImplementedError

    # -- one episode in Python scalars ---------------------------------------------------------------------
    def reset_one(self, start: int, searching: bool) -> None:
        """:meth:`reset` of a batch of one (``owner.scene[0]`` / ``owner.target[0]`` are set)."""

    def step_one(
        self, prev: int, action: int, new: int, collided: bool, done: bool, success: bool, searching: bool
    ) -> float:
        """:meth:`step` of a batch of one, a Python float computed as ``step`` computes it."""
        raise NotImplementedError

    # -- the reference: one episode of one scene, scene-local state ids ------------------------------------
    def bind_reference(self, owner) -> None:
        """Precompute what the term needs of ``owner.scene`` (once per reference)."""
        self.owner = owner

    def reference_reset(self, target: int, start: int, searching: bool) -> None:
        """A new episode of ``target`` from ``start``; ``searching``: the start frame's stage."""

    def reference_step(
        self, prev: int, action: int, new: int, collided: bool, done: bool, success: bool, searching: bool
    ) -> float:
        """The term of one step, written from the paper."""
        raise NotImplementedError


class ExploreTerm(RewardTerm):
    """``K_e * (Area(RG_t) - Area(RG_{t-1}))`` for a step taken in the searching stage (eq. ExploreReward).

    ``RG`` starts as the start frame's trapezoid (no reward) and grows only while searching; a revisited state
    adds nothing (its view is in ``RG`` already), so its stencil is skipped. Fast: the packed raster of
    :class:`~tsnav.tsrm.area.BatchCoverage` (or shapely per episode with ``exact_area``); reference: shapely."""

    name = "explore"

    def bind(self, owner) -> None:
        super().bind(owner)
        bank, cfg = owner.bank, self.config
        self.state_local = np.arange(bank.num_states, dtype=np.int64) - bank.offsets[bank.scene_of]
        self.states_per_scene = int(np.diff(bank.offsets).max())
        self.area_index = None
        self._floors: dict[int, object] = {}
        if not cfg.exact_area:
            self.area_index = AreaIndex(
                [scene_floor(s) for s in bank.scenes],
                [(s.x, s.z) for s in bank.scenes],
                bank.rotation,
                bank.horizon,
                cfg.area,
            )

    def alloc(self, b: int) -> None:
        # States whose view is already in RG: revisiting one adds no area, skip its stencil.
        self.viewed = np.zeros((b, self.states_per_scene), dtype=bool)
        self.coverage = BatchCoverage(self.area_index, b) if self.area_index is not None else None
        self._exact: list[ExactSearchedRegion | None] = [None] * b

    def searched_area(self) -> np.ndarray:
        """``Area(RG_t)`` of every episode, m^2."""
        if self.coverage is not None:
            return self.coverage.area()
        return np.array([r.area if r is not None else 0.0 for r in self._exact])

    def _exact_region(self, scene: int) -> ExactSearchedRegion:
        if scene not in self._floors:
            self._floors[scene] = scene_floor(self.owner.bank.scenes[scene])
        return ExactSearchedRegion(self._floors[scene], self.config.area)

    def _add_views(self, rows: np.ndarray, states: np.ndarray) -> np.ndarray:
        """Add the trapezoids of ``states`` to episodes ``rows``; gained area per row, m^2."""
        if self.coverage is not None:
            return self.coverage.add(rows, states)
        bank = self.owner.bank
        return np.array(
            [
                self._exact[b].add(float(bank.x[s]), float(bank.z[s]), int(bank.rotation[s]), int(bank.horizon[s]))
                for b, s in zip(rows, states)
            ]
        )

    def reset(self, mask, rows, start, searching) -> None:
        if self.coverage is not None:
            self.coverage.reset(mask, self.owner.scene)
        else:
            for b, s in zip(rows, self.owner.scene[rows]):
                self._exact[b] = self._exact_region(int(s))
        search = np.asarray(searching, dtype=bool)
        self.viewed[rows] = False
        self.viewed[rows[search], self.state_local[start[search]]] = True
        self._add_views(rows[search], start[search])  # the start view, without reward

    def step(self, prev, action, new, collided, done, success, searching) -> np.ndarray:
        out = np.zeros(len(new), dtype=np.float64)
        fresh = np.zeros(len(new), dtype=bool)
        fresh[searching] = ~self.viewed[np.flatnonzero(searching), self.state_local[new[searching]]]
        rows = np.flatnonzero(fresh)
        self.viewed[rows, self.state_local[new[rows]]] = True
        out[rows] = self.config.k_explore * self._add_views(rows, new[rows])
        return out

    def _add_view_one(self, state: int) -> float:
        if self.coverage is not None:
            return self.coverage.add_one(0, state)
        bank = self.owner.bank
        return self._exact[0].add(
            float(bank.x[state]), float(bank.z[state]), int(bank.rotation[state]), int(bank.horizon[state])
        )

    def reset_one(self, start: int, searching: bool) -> None:
        scene_idx = self.owner.scene[0]
        if self.coverage is not None:
            self.coverage.reset_one(0, scene_idx)
        else:
            self._exact[0] = self._exact_region(int(scene_idx))
        self.viewed[0] = False
        if searching:
            self.viewed[0, self.state_local[start]] = True
            self._add_view_one(start)  # the start view, without reward

    def step_one(self, prev, action, new, collided, done, success, searching) -> float:
        if searching:
            local = self.state_local[new]
            if not self.viewed[0, local]:
                self.viewed[0, local] = True
                return self.config.k_explore * self._add_view_one(new)
        return 0.0

    def bind_reference(self, owner) -> None:
        super().bind_reference(owner)
        self.floor = scene_floor(owner.scene)

    def reference_reset(self, target, start, searching) -> None:
        self.region = ExactSearchedRegion(self.floor, self.config.area)
        if searching:
            sc = self.owner.scene
            self.region.add(sc.x[start], sc.z[start], sc.rotation[start], sc.horizon[start])

    def reference_step(self, prev, action, new, collided, done, success, searching) -> float:
        if not searching:
            return 0.0
        sc = self.owner.scene
        before = self.region.area
        self.region.add(sc.x[new], sc.z[new], sc.rotation[new], sc.horizon[new])
        return self.config.k_explore * (self.region.area - before)


class DistanceTerm(RewardTerm):
    """``K_d * (d(p_{t-1}, g) - d(p_t, g))`` for a step taken in the pathfinding stage (eq. DistanceReward);
    ``d``: actions on the (position, rotation) graph to the nearest success pose (:mod:`tsnav.tsrm.distance`;
    0 where either end is unreachable). A step that increases ``d`` is multiplied by
    ``distance_increase_scale`` (1.0, the paper's symmetric term, by default)."""

    name = "distance"

    def bind(self, owner) -> None:
        super().bind(owner)
        self.dist = bank_pose_distance(owner.bank)

    def step(self, prev, action, new, collided, done, success, searching) -> np.ndarray:
        cfg = self.config
        out = np.zeros(len(new), dtype=np.float64)
        rows = np.flatnonzero(~searching)
        delta = distance_delta(self.dist, prev[rows], new[rows], self.owner.target[rows])
        if cfg.distance_increase_scale != 1.0:
            delta = np.where(delta < 0, cfg.distance_increase_scale * delta, delta)
        out[rows] = cfg.k_distance * delta
        return out

    def step_one(self, prev, action, new, collided, done, success, searching) -> float:
        if searching:
            return 0.0
        cfg = self.config
        target = int(self.owner.target[0])
        d0, d1 = int(self.dist[prev, target]), int(self.dist[new, target])
        delta = float(d0 - d1) if d0 != UNREACHABLE and d1 != UNREACHABLE else 0.0  # distance_delta
        if delta < 0 and cfg.distance_increase_scale != 1.0:
            delta = cfg.distance_increase_scale * delta
        return cfg.k_distance * delta

    def bind_reference(self, owner) -> None:
        super().bind_reference(owner)
        self._dist_cache: dict[int, np.ndarray] = {}

    def reference_reset(self, target, start, searching) -> None:
        owner = self.owner
        if target not in self._dist_cache:  # BFS once per target
            sc = owner.scene
            self._dist_cache[target] = pose_distance_reference(
                sc.next_state,
                sc.x,
                sc.z,
                sc.rotation,
                sc.success_table(owner.protocol, owner.success_distance)[:, target],
            )
        self._d = self._dist_cache[target]

    def reference_step(self, prev, action, new, collided, done, success, searching) -> float:
        if searching:
            return 0.0
        cfg = self.config
        d0, d1 = int(self._d[prev]), int(self._d[new])
        if d0 == UNREACHABLE or d1 == UNREACHABLE:
            return 0.0
        scale = cfg.distance_increase_scale if d1 > d0 else 1.0  # an increase may cost more (a deviation)
        return cfg.k_distance * scale * (d0 - d1)


class CollisionTerm(RewardTerm):
    """``collision_penalty`` (-0.1) when a MoveAhead fails at a (position, rotation) where this episode already
    had a failed MoveAhead; the first there is free (III-D (iii)). A failed look is no collision (``sim.batch``)."""

    name = "collision"

    def constants(self):
        return (self.config.collision_penalty,)

    def bind(self, owner) -> None:
        super().bind(owner)
        bank = owner.bank
        node_of, _ = pose_nodes(bank.x, bank.z, bank.rotation, bank.scene_of)
        # Pose nodes are numbered scene by scene; the collision memory indexes them per scene.
        first = np.full(bank.num_scenes, np.iinfo(np.int64).max, dtype=np.int64)
        np.minimum.at(first, bank.scene_of.astype(np.int64), node_of)
        self.node_local = node_of - first[bank.scene_of]
        self.nodes_per_scene = int(self.node_local.max()) + 1

    def alloc(self, b: int) -> None:
        self.collided_at = np.zeros((b, self.nodes_per_scene), dtype=bool)

    def reset(self, mask, rows, start, searching) -> None:
        self.collided_at[rows] = False

    def step(self, prev, action, new, collided, done, success, searching) -> np.ndarray:
        out = np.zeros(len(prev), dtype=np.float64)
        rows = np.flatnonzero(collided)
        if len(rows):
            nodes = self.node_local[prev[rows]]
            repeat = self.collided_at[rows, nodes]
            self.collided_at[rows, nodes] = True
            out[rows] = np.where(repeat, self.config.collision_penalty, 0.0)
        return out

    def reset_one(self, start, searching) -> None:
        self.collided_at[0] = False

    def step_one(self, prev, action, new, collided, done, success, searching) -> float:
        if not collided:
            return 0.0
        node = self.node_local[prev]
        repeat = bool(self.collided_at[0, node])
        self.collided_at[0, node] = True
        return self.config.collision_penalty if repeat else 0.0

    def reference_reset(self, target, start, searching) -> None:
        self.poses: set = set()

    def reference_step(self, prev, action, new, collided, done, success, searching) -> float:
        if not collided:
            return 0.0
        sc = self.owner.scene
        pose = (round(float(sc.x[prev]), 2), round(float(sc.z[prev]), 2), int(sc.rotation[prev]) % 360)
        value = self.config.collision_penalty if pose in self.poses else 0.0
        self.poses.add(pose)
        return value


class SlackTerm(RewardTerm):
    """``slack`` (-0.01) at every step, the final one included (III-D (iv))."""

    name = "slack"

    def constants(self):
        return (self.config.slack,)

    def step(self, prev, action, new, collided, done, success, searching) -> np.ndarray:
        out = np.zeros(len(prev), dtype=np.float64)
        out[:] = self.config.slack
        return out

    def step_one(self, prev, action, new, collided, done, success, searching) -> float:
        return self.config.slack

    def reference_step(self, prev, action, new, collided, done, success, searching) -> float:
        return self.config.slack


class SuccessTerm(RewardTerm):
    """``success_reward`` (+5) when Done succeeds (III-D (v)); ``failed_done`` (0, the paper's: a Done that fails
    only ends the episode) when it fails, a deviation from the paper when not 0."""

    name = "success"

    def constants(self):
        return (self.config.success_reward, self.config.failed_done)

    def step(self, prev, action, new, collided, done, success, searching) -> np.ndarray:
        out = np.zeros(len(prev), dtype=np.float64)
        out[(np.asarray(action) == DONE) & ~np.asarray(success, dtype=bool)] = self.config.failed_done
        out[success] = self.config.success_reward
        return out

    def step_one(self, prev, action, new, collided, done, success, searching) -> float:
        if success:
            return self.config.success_reward
        return self.config.failed_done if action == DONE else 0.0

    def reference_step(self, prev, action, new, collided, done, success, searching) -> float:
        if success:
            return self.config.success_reward
        if action == DONE:
            return self.config.failed_done
        return 0.0


class RegretTerm(RewardTerm):
    """A deviation from the paper, off by default (in no variant of the paper; variant ``tsrm-regret``): for a
    movement action taken in the pathfinding stage, ``K_r * (D(s_{t-1}) - D(s_t) - 1)`` with ``K_r = k_regret``,
    ``D(s)`` the shortest number of movement actions (turns and looks included, Done not) from state ``s`` to a
    success state of the target on the state graph: the optimal path length L* of SPL and NSNPL
    (``SceneBank.dist``, :func:`tsnav.sim.paths.distance_fields`; 0 where either end is unreachable).

    ``1 + D(s_t) - D(s_{t-1})`` is the action's *regret*: by how many actions it lengthened the shortest way from
    where the step started (the action itself plus what is left, against what was left): 0 for a step along a
    shortest path, 1 for a step that leaves ``D`` as it was (a look the way does not need, a failed move), 2 for a
    turn the wrong way, more for a MoveAhead away (coming back takes turns). Summed over the pathfinding stage it is ``K_r`` times the actions taken beyond the
    shortest path, ``L - (D(switch) - D(end))``, which NSNPL charges. The paper's distance term is a difference
    of potentials (``K_d`` per pose-graph action of progress), whose sum over the stage does not depend on the
    path: a turn the long way round (six 45-degree turns instead of two) earns what the short way earns and costs
    only the slack, 0.01 per action; with this term each extra action costs ``K_r`` more. Done earns nothing here
    (a wrong Done ends the episode without the success reward; a right one has ``D = 0``)."""

    name = "regret"

    def constants(self):
        return (self.config.k_regret * -1, self.config.k_regret * -2)

    def bind(self, owner) -> None:
        super().bind(owner)
        self.dist = owner.bank.dist

    def step(self, prev, action, new, collided, done, success, searching) -> np.ndarray:
        out = np.zeros(len(new), dtype=np.float64)
        rows = np.flatnonzero(~np.asarray(searching, dtype=bool) & (np.asarray(action) != DONE))
        target = self.owner.target[rows]
        d0 = self.dist[prev[rows], target].astype(np.int64)
        d1 = self.dist[new[rows], target].astype(np.int64)
        ok = (d0 != UNREACHABLE) & (d1 != UNREACHABLE)
        out[rows] = np.where(ok, self.config.k_regret * (d0 - d1 - 1), 0.0)
        return out

    def step_one(self, prev, action, new, collided, done, success, searching) -> float:
        if searching or action == DONE:
            return 0.0
        target = int(self.owner.target[0])
        d0, d1 = int(self.dist[prev, target]), int(self.dist[new, target])
        if d0 == UNREACHABLE or d1 == UNREACHABLE:
            return 0.0
        return self.config.k_regret * (d0 - d1 - 1)

    def bind_reference(self, owner) -> None:
        super().bind_reference(owner)
        self._remaining_cache: dict[int, np.ndarray] = {}

    def reference_reset(self, target, start, searching) -> None:
        owner = self.owner
        if target not in self._remaining_cache:  # a Python BFS over the state graph, once per target
            sc = owner.scene
            success = sc.success_table(owner.protocol, owner.success_distance)[:, target]
            self._remaining_cache[target] = bfs_reference(sc.next_state, success)
        self._remaining = self._remaining_cache[target]

    def reference_step(self, prev, action, new, collided, done, success, searching) -> float:
        if searching or action == DONE:
            return 0.0
        before, after = int(self._remaining[prev]), int(self._remaining[new])
        if before == UNREACHABLE or after == UNREACHABLE:
            return 0.0
        regret = 1 + after - before  # the action taken plus what is left, against what was left
        return -self.config.k_regret * regret


#: Every reward term by name, in the order they are summed and reported.
TERM_CLASSES: dict[str, type[RewardTerm]] = {}
#: Terms each variant switches on (Table II of the paper, and the sparse reward of the lineage).
VARIANT_TERMS: dict[str, tuple[str, ...]] = {}


class _Names(Sequence):
    """A read-only, live view of a registry's names (it follows :func:`register_term` / :func:`register_variant`)."""

    def __init__(self, registry: dict):
        self._registry = registry

    def __getitem__(self, i):
        return tuple(self._registry)[i]

    def __len__(self) -> int:
        return len(self._registry)

    def __contains__(self, name) -> bool:
        return name in self._registry

    def __eq__(self, other) -> bool:
        return tuple(self) == tuple(other) if isinstance(other, (tuple, list, _Names)) else NotImplemented

    def __hash__(self):
        return hash(tuple(self))

    def __add__(self, other):
        return tuple(self) + tuple(other)

    def __repr__(self) -> str:
        return repr(tuple(self))


#: Names of all terms (registration order) and of all variants.
TERMS = _Names(TERM_CLASSES)
VARIANTS = _Names(VARIANT_TERMS)


def register_term(cls: type[RewardTerm]) -> type[RewardTerm]:
    """Add a term class under ``cls.name`` (usable as a class decorator); its name may then appear in variants."""
    if not (isinstance(cls, type) and issubclass(cls, RewardTerm)) or not cls.name:
        raise ValueError(f"{cls!r} is not a RewardTerm subclass with a name")
    if cls.name in TERM_CLASSES and TERM_CLASSES[cls.name] is not cls:
        raise ValueError(f"reward term {cls.name!r} is already registered ({TERM_CLASSES[cls.name].__name__})")
    TERM_CLASSES[cls.name] = cls
    return cls


def register_variant(name: str, terms: Sequence[str]) -> None:
    """Add a reward variant: ``RewardConfig(variant=name)`` then sums ``terms`` (registered term names)."""
    unknown = [t for t in terms if t not in TERM_CLASSES]
    if unknown:
        raise ValueError(
            f"unknown reward term(s) {', '.join(map(repr, unknown))} (registered: {', '.join(TERM_CLASSES)})"
        )
    if name in VARIANT_TERMS and VARIANT_TERMS[name] != tuple(terms):
        raise ValueError(f"reward variant {name!r} is already registered with terms {VARIANT_TERMS[name]}")
    VARIANT_TERMS[name] = tuple(terms)


for _cls in (ExploreTerm, DistanceTerm, CollisionTerm, SlackTerm, SuccessTerm, RegretTerm):
    register_term(_cls)
register_variant("baseline", ("collision", "slack", "success"))
register_variant("explore", ("explore", "collision", "slack", "success"))
register_variant("distance", ("distance", "collision", "slack", "success"))
register_variant("tsrm", ("explore", "distance", "collision", "slack", "success"))
register_variant("sparse", ("slack", "success"))
# deviations from the paper, off unless named
register_variant("tsrm-regret", ("explore", "distance", "collision", "slack", "success", "regret"))
