"""The lineage's conventions (issue 13, part 1): action ids, target sets, object ids, the visibility map's
objects, episode starts at both horizons, and old runs / trajectories written in the former action order."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch

from tsnav.constants import (
    ACTION_ORDER,
    ACTIONS,
    DONE,
    LOOK_DOWN,
    LOOK_UP,
    MOVE_AHEAD,
    OLD_ACTION_ORDER,
    ROOM_TARGETS,
    ROTATE_LEFT,
    ROTATE_RIGHT,
    TARGET_CATEGORIES,
    action_permutation,
    object_id,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: The lineage's object id: sign, two or more integer digits, two decimals.
THOR_ID = re.compile(r"^[A-Za-z]+\|[+-]\d{2,}\.\d\d\|[+-]\d{2,}\.\d\d\|[+-]\d{2,}\.\d\d$")


def test_action_ids_are_the_lineages():
    # IOM utils/action_util.py
    assert ACTIONS == ("MoveAhead", "RotateLeft", "RotateRight", "LookUp", "LookDown", "Done")
    assert (MOVE_AHEAD, ROTATE_LEFT, ROTATE_RIGHT, LOOK_UP, LOOK_DOWN, DONE) == (0, 1, 2, 3, 4, 5)
    assert action_permutation(ACTION_ORDER).tolist() == [0, 1, 2, 3, 4, 5]
    assert action_permutation(OLD_ACTION_ORDER).tolist() == [0, 1, 2, 4, 3, 5]
    with pytest.raises(ValueError, match="unknown action order"):
        action_permutation("MoveAhead,Jump")


def test_look_actions_move_the_camera_the_right_way(tiny_scenes):
    s = tiny_scenes[0]
    level = np.flatnonzero(s.horizon == 0)[0]
    down = s.next_state[level, LOOK_DOWN]
    assert s.horizon[down] == 30 and s.next_state[down, LOOK_UP] == level
    assert s.next_state[level, LOOK_UP] == level  # already level: the action fails


def test_room_targets_as_the_lineages_test_splits():
    assert set(ROOM_TARGETS["kitchen"]) == {
        "Bowl",
        "CellPhone",
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
    assert set(ROOM_TARGETS["living_room"]) == {
        "Book",
        "CellPhone",
        "Chair",
        "DeskLamp",
        "FloorLamp",
        "GarbageCan",
        "Laptop",
        "LightSwitch",
        "RemoteControl",
        "Television",
    }
    assert set(ROOM_TARGETS["bedroom"]) == {
        "AlarmClock",
        "Book",
        "CellPhone",
        "Chair",
        "DeskLamp",
        "GarbageCan",
        "Laptop",
        "LightSwitch",
    }
    assert set(ROOM_TARGETS["bathroom"]) == {"GarbageCan", "LightSwitch", "Sink"}
    assert set().union(*ROOM_TARGETS.values()) == set(TARGET_CATEGORIES)


def test_object_id_format():
    assert object_id("Plate", 0.52, 0.92, 3.73) == "Plate|+00.52|+00.92|+03.73"
    assert object_id("Fridge", -2.1, 0.0, 1.07) == "Fridge|-02.10|+00.00|+01.07"
    assert object_id("Sofa", -10.25, 12.5, -0.004) == "Sofa|-10.25|+12.50|+00.00"  # no negative zero
    assert object_id("Bed", 100.456, -0.999, 9.996) == "Bed|+100.46|-01.00|+10.00"
    assert THOR_ID.match(object_id("Pot", -0.5, 1, 0.25))


def test_procedural_world_places_cellphones_in_kitchens_and_living_rooms():
    from tsnav.world.house import generate

    for base in (1, 201):  # kitchens, living rooms
        specs = [generate(f"FloorPlan{base + i}") for i in range(12)]
        phones = sum(any(o.objectType == "CellPhone" for o in s.objects) for s in specs)
        assert phones >= 6, f"only {phones} of 12 rooms from FloorPlan{base} have a CellPhone"
        for s in specs:
            allowed = set(ROOM_TARGETS[s.room_type])
            assert {o.objectType for o in s.objects} <= allowed
            assert all(THOR_ID.match(o.objectId) for o in s.objects), [o.objectId for o in s.objects][:3]


def test_visible_object_map_lists_no_object_without_a_state(tiny_world):
    from tsnav.data.reader import list_scenes

    listed = empty = 0
    for d in list_scenes(tiny_world):
        vis = json.loads((d / "visible_object_map_1.5.json").read_text())
        scene = json.loads((d / "scene.json").read_text())
        listed += len(vis)
        empty += sum(not v for v in vis.values())
        assert set(vis) <= {o["objectId"] for o in scene["objects"]}
        assert all(THOR_ID.match(o) for o in vis)
    assert listed > 0 and empty == 0


def test_visible_object_map_helper_leaves_out_unseen_objects():
    from tsnav.data.lineage import visible_object_map

    vis = np.array([[True, False, False], [True, False, True]])
    assert visible_object_map(["A|1|2|3", "B|1|2|3", "C|1|2|3"], ["k0", "k1"], vis) == {
        "A|1|2|3": ["k0", "k1"],
        "C|1|2|3": ["k1"],
    }


def test_fixed_episodes_start_at_both_horizons_and_every_rotation(tiny_world):
    from tsnav.sim.batch import SceneBank
    from tsnav.sim.episodes import episodes_to_arrays, make_episodes

    bank = SceneBank.from_root(tiny_world, None)
    eps = make_episodes(bank, per_room_type=200, seed=0)
    hor = np.array([int(e.start.split("|")[3]) for e in eps])
    rot = {int(e.start.split("|")[2]) for e in eps}
    assert set(hor.tolist()) == {0, 30} and 0.35 < (hor == 30).mean() < 0.65, (hor == 30).mean()
    assert rot == {0, 45, 90, 135, 180, 225, 270, 315}
    # the stored L* is the BFS length from the start state itself (horizon included), and no start succeeds
    _, target, start = episodes_to_arrays(bank, eps, check=True)
    assert not bank.success[start, target].any()
    up = np.array([h == 30 for h in hor])
    assert (bank.dist[start[up], target[up]] >= 1).all()


def _tiny_model():
    from tsnav.agent.model import ActorCritic, agent_config

    torch.manual_seed(0)
    return ActorCritic(agent_config("cpu"), (3, 2, 2), 3)


def test_old_checkpoint_is_converted_on_load(tmp_path, capsys):
    from safetensors.torch import load_file, save_file

    from tsnav.rl.checkpoint import load_checkpoint, save_checkpoint

    model = _tiny_model()
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    model.actor.weight.sum().backward()
    opt.step()
    path = save_checkpoint(tmp_path / "run", {"update": 1}, model, opt)
    # the same checkpoint as the old order wrote it: rows 3 and 4 swapped, no action_order
    swap = [0, 1, 2, 4, 3, 5]
    for name in ("model.safetensors", "optimizer.safetensors"):
        sd = load_file(str(path / name))
        from safetensors import safe_open

        with safe_open(str(path / name), framework="pt") as f:
            meta = dict(f.metadata() or {})
        meta.pop("action_order", None)
        for k in list(sd):
            if k.split("::")[0] in ("actor.weight", "actor.bias", "action_embed.weight") and sd[k].ndim:
                v = sd[k].clone()
                v[:6] = sd[k][swap]
                sd[k] = v
        save_file(sd, str(path / name), metadata=meta or None)
    fresh = _tiny_model()
    with torch.no_grad():
        for p in fresh.parameters():
            p.zero_()
    opt2 = torch.optim.Adam(fresh.parameters(), lr=1e-3)
    load_checkpoint(path, fresh, opt2)
    assert (
        "trained with the action order MoveAhead,RotateLeft,RotateRight,LookDown,LookUp,Done" in capsys.readouterr().err
    )
    for (n, a), b in zip(model.state_dict().items(), fresh.state_dict().values()):
        assert torch.equal(a, b), n
    s1, s2 = opt.state_dict()["state"], opt2.state_dict()["state"]
    for i in s1:
        assert torch.equal(s1[i]["exp_avg"], s2[i]["exp_avg"])
    # a checkpoint of the current order loads silently and exactly
    path2 = save_checkpoint(tmp_path / "run2", {"update": 1}, model, opt)
    again = _tiny_model()
    load_checkpoint(path2, again)
    assert capsys.readouterr().err == ""
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), again.state_dict().values()))


def test_old_trajectories_are_converted_on_read(tmp_path):
    from tsnav.eval.runner import Trajectory, read_trajectories, write_trajectories

    t = Trajectory(
        episode=0, scene="FloorPlan1", target="Bowl", keys=["a", "b", "c", "d"], actions=[LOOK_DOWN, LOOK_UP, DONE]
    )
    write_trajectories(tmp_path / "new.jsonl", [t])
    assert read_trajectories(tmp_path / "new.jsonl") == [t]
    old = json.loads(t.to_json())
    old.pop("action_order")
    old["actions"] = [3, 4, 5]  # LookDown, LookUp, Done in the old order
    (tmp_path / "old.jsonl").write_text(json.dumps(old) + "\n")
    assert read_trajectories(tmp_path / "old.jsonl")[0].actions == [LOOK_DOWN, LOOK_UP, DONE]
