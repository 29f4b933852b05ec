"""Shared fixtures-as-functions for the sim / eval tests: toy banks and a toy dataset written to disk."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from tsnav.data.toy import toy_scene


def toy_scenes():
    """Three small analytic scenes of two room types with blocked cells and several target categories."""
    a = toy_scene(
        2.0,
        1.5,
        {"Bowl|1": (2.0, 1.5), "Chair|1": (0.0, 0.75), "Vase|1": (1.0, 0.0)},
        blocked=[(1.0, 0.5), (1.0, 0.75), (1.0, 1.0)],
        name="ToyA",
    )
    b = toy_scene(1.5, 1.5, {"Sink|1": (0.75, 1.5), "GarbageCan|1": (0.0, 0.0)}, name="ToyB")
    c = toy_scene(1.75, 1.0, {"Sink|1": (1.75, 0.5)}, blocked=[(0.75, 0.25)], name="ToyC")
    a.meta["room_type"] = "kitchen"
    b.meta["room_type"] = c.meta["room_type"] = "bathroom"
    for s in (a, b, c):
        s.meta["split"] = "test"
    return [a, b, c]


def write_scene_folder(scene, folder: Path, images: int | None = None) -> Path:
    """Write ``scene`` in the lineage layout (graph.json, visible map, scene.json, states.hdf5, COMPLETE) and,
    with ``images`` = side in pixels, images.hdf5 / depth.hdf5 with a per-state pattern."""
    import h5py

    folder.mkdir(parents=True, exist_ok=True)
    keys = scene.keys.tolist()
    src = np.repeat(np.arange(len(keys)), scene.next_state.shape[1])
    dst = scene.next_state.reshape(-1)
    keep = src != dst
    graph = {
        "directed": True,
        "multigraph": False,
        "graph": {},
        "nodes": [{"id": k} for k in keys],
        "links": [{"source": keys[s], "target": keys[t]} for s, t in zip(src[keep], dst[keep])],
    }
    (folder / "graph.json").write_text(json.dumps(graph))
    (folder / "grid.json").write_text(
        json.dumps(
            [{"x": float(x), "y": 0.9, "z": float(z)} for x, z in sorted(set(zip(scene.x.tolist(), scene.z.tolist())))]
        )
    )
    # as the lineage's maps: objects seen from no state are not listed
    vis = {
        str(o): [keys[s] for s in np.flatnonzero(scene.visible[:, j])]
        for j, o in enumerate(scene.object_ids)
        if scene.visible[:, j].any()
    }
    (folder / "visible_object_map_1.5.json").write_text(json.dumps(vis))
    meta = dict(scene.meta)
    meta["floor"] = [p.tolist() for p in scene.floor]
    meta["image_size"] = images or scene.image_size
    (folder / "scene.json").write_text(json.dumps(meta))
    with h5py.File(folder / "states.hdf5", "w") as f:
        f["keys"] = np.array(keys, dtype="S")
        f["object_ids"] = np.array(scene.object_ids.tolist(), dtype="S")
        f["distance"] = scene.distance
        f["pixels"] = scene.pixels
        f["boxes"] = scene.boxes
        f.attrs["image_size"] = images or scene.image_size
    if images:
        with h5py.File(folder / "images.hdf5", "w") as fi, h5py.File(folder / "depth.hdf5", "w") as fd:
            for i, k in enumerate(keys):
                fi[k] = np.full((images, images, 3), i % 251, dtype=np.uint8)
                fd[k] = np.full((images, images), 0.5 + (i % 7), dtype=np.float32)
    (folder / "COMPLETE").write_text("")
    return folder


def write_toy_dataset(root: Path, images: int | None = None) -> Path:
    """The :func:`toy_scenes` as a dataset root (split ``test``)."""
    root.mkdir(parents=True, exist_ok=True)
    for s in toy_scenes():
        write_scene_folder(s, root / s.name, images)
    return root


def oracle_factory(bank, seed=0, c_target=None):
    """A ``module:factory`` policy for testing the learned-agent hook of ``tsnav eval``."""
    from tsnav.eval.policies import OraclePolicy

    return OraclePolicy(bank)


class StagedReward:
    """A stage reward (``uses_stage``, e.g. the TSRM reward) stepped outside an env the way
    :class:`~tsnav.sim.batch.BatchEnv` steps it: one :class:`~tsnav.sim.stage.StageSwitch` (over ``confidence``,
    default the bank's rule) reset before the reward, its ``searching`` mask handed in, updated after each
    step with the same step and movement counters. Exposes the switch's ``stage`` / ``switch_step`` and the
    reward's other attributes."""

    def __init__(self, reward, confidence=None):
        from tsnav.sim.stage import StageSwitch

        self.reward = reward
        self.switch = StageSwitch(reward.bank, confidence=confidence)
        self.steps = np.zeros(0, dtype=np.int64)
        self.path_length = np.zeros(0, dtype=np.int64)

    def reset(self, mask, scene_idx, target, start_state):
        mask = np.asarray(mask, dtype=bool)
        if len(mask) != len(self.steps):
            self.steps = np.zeros(len(mask), dtype=np.int64)
            self.path_length = np.zeros(len(mask), dtype=np.int64)
        self.steps[mask] = 0
        self.path_length[mask] = 0
        self.switch.reset(mask, start_state, target)
        self.reward.reset(mask, scene_idx, target, start_state, searching=self.switch.searching)

    def step(self, prev_state, action, new_state, collided, done, success):
        from tsnav.constants import DONE

        self.steps += 1
        self.path_length += np.asarray(action) != DONE
        out = self.reward.step(prev_state, action, new_state, collided, done, success, searching=self.switch.searching)
        self.switch.update(new_state, self.steps, self.path_length)
        return out

    @property
    def stage(self):
        return self.switch.stage

    @property
    def switch_step(self):
        return self.switch.switch_step

    def __getattr__(self, name):
        return getattr(self.reward, name)
