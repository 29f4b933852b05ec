"""The live exporter against a real ai2thor 5 event (issue 13, part 4): its reading of ``agent``, ``objects``,
visibility and ``sceneBounds`` from the metadata of FloorPlan29_physics after reset, and the stand-in
controller replaying that metadata's shape."""

from __future__ import annotations

import json

import numpy as np
import pytest

from thor_standin import GRID_Y, StandInController, real_event_metadata
from tsnav.constants import CAMERA_HEIGHT, TARGET_CATEGORIES
from tsnav.data.thor_live import LiveConfig, _aabb, _object_table, agent_pose, scene_bounds, visible_object_ids


class _Event:
    def __init__(self, metadata):
        self.metadata = metadata


@pytest.fixture(scope="module")
def real():
    return real_event_metadata()


def test_fixture_is_the_real_event(real):
    assert real["sceneName"] == "FloorPlan29_physics" and real["lastAction"] == "Initialize"
    assert real["screenWidth"] == real["screenHeight"] == 300 and real["fov"] == 90.0
    assert len(real["objects"]) == 32 and all(o["objectId"].count("|") == 3 for o in real["objects"])


def test_agent_pose_of_the_real_event(real):
    # position (1.25, 0.93, -0.5), rotation y 270, cameraHorizon -0.0 (Unity's negative zero)
    x, y, z, rot, hor = agent_pose(real)
    assert (x, z, rot, hor) == (1.25, -0.5, 270, 0) and y == pytest.approx(0.9318, abs=1e-4)
    assert agent_pose({"agent": {"position": {"x": 0.0, "z": 1.0}}}) is None  # no rotation / horizon
    odd = {
        **real,
        "agent": {**real["agent"], "rotation": {"x": 0.0, "y": 359.9999, "z": 0.0}, "cameraHorizon": 29.99998},
    }
    assert agent_pose(odd)[3:] == (0, 30)


def test_object_table_and_boxes_of_the_real_event(real):
    table = _object_table(_Event(real), LiveConfig())
    expect = sorted(o["objectId"] for o in real["objects"] if o["objectType"] in TARGET_CATEGORIES)
    assert [o["objectId"] for o in table] == expect and len(table) == 20
    assert {o["objectType"] for o in table} == {
        "Bowl",
        "Chair",
        "CoffeeMachine",
        "Fridge",
        "GarbageCan",
        "Kettle",
        "LightSwitch",
        "Microwave",
        "Pan",
        "Plate",
        "Pot",
        "Sink",
        "StoveBurner",
        "Toaster",
    }
    everything = _object_table(_Event(real), LiveConfig(targets_only=False))
    assert len(everything) == 32
    fridge = next(o for o in real["objects"] if o["objectType"] == "Fridge")
    base, size = _aabb(fridge)
    box = fridge["axisAlignedBoundingBox"]
    assert size == [box["size"][a] for a in "xyz"]
    assert base == [box["center"]["x"], box["center"]["y"] - box["size"]["y"] / 2, box["center"]["z"]]
    # the box's corner points bound the same box
    corners = np.array(box["cornerPoints"])
    assert np.allclose(corners.min(0), [base[0] - size[0] / 2, base[1], base[2] - size[2] / 2], atol=1e-5)


def test_visibility_of_the_real_event(real):
    vis = visible_object_ids(real)
    assert len(vis) == 12 + 4  # 12 non-targets and 4 targets are flagged visible at reset
    targets = {o for o in vis if o.split("|")[0] in TARGET_CATEGORIES}
    assert sorted(o.split("|")[0] for o in targets) == ["Kettle", "StoveBurner", "StoveBurner", "StoveBurner"]
    assert all(o["visible"] == (o["objectId"] in vis) for o in real["objects"])


def test_scene_bounds_of_the_real_event(real):
    b = scene_bounds(real)
    assert b["center"] == real["sceneBounds"]["center"] and b["size"] == real["sceneBounds"]["size"]
    assert len(b["cornerPoints"]) == 8
    c = np.array(b["cornerPoints"])
    assert np.allclose((c.max(0) - c.min(0)), [b["size"][a] for a in "xyz"], atol=1e-4)
    assert scene_bounds({}) is None and scene_bounds({"sceneBounds": {"center": {"x": 1}}}) is None


def test_standin_replays_the_real_metadata_shape(real, tiny_world):
    ctrl = StandInController(tiny_world / "FloorPlan21", width=32)
    ev = ctrl.reset("FloorPlan21")
    m = ev.metadata
    assert set(m) == set(real)
    assert set(m["agent"]) == set(real["agent"]) and set(m["sceneBounds"]) == set(real["sceneBounds"])
    assert all(set(o) == set(real["objects"][0]) for o in m["objects"])
    # the values the exporter reads: this scene's, in the real event's types and units
    scene = ctrl.scene
    assert m["sceneName"] == "FloorPlan21" and m["lastAction"] == "Reset" and m["lastActionSuccess"] is True
    assert m["screenWidth"] == m["screenHeight"] == 32 and m["fov"] == real["fov"] == 90.0
    pos, rot = m["agent"]["position"], m["agent"]["rotation"]
    assert all(type(pos[a]) is float and type(rot[a]) is float for a in "xyz")
    assert type(m["agent"]["cameraHorizon"]) is float
    start = ctrl.grid[0]
    assert (pos["x"], pos["z"], rot["y"], m["agent"]["cameraHorizon"]) == (start["x"], start["z"], 0.0, 0.0)
    assert (m["cameraPosition"]["x"], m["cameraPosition"]["z"]) == (pos["x"], pos["z"])
    assert m["cameraPosition"]["y"] - pos["y"] == pytest.approx(CAMERA_HEIGHT - GRID_Y)  # camera above the body centre
    targets = [o for o in m["objects"] if o["objectType"] in TARGET_CATEGORIES]
    assert sorted(o["objectId"] for o in targets) == sorted(scene.object_ids.tolist())
    for o in m["objects"]:
        kind, *coords = o["objectId"].split("|")
        assert kind == o["objectType"] and type(o["visible"]) is bool and type(o["distance"]) is float
        assert np.allclose([float(c) for c in coords], [o["position"][a] for a in "xyz"], atol=0.005)
        box = o["axisAlignedBoundingBox"]
        c, h = np.array([box["center"][a] for a in "xyz"]), np.array([box["size"][a] for a in "xyz"]) / 2
        corners = np.array(box["cornerPoints"])
        assert corners.shape == (8, 3) and np.allclose(corners.min(0), c - h) and np.allclose(corners.max(0), c + h)
        cam = np.array([m["cameraPosition"][a] for a in "xyz"])
        assert o["distance"] == pytest.approx(float(np.linalg.norm(cam - [o["position"][a] for a in "xyz"])))
    for k in ("fov", "screenWidth", "lastActionSuccess", "cameraPosition", "agent", "sceneBounds"):
        assert type(m[k]) is type(real[k]), k
    for k, v in real["objects"][0].items():
        if k not in ("parentReceptacles", "receptacleObjectIds", "fillLiquid", "controlledObjects"):
            assert type(m["objects"][0][k]) is type(v), k
    # the exporter reads the stand-in's events with the same functions as the real one
    x, _, z, rot, hor = agent_pose(m)
    assert f"{x:.2f}|{z:.2f}|{rot}|{hor}" in set(ctrl.scene.keys.tolist())
    assert scene_bounds(m) is not None and visible_object_ids(m) <= {o["objectId"] for o in m["objects"]}


def test_live_export_writes_the_scene_bounds_it_read(tiny_world, tmp_path):
    from tsnav.data.thor_live import export_live

    ctrl = StandInController(tiny_world / "FloorPlan21", width=32)
    export_live(ctrl, "FloorPlan21", tmp_path, size=32)
    meta = json.loads((tmp_path / "FloorPlan21" / "scene.json").read_text())
    assert meta["scene_bounds"] == scene_bounds(ctrl.reset("FloorPlan21").metadata)
    assert set(meta["scene_bounds"]) == {"center", "size", "cornerPoints"}
