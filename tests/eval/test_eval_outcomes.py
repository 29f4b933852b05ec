"""How evaluation episodes end (`tsnav.eval.outcomes`): each ending x switch cell on hand-made episodes, and the
figures of a real evaluation folder agree with its records and metrics."""

import json

import pytest

from tsnav.cli import main
from tsnav.constants import DONE, MOVE_AHEAD, ROTATE_LEFT, ROTATE_RIGHT
from tsnav.eval.outcomes import format_outcomes, outcome_summary
from tsnav.eval.runner import Trajectory, read_trajectories
from tsnav.metrics import EpisodeRecord, read_records


def episode(i, target, success, switched, actions):
    rec = EpisodeRecord(
        success=success,
        path_length=len(actions),
        optimal_length=1,
        entered_pathfinding=switched,
        target=target,
        episode=i,
        steps=len(actions),
    )
    traj = Trajectory(
        episode=i, scene="S", target=target, keys=["k"] * (len(actions) + 1), actions=actions, success=success
    )
    return rec, traj


def test_each_ending_and_switch():
    eps = [
        episode(0, "Fridge", True, True, [MOVE_AHEAD, DONE]),
        episode(1, "Fridge", False, True, [MOVE_AHEAD, DONE]),  # wrong Done after the switch
        episode(2, "CellPhone", False, False, [ROTATE_RIGHT] * 5),  # step limit, never switched
        episode(3, "CellPhone", False, False, [ROTATE_RIGHT, DONE]),  # wrong Done, never switched
        episode(4, "CellPhone", True, False, [MOVE_AHEAD, MOVE_AHEAD, DONE]),
        episode(5, "Fridge", False, True, [ROTATE_LEFT] * 4),
    ]  # step limit after the switch
    s = outcome_summary([e[0] for e in eps], [e[1] for e in eps])
    assert s["counts"] == {
        "success, switched": 1,
        "success, never switched": 1,
        "wrong Done, switched": 1,
        "wrong Done, never switched": 1,
        "step limit, switched": 1,
        "step limit, never switched": 1,
    }
    assert s["switched"] == 3 and s["success_if_switched"] == pytest.approx(1 / 3)
    assert s["success_if_never_switched"] == pytest.approx(1 / 3)
    assert s["per_target"]["Fridge"] == {"episodes": 3, "SR": pytest.approx(1 / 3), "switch_rate": 1.0}
    assert s["per_target"]["CellPhone"] == {"episodes": 3, "SR": pytest.approx(1 / 3), "switch_rate": 0.0}
    n_actions = 2 + 2 + 5 + 2 + 3 + 4
    assert s["action_shares"]["RotateRight"] == pytest.approx(6 / n_actions)
    assert s["action_shares"]["Done"] == pytest.approx(4 / n_actions) and s["action_shares"]["LookUp"] == 0.0
    text = format_outcomes(s)
    assert "wrong Done, never switched" in text and "CellPhone" in text and "33.3 %" in text
    assert s["failed_after_a_success_state"] is None  # trajectories without success_frame (older files)
    assert "Done there would have succeeded" not in text
    with pytest.raises(ValueError, match="6 records but 5 trajectories"):
        outcome_summary([e[0] for e in eps], [e[1] for e in eps][:5])
    with pytest.raises(ValueError, match="disagree"):
        outcome_summary([e[0] for e in eps], [eps[1][1]] + [e[1] for e in eps][1:])


def test_failures_that_passed_a_success_state():
    eps = [
        episode(0, "Fridge", True, True, [MOVE_AHEAD, DONE]),
        episode(1, "Fridge", False, True, [MOVE_AHEAD, DONE]),  # wrong Done after passing a success state
        episode(2, "Fridge", False, True, [ROTATE_LEFT] * 4),  # step limit, never in a success state
        episode(3, "CellPhone", False, False, [ROTATE_RIGHT] * 3),
    ]  # step limit after passing one
    for (_, t), frame in zip(eps, (1, 1, -1, 2)):
        t.success_frame = frame
    s = outcome_summary([e[0] for e in eps], [e[1] for e in eps])
    assert s["failed_after_a_success_state"] == {"switched": 1, "never switched": 1}
    assert "Done there would have succeeded): 1 of 2 switched failures, 1 of 1 never-switched ones" in format_outcomes(
        s
    )


def test_eval_folder_outcomes_agree_with_records(tiny_world, tmp_path, capsys):
    eps = tmp_path / "eps.json"
    assert (
        main(["episodes", "--data", str(tiny_world), "--split", "test", "--per-room-type", "8", "--out", str(eps)]) == 0
    )
    out = tmp_path / "eval"
    assert (
        main(
            [
                "eval",
                "--data",
                str(tiny_world),
                "--episodes",
                str(eps),
                "--policy",
                "random",
                "--max-steps",
                "30",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert "how the" in capsys.readouterr().out
    s = json.loads((out / "outcomes.json").read_text())
    records = read_records(out / "records.jsonl")
    trajs = read_trajectories(out / "trajectories.jsonl")
    m = json.loads((out / "metrics.json").read_text())["metrics"]["ALL"]
    n = len(records)
    assert s["episodes"] == n == m["episodes"] and sum(s["counts"].values()) == n
    assert s["counts"]["success, switched"] + s["counts"]["success, never switched"] == round(m["SR"] * n)
    assert s["switched"] == sum(r.entered_pathfinding for r in records)
    # step limit exactly when the episode used all 30 steps without a final Done
    limit = sum(1 for t in trajs if len(t.actions) == 30 and t.actions[-1] != DONE)
    assert s["counts"]["step limit, switched"] + s["counts"]["step limit, never switched"] == limit
    assert sum(s["action_shares"].values()) == pytest.approx(1.0)
    # success_frame against a slow reference, on this folder (random: never in a success state here) and on the
    # scripted explorer's (always gets there)
    out2 = tmp_path / "eval_explorer"
    assert (
        main(
            [
                "eval",
                "--data",
                str(tiny_world),
                "--episodes",
                str(eps),
                "--policy",
                "explorer",
                "--max-steps",
                "30",
                "--out",
                str(out2),
            ]
        )
        == 0
    )
    frames = check_success_frames(tiny_world, out) + check_success_frames(tiny_world, out2)
    assert {f >= 0 for f in frames} == {True, False}  # both cases exercised
    assert any(t.switch_distance > 0 for t in read_trajectories(out2 / "trajectories.jsonl"))


def bfs_to_success(scene, start, ok) -> int:
    """Fewest actions other than Done from state ``start`` to a state where ``ok``, by breadth-first search over
    the scene's transition table; -1 when none can be reached."""
    from collections import deque

    from tsnav.constants import ACTIONS

    moves = [i for i, a in enumerate(ACTIONS) if i != DONE]
    seen, queue = {start: 0}, deque([start])
    while queue:
        s = queue.popleft()
        if ok[s]:
            return seen[s]
        for a in moves:
            n = int(scene.next_state[s, a])
            if n not in seen:
                seen[n] = seen[s] + 1
                queue.append(n)
    return -1


def check_success_frames(world, out) -> list[int]:
    """Each trajectory's success_frame equals the first of its keys that the scene lists as a success state for
    its target; the outcome summary's count of failures after a success state follows. Returns the frames."""
    from tsnav.constants import CATEGORY_INDEX, SUCCESS_DISTANCE
    from tsnav.data.reader import load_scene

    s = json.loads((out / "outcomes.json").read_text())
    scenes, missed, frames = {}, {"switched": 0, "never switched": 0}, []
    for r, t in zip(read_records(out / "records.jsonl"), read_trajectories(out / "trajectories.jsonl")):
        sc = scenes.setdefault(t.scene, load_scene(world / t.scene))
        ok = sc.category_visible_within(SUCCESS_DISTANCE)[:, CATEGORY_INDEX[t.target]]
        index = {k: i for i, k in enumerate(sc.keys)}
        ref = next((i for i, k in enumerate(t.keys) if ok[index[k]]), -1)
        assert t.success_frame == ref
        assert ref >= 0 or not r.success
        sw = t.switch_frame
        assert t.success_after_switch == (
            next((i for i in range(sw, len(t.keys)) if ok[index[t.keys[i]]]), -1) if sw >= 0 else -1
        )
        assert t.switch_distance == (bfs_to_success(sc, index[t.keys[sw]], ok) if sw >= 0 else -1)
        if not r.success and ref >= 0:
            missed["switched" if r.entered_pathfinding else "never switched"] += 1
        frames.append(ref)
    assert s["failed_after_a_success_state"] == missed
    return frames


def test_after_the_switch():
    eps = [
        episode(0, "Fridge", True, True, [MOVE_AHEAD, MOVE_AHEAD, DONE]),  # switch at 1, L* 0: 2 actions / 1
        episode(1, "Fridge", True, True, [MOVE_AHEAD, DONE]),  # switch at 0, L* 1: 2 / 2
        episode(2, "Fridge", False, True, [MOVE_AHEAD, DONE]),  # wrong Done
        episode(3, "Fridge", False, True, [ROTATE_LEFT] * 4),  # passed a success state
        episode(4, "Fridge", False, True, [ROTATE_LEFT] * 4),  # never got there
        episode(5, "CellPhone", False, False, [ROTATE_RIGHT] * 3),
    ]  # never switched: not counted
    for (_, t), (sw, d, hit) in zip(eps, [(1, 0, 1), (0, 1, 1), (0, 2, 1), (2, 3, 3), (1, 4, -1), (-1, -1, -1)]):
        t.switch_frame, t.switch_distance, t.success_after_switch, t.success_frame = sw, d, hit, hit
    s = outcome_summary([e[0] for e in eps], [e[1] for e in eps])["after_switch"]
    assert s == {
        "episodes": 5,
        "success": 2,
        "median_distance_at_switch": 2.0,
        "path_ratio": pytest.approx(4 / 3),
        "failures": {"passed a success state without Done": 1, "wrong Done": 1, "never got to a success state": 1},
    }
    assert "after the switch: 2 of 5 succeeded" in format_outcomes(
        outcome_summary([e[0] for e in eps], [e[1] for e in eps])
    )
    eps[0][1].switch_distance = None  # an older file: no figures rather than wrong ones
    assert outcome_summary([e[0] for e in eps], [e[1] for e in eps])["after_switch"] is None
