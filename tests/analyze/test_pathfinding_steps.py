"""tsnav analyze pathfinding-steps: the classes of the steps after the switch equal the slow reference's on real
evaluations of the tiny world under both protocols, the waste adds up to the walk less the drop of d, the classes
follow their definition on a hand-made graph, and bad folders get one line."""

import json

import numpy as np
import pytest
from script_helpers import load_analysis

from tsnav.cli import main
from tsnav.constants import DONE, LOOK_DOWN, MOVE_AHEAD, ROTATE_LEFT, ROTATE_RIGHT
from tsnav.data.reader import load_scene
from tsnav.eval.runner import read_trajectories
from tsnav.sim.paths import UNREACHABLE


@pytest.fixture(scope="module")
def mod():
    return load_analysis("pathfinding_steps")


def _evaluate(world, folder, policy: str, protocol: str):
    eps, ev = folder / f"eps_{protocol}.json", folder / f"eval_{policy}_{protocol}"
    args = ["episodes", "--data", str(world), "--split", "test", "--per-room-type", "6", "--protocol", protocol]
    assert main([*args, "--out", str(eps)]) == 0
    args = ["eval", "--data", str(world), "--episodes", str(eps), "--policy", policy, "--protocol", protocol]
    assert main([*args, "--out", str(ev)]) == 0
    return ev


@pytest.mark.parametrize("protocol", ["paper", "lineage"])
def test_fast_equals_reference_on_real_evaluations(mod, tiny_world, tmp_path, protocol):
    for policy in ("random", "explorer"):
        ev = _evaluate(tiny_world, tmp_path, policy, protocol)
        traj = read_trajectories(ev / "trajectories.jsonl")
        fast = mod.step_classes(tiny_world, traj, protocol)
        ref = mod.step_classes_reference(tiny_world, traj, protocol)
        assert fast == ref
        assert fast["episodes"] == sum(t.switch_frame >= 0 for t in traj) > 0
        steps = sum(n for v in fast["counts"].values() for row in v.values() for n in row.values())
        assert steps > 0


def test_waste_is_the_walk_less_the_drop_of_d(mod, tiny_world, tmp_path):
    ev = _evaluate(tiny_world, tmp_path, "random", "paper")
    traj = [t for t in read_trajectories(ev / "trajectories.jsonl") if t.switch_frame >= 0]
    total_pose, total_drop, skipped = 0, 0, 0
    for t in traj:
        scene = load_scene(tiny_world / t.scene)
        d, _ = mod.scene_tables(scene, "paper", 1.0)
        c = scene.class_set.index[t.target]
        ids = scene.indices(t.keys)
        for i in range(t.switch_frame, len(t.actions)):
            a, d0, d1 = t.actions[i], d[ids[i], c], d[ids[i + 1], c]
            if a == DONE:
                continue
            if UNREACHABLE in (d0, d1):
                skipped += 1
            elif a in (MOVE_AHEAD, ROTATE_LEFT, ROTATE_RIGHT):
                total_pose += 1
                total_drop += int(d0) - int(d1)
    res = mod.step_classes(tiny_world, traj, "paper")
    wasted = res["wasted"]["in view"] + res["wasted"]["out of view"]
    assert wasted == total_pose - total_drop and res["skipped"] == skipped
    pose = sum(
        n for v in res["counts"].values() for r, row in v.items() if r != "LookUp/LookDown" for n in row.values()
    )
    assert pose == total_pose


def test_classes_by_hand(mod):
    d0 = np.array([3, 3, 3, 3, 3, 3, UNREACHABLE, 2])
    d1 = np.array([2, 3, 3, 7, 3, 3, 4, 2])
    acts = np.array([MOVE_AHEAD, MOVE_AHEAD, ROTATE_RIGHT, ROTATE_LEFT, LOOK_DOWN, MOVE_AHEAD, MOVE_AHEAD, DONE])
    moved = np.array([True, True, True, True, True, False, True, False])
    want = ["closer", "no progress", "no progress", "farther", "look", "blocked", None, None]
    got = mod.classify(d0, d1, acts, moved)
    assert [mod.CLASSES[k] if k >= 0 else None for k in got] == want


def test_command_and_refusals(mod, tiny_world, tmp_path, capsys):
    ev = _evaluate(tiny_world, tmp_path, "explorer", "paper")
    out = tmp_path / "p.json"
    capsys.readouterr()
    assert main(["analyze", "pathfinding-steps", f"explorer={ev}", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    res = json.loads(out.read_text())["results"][0]
    assert res["label"] == "explorer" and res["protocol"] == "paper"
    assert f"explorer: {res['episodes']} switched episodes" in printed and "wasted" in printed
    # the scripted explorer walks a shortest path once switched, the random policy does not: it wastes more per step
    rnd = mod.step_classes(
        tiny_world,
        read_trajectories(_evaluate(tiny_world, tmp_path, "random", "paper") / "trajectories.jsonl"),
        "paper",
    )

    def share(r):
        pose = sum(
            n for v in r["counts"].values() for k, row in v.items() if k != "LookUp/LookDown" for n in row.values()
        )
        return (r["wasted"]["in view"] + r["wasted"]["out of view"]) / pose

    assert share(res) < share(rnd)
    assert main(["analyze", "pathfinding-steps", str(tmp_path / "none")]) == 2
    assert "no trajectories.jsonl" in capsys.readouterr().err
    meta = json.loads((ev / "metrics.json").read_text())
    meta["data"] = str(tmp_path / "gone")
    (ev / "metrics.json").write_text(json.dumps(meta))
    assert main(["analyze", "pathfinding-steps", str(ev)]) == 2
    assert "give --data" in capsys.readouterr().err
    assert main(["analyze", "pathfinding-steps", str(ev), "--data", str(tiny_world)]) == 0
