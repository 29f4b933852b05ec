"""A slow, obviously-correct controller written like the lineage's offline controller (one episode at a
time, string state keys, dict and networkx graph look-ups per step). It is the reference that
:class:`~tsnav.sim.batch.BatchEnv` is tested against, and the baseline of ``bench/bench_sim.py``.
"""

from __future__ import annotations

import math

import networkx as nx

from ..constants import (
    ACTIONS,
    GRID_SIZE,
    HORIZONS,
    ROTATE_STEP,
    SUCCESS_DISTANCE,
    parse_state_key,
    state_key,
)
from ..data.reader import Scene


def scene_graph(scene: Scene) -> nx.DiGraph:
    """The scene's state graph as a networkx DiGraph over state keys (the lineage's ``graph.json``)."""
    g = nx.DiGraph()
    keys = scene.keys.tolist()
    g.add_nodes_from(keys)
    for s, row in enumerate(scene.next_state.tolist()):
        for t in row:
            if t != s:
                g.add_edge(keys[s], keys[t])
    return g


class ReferenceController:
    """One episode at a time over a scene, per-step dict / graph look-ups.

    ``success_objects[key]`` maps a state key to {category: True} for target categories in view and within
    the success distance (``protocol="lineage"``: listed in the visibility map); the next key of an action is computed from the geometry of the current key and
    accepted when it is a graph neighbour (a failed action leaves the state unchanged).
    """

    def __init__(
        self,
        scene: Scene,
        success_distance: float = SUCCESS_DISTANCE,
        graph: nx.DiGraph | None = None,
        protocol: str = "paper",
    ):
        self.scene = scene
        self.graph = scene_graph(scene) if graph is None else graph
        seen = scene.visible_at_any_range()
        no_distances = all(math.isnan(v) for v in scene.distance.reshape(-1).tolist())
        self.success_objects: dict[str, dict[str, bool]] = {}
        for s, key in enumerate(scene.keys.tolist()):
            d: dict[str, bool] = {}
            for o, cat in enumerate(scene.object_category.tolist()):
                if cat < 0:
                    continue
                dist = scene.distance[s, o]
                if no_distances or protocol == "lineage":  # the 1.5 m visibility map decides (tsnav.protocol)
                    ok = bool(scene.visible[s, o])
                else:
                    ok = bool(seen[s, o]) and bool(dist <= success_distance)
                if ok:
                    d[scene.class_set.categories[cat]] = True
            self.success_objects[key] = d
        self.state = ""
        self.target = ""
        self.steps = 0
        self.path_length = 0
        self.done = False

    def reset(self, start_key: str, target: str) -> str:
        self.state, self.target = start_key, target
        self.steps, self.path_length, self.done = 0, 0, False
        return self.state

    def _next_key(self, action: str) -> str:
        x, z, r, h = parse_state_key(self.state)
        if action == "MoveAhead":
            rad = math.radians(r)
            return state_key(x + round(math.sin(rad)) * GRID_SIZE, z + round(math.cos(rad)) * GRID_SIZE, r, h)
        if action == "RotateLeft":
            return state_key(x, z, (r - ROTATE_STEP) % 360, h)
        if action == "RotateRight":
            return state_key(x, z, (r + ROTATE_STEP) % 360, h)
        if action == "LookDown":
            return state_key(x, z, r, HORIZONS[1] if h == HORIZONS[0] else h + 30)
        if action == "LookUp":
            return state_key(x, z, r, HORIZONS[0] if h == HORIZONS[1] else h - 30)
        raise ValueError(f"unknown action {action!r}")

    def step(self, action: int, max_steps: int = 100) -> dict:
        """Apply one action id; returns a dict with the new key and the episode flags."""
        name = ACTIONS[action]
        self.steps += 1
        collided = failed = terminated = success = False
        if name == "Done":
            terminated = True
            success = self.success_objects[self.state].get(self.target, False)
        else:
            self.path_length += 1
            nxt = self._next_key(name)
            if self.graph.has_edge(self.state, nxt):
                self.state = nxt
            else:  # lastActionSuccess False; a collision only for MoveAhead (see sim.batch)
                failed = True
                collided = name == "MoveAhead"
        truncated = (not terminated) and self.steps >= max_steps
        self.done = terminated or truncated
        return {
            "state": self.state,
            "collided": collided,
            "failed": failed,
            "terminated": terminated,
            "truncated": truncated,
            "success": success,
            "steps": self.steps,
            "path_length": self.path_length,
        }
