"""``tsnav analyze agent-diagnostics outcomes`` (issue 23 analysis): outcome counts, blocked MoveAheads and loops of
hand-made trajectories, and the command on a real evaluation folder of the tiny world."""

import json

import numpy as np

import pytest

from tsnav.cli import main
from tsnav.constants import DONE, MOVE_AHEAD, ROTATE_LEFT
from tsnav.constants import ROTATE_RIGHT as ACTIONS_RIGHT
from tsnav.eval.runner import Trajectory, read_trajectories
from script_helpers import load_analysis


@pytest.fixture(scope="module")
def diag():
    return load_analysis("agent_diagnostics")


def _traj(keys, actions, switch=-1, success=False):
    return Trajectory(
        episode=0, scene="S", target="Bowl", keys=keys, actions=actions, switch_frame=switch, success=success
    )


def test_outcome_figures_by_hand(diag):
    F, L, D = MOVE_AHEAD, ROTATE_LEFT, DONE
    stuck = _traj(["a"] + ["a"] * 100, [F] * 100, switch=0)  # 100 blocked MoveAheads: a loop at the step limit
    walk = _traj([f"s{i}" for i in range(101)], [F] * 100)  # 100 moves, never blocked, never switched
    found = _traj(["a", "b", "b", "b", "c"], [F, L, F, D], switch=1, success=True)  # one blocked of three
    wrong = _traj(["a", "a", "b"], [F, D], switch=0)  # a failed Done after a blocked move
    r = diag.outcome_figures([stuck, walk, found, wrong])
    assert r["episodes"] == 4
    assert (r["switched_limit"], r["unswitched_limit"], r["switched_success"], r["switched_done"]) == (1, 1, 1, 1)
    assert r["unswitched_success"] == r["unswitched_done"] == 0
    assert r["blocked_share"]["limit"] == pytest.approx(100 / 200)
    assert r["blocked_share"]["success"] == pytest.approx(1 / 2)
    assert r["blocked_share"]["done"] == pytest.approx(1.0)
    assert r["blocked_share"]["all"] == pytest.approx(102 / 203)
    assert r["many_blocked"] == 1 and r["limit_loops"] == 1
    assert diag.outcome(found) == "success" and diag.outcome(wrong) == "done" and diag.outcome(walk) == "limit"


def _evaluate(world, folder, policy: str):
    """``tsnav eval`` of ``policy`` on 4 test episodes per room type of ``world``; the evaluation folder."""
    eps, ev = folder / "eps.json", folder / "eval"
    assert main(["episodes", "--data", str(world), "--split", "test", "--per-room-type", "4", "--out", str(eps)]) == 0
    assert main(["eval", "--data", str(world), "--episodes", str(eps), "--policy", policy, "--out", str(ev)]) == 0
    return ev


def test_outcomes_command_on_an_evaluation(diag, tiny_world, tmp_path, capsys):
    ev = _evaluate(tiny_world, tmp_path, "random")
    capsys.readouterr()
    assert diag.main(["outcomes", str(ev)]) == 0
    out = capsys.readouterr().out
    n = json.loads((ev / "metrics.json").read_text())["metrics"]["ALL"]["episodes"]
    assert f"{n} episodes" in out and "blocked MoveAheads" in out
    # with --data, the switched episodes split into true and false switches, by outcome
    from tsnav.eval.runner import read_trajectories

    traj = read_trajectories(ev / "trajectories.jsonl")
    r, split = diag.outcome_figures(traj), diag.switch_truth(tiny_world, traj)
    for o in ("success", "done", "limit"):
        assert split["true"][o] + split["false"][o] == r[f"switched_{o}"]
    assert diag.main(["outcomes", str(ev), "--data", str(tiny_world)]) == 0
    printed = capsys.readouterr().out
    assert "true switches" in printed
    assert sum(split["true"].values()) + sum(split["false"].values()) > 0, printed  # some episodes switched
    with pytest.raises(SystemExit, match="no trajectories.jsonl"):
        diag.main(["outcomes", str(tmp_path)])


def test_switch_misses_by_hand(diag, tmp_path, capsys):
    def t(ep, target, switch):
        return Trajectory(episode=ep, scene="S", target=target, keys=["a", "a"], actions=[DONE], switch_frame=switch)

    a = [t(0, "Plate", -1), t(1, "Plate", 3), t(2, "Bowl", -1), t(3, "Bowl", -1)]
    b = [t(0, "Plate", 2), t(1, "Plate", 1), t(2, "Bowl", -1), t(3, "Bowl", 5)]
    r = diag.switch_misses(a, b)
    assert (r["both"], r["a_only"], r["b_only"], r["neither"]) == (1, 0, 2, 1)
    assert r["targets"] == {"Plate": [2, 1, 0, 1], "Bowl": [2, 2, 1, 1]}
    with pytest.raises(ValueError, match="same episode list"):
        diag.switch_misses(a, b[:3])
    with pytest.raises(ValueError, match="another room or target"):
        diag.switch_misses(a, [t(0, "Bowl", 1)] + b[1:])
    for name, trajs in (("A", a), ("B", b)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "trajectories.jsonl").write_text("".join(x.to_json() + "\n" for x in trajs))
    assert diag.main(["switches", str(tmp_path / "A"), str(tmp_path / "B")]) == 0
    out = capsys.readouterr().out
    assert "only B 2, neither 1" in out and out.index("Bowl") < out.index(
        "Plate"
    )  # equal "B only": most A misses first
    with pytest.raises(SystemExit, match="no trajectories.jsonl"):
        diag.main(["switches", str(tmp_path / "A"), str(tmp_path)])


def test_switch_distance_bands_by_hand(diag):
    from tsnav.metrics import EpisodeRecord

    def rec(opt_nav, nav, success, switched=True):
        return EpisodeRecord(
            success=success,
            path_length=nav,
            optimal_length=opt_nav,
            entered_pathfinding=switched,
            pathfinding_path_length=nav if switched else None,
            optimal_pathfinding_length=opt_nav if switched else None,
        )

    records = [
        rec(0, 0, True),  # began at the goal: a success without a ratio
        rec(2, 4, True),  # ratio 2
        rec(4, 4, False),
        rec(7, 14, True),  # ratio 2, band 5-9
        rec(31, 40, False),  # the open-ended band
        rec(45, 90, True),  # ratio 2, the same band
        rec(3, 3, True, switched=False),  # never switched: not counted
    ]
    rows = diag.switch_distance_figures(records, band=5, last=30)
    assert [(r["from"], r["to"], r["episodes"], r["successes"]) for r in rows] == [
        (0, 5, 3, 2),
        (5, 10, 1, 1),
        (30, None, 2, 1),
    ]
    assert rows[0]["success_share"] == pytest.approx(2 / 3) and rows[0]["median_ratio"] == pytest.approx(2.0)
    assert rows[2]["median_ratio"] == pytest.approx(2.0)
    truth = {i: i != 1 for i in range(len(records))}  # episode 1 (band 0-4, a success) switched on a false positive
    for i, r in enumerate(records):
        r.episode = i
    rows = diag.switch_distance_figures(records, band=5, last=30, truth=truth)
    assert [(r["false_switches"], r["false_successes"]) for r in rows] == [(1, 1), (0, 0), (0, 0)]
    only_goal = diag.switch_distance_figures([rec(0, 0, True)])
    assert only_goal[0]["median_ratio"] is None
    with pytest.raises(ValueError, match="multiple of --band"):
        diag.switch_distance_figures(records, band=4, last=30)
    edges = [rec(4, 4, True), rec(5, 5, True), rec(29, 29, False), rec(30, 30, False)]
    spans = [(r["from"], r["to"], r["episodes"]) for r in diag.switch_distance_figures(edges, band=5, last=30)]
    assert spans == [(0, 5, 1), (5, 10, 1), (25, 30, 1), (30, None, 1)]
    with pytest.raises(ValueError, match="not in the trajectories"):
        diag.switch_distance_figures(records, truth={0: True})


def test_switch_distance_command(diag, tiny_world, tmp_path, capsys):
    ev = _evaluate(tiny_world, tmp_path, "explorer")
    capsys.readouterr()
    js = tmp_path / "sd.json"
    args = ["switch-distance", f"explorer={ev}", "--band", "2", "--last", "4", "--json", str(js), "--false-switches"]
    assert diag.main(args) == 0
    out = capsys.readouterr().out
    from tsnav.metrics import read_records

    records = read_records(ev / "records.jsonl")
    switched = sum(r.entered_pathfinding for r in records)
    assert f"explorer: {switched} of {len(records)} episodes switched" in out and "LNav/L*Nav" in out
    written = json.loads(js.read_text())["evaluations"][0]
    assert written["label"] == "explorer" and written["switched"] == switched
    assert sum(b["episodes"] for b in written["bands"]) == switched
    truth = diag.true_switches(tiny_world, read_trajectories(ev / "trajectories.jsonl"))
    assert len(truth) == switched
    assert sum(b["false_switches"] for b in written["bands"]) == sum(not v for v in truth.values())
    with pytest.raises(SystemExit, match="no records.jsonl"):
        diag.main(["switch-distance", str(tmp_path)])


def test_reach_share_reads_the_tables_class_set(diag, tmp_path):
    """A RoboTHOR table's columns are robothor12's: the share looks the target up there, not in iTHOR's 22."""
    from tsnav.constants import class_set
    from tsnav.data.detections import Detections, write_detections
    from tsnav.sim.episodes import Episode

    robo = class_set("robothor12")
    S, C = 3, robo.size
    scores = np.zeros((S, C), np.float32)
    scores[1, robo.index["Vase"]] = 0.9  # seen above C_target at one state
    scores[2, robo.index["Apple"]] = 0.6  # never above it
    labels = np.where(scores > 0, np.arange(C, dtype=np.int16)[None, :], -1).astype(np.int16)
    det = Detections(
        keys=["a", "b", "c"],
        scores=scores,
        labels=labels,
        boxes=np.full((S, C, 4), -1, np.float32),
        features=np.zeros((S, C, 2), np.float16),
        class_set="robothor12",
    )
    (tmp_path / "Room").mkdir()
    write_detections(tmp_path / "Room", "t", det)
    eps = [Episode(scene="Room", target=t, start="a", optimal_length=1) for t in ("Vase", "Apple", "Vase", "Mug")]
    assert diag.reach_share(tmp_path, eps, "t") == pytest.approx(2 / 4)


def test_true_switches_read_the_frame_where_the_switch_fired(diag, tiny_world):
    """A switch at a state where an instance of the target is in view is true, one where none is, false; an episode
    that never switched is not listed."""
    from tsnav.data.reader import list_scenes, load_scene

    folder = list_scenes(tiny_world)[0]
    scene = load_scene(folder)
    visible = scene.visible_at_any_range()
    for target in scene.class_set.categories:
        objs = np.flatnonzero(scene.object_category == scene.class_set.index[target])
        seen = visible[:, objs].any(axis=1) if len(objs) else np.zeros(len(scene.keys), bool)
        if seen.any() and not seen.all():
            break
    else:
        pytest.skip("no target of the tiny scene is in view at some states and out of view at others")
    inside, outside = scene.keys[int(np.flatnonzero(seen)[0])], scene.keys[int(np.flatnonzero(~seen)[0])]

    def traj(episode, key, switch):
        return Trajectory(
            episode=episode, scene=folder.name, target=target, keys=[key, key], actions=[DONE], switch_frame=switch
        )

    truth = diag.true_switches(tiny_world, [traj(3, inside, 0), traj(5, outside, 0), traj(7, outside, -1)])
    assert truth == {3: True, 5: False}


def test_switch_distance_refuses_missing_files_in_one_line(diag, tmp_path):
    (tmp_path / "records.jsonl").write_text("")
    with pytest.raises(SystemExit, match="no metrics.json"):
        diag.main(["switch-distance", str(tmp_path), "--false-switches"])
    with pytest.raises(SystemExit, match="multiple of --band"):
        diag.main(["switch-distance", str(tmp_path), "--band", "4"])


def test_short_turn_spl_by_hand(diag, tmp_path):
    from tsnav.eval.runner import write_trajectories
    from tsnav.metrics import EpisodeRecord, write_records

    L, R, M = ROTATE_LEFT, ACTIONS_RIGHT, MOVE_AHEAD
    # a success with a run of 6 turns left (2 right would do: saves 4) and one of 3 (saves nothing); a failure with a
    # run of 7 turns right (kept: failures keep their path); a success without long runs
    acts = [[L] * 6 + [M, M] + [L] * 3 + [M, DONE], [R] * 7 + [M] * 3, [M, M, DONE]]
    records = [
        EpisodeRecord(success=True, path_length=12, optimal_length=4, scene="S", target="Bowl", start="0|0|0|0"),
        EpisodeRecord(success=False, path_length=10, optimal_length=3, scene="S", target="Bowl", start="1|0|0|0"),
        EpisodeRecord(success=True, path_length=2, optimal_length=2, scene="S", target="Bowl", start="2|0|0|0"),
    ]
    assert [diag.saved_turns(a) for a in acts] == [4, 6, 0]
    write_records(tmp_path / "records.jsonl", records)
    write_trajectories(tmp_path / "trajectories.jsonl", [_traj(["k"] * (len(a) + 1), a) for a in acts])
    (tmp_path / "metrics.json").write_text(json.dumps({"protocol": "paper"}))
    before, after = diag.short_turn_spl(tmp_path)
    # paper: L* / max(L, L*) over all episodes
    assert before == pytest.approx(100 * (4 / 12 + 0 + 1) / 3)
    assert after == pytest.approx(100 * (4 / 8 + 0 + 1) / 3)
