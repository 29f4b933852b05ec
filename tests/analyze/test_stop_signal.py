"""``tsnav analyze stop-signal`` (issue 23, the stop decision): its rank AUC agrees with the all-pairs reference, the
leave-one-room-out regression finds a signal that is there, and on a built world its counts are consistent with the
protocol (success states only within 1.5 m under ``lineage``)."""

import json

import numpy as np
import pytest
from script_helpers import load_analysis


def _script():
    return load_analysis("stop_signal")


def test_auc_matches_the_all_pairs_reference():
    mod = _script()
    rng = np.random.default_rng(0)
    for n, m, levels in ((5, 7, 3), (40, 25, 1000), (60, 60, 4)):
        pos = rng.integers(0, levels, n).astype(float)
        neg = rng.integers(0, levels, m).astype(float) - 0.5
        assert mod.auc(pos, neg) == pytest.approx(mod.auc_reference(pos, neg), abs=1e-12)
    assert mod.auc(np.array([2.0, 3.0]), np.array([0.0, 1.0])) == 1.0
    assert mod.auc(np.array([1.0]), np.array([1.0])) == 0.5
    assert np.isnan(mod.auc(np.array([]), np.array([1.0])))


def test_leave_one_room_out_finds_a_box_signal():
    """Success when the box is tall, with noise: the held-out regression ranks it far above chance, and a feature
    with no signal stays near 0.5."""
    mod = _script()
    rng = np.random.default_rng(1)
    rows = []
    for room in ("A", "B", "C", "D"):
        for _ in range(150):
            h = float(rng.uniform(0.05, 0.6))
            rows.append(
                {
                    "room": room,
                    "category": "Bowl",
                    "success": h + rng.normal(0, 0.05) > 0.3,
                    "dist": 1.0,
                    "score": float(rng.uniform(0.7, 1.0)),
                    "area": h * h,
                    "height": h,
                    "width": h,
                    "bottom": 0.5 + h / 2,
                    "top": 0.5 - h / 2,
                    "horizon": 0.0,
                }
            )
    s = mod.summary(rows)
    assert s["auc"]["logistic, leave one room out"] > 0.9
    assert abs(s["auc"]["score"] - 0.5) < 0.1
    assert s["confident_states"] == 600


def test_on_a_world(pixel_world, tmp_path, capsys):
    mod = _script()
    out = tmp_path / "s.json"
    assert (
        mod.main(["--data", str(pixel_world), "--detections", "oracle", "--threshold", "0.5", "--json", str(out)]) == 0
    )
    res = json.loads(out.read_text())["tables"]["oracle"]
    bands = res["bands"]
    assert sum(v["states"] for v in bands.values()) == res["confident_states"] > 0
    for k, v in bands.items():  # lineage: a success state lists the target within 1.5 m
        if k not in ("0-1 m", "1-1.5 m"):
            assert v["success"] == 0, k
    assert 0 < res["success_share"] < 1
    assert "confident (state, category) pairs" in capsys.readouterr().out
    assert mod.main(["--data", str(tmp_path / "missing"), "--detections", "oracle"]) == 2
    assert "is not a folder" in capsys.readouterr().err


def test_an_agents_dones_are_scored(pixel_world, tmp_path, capsys):
    """Two hand-made episodes end in Done, one at a success state and one at a confident non-success state: the
    script counts one successful and one failed Done and scores both with the held-out model."""
    from tsnav.constants import DONE, MOVE_AHEAD, TARGET_CATEGORIES
    from tsnav.data.detections import load_detections
    from tsnav.data.reader import list_scenes, load_scene
    from tsnav.eval.runner import Trajectory

    mod = _script()
    picked = None
    for p in list_scenes(pixel_world):
        s, det = load_scene(p), load_detections(p, "oracle")
        ok = s.success_table("lineage")
        conf = det.scores > 0.5
        for c in sorted(set(int(v) for v in s.object_category if v >= 0)):
            good, bad = np.flatnonzero(ok[:, c] & conf[:, c]), np.flatnonzero(~ok[:, c] & conf[:, c])
            if len(good) and len(bad):
                picked = (s, c, int(good[0]), int(bad[0]))
                break
        if picked:
            break
    assert picked, "the tiny world has a category with confident success and non-success states"
    s, c, good, bad = picked
    ev = tmp_path / "eval"
    ev.mkdir()
    trajs = [
        Trajectory(
            episode=k,
            scene=s.name,
            target=TARGET_CATEGORIES[c],
            keys=[str(s.keys[i]), str(s.keys[i])],
            actions=[DONE],
            success=k == 0,
        )
        for k, i in enumerate((good, bad))
    ]
    trajs.append(
        Trajectory(
            episode=2, scene=s.name, target=TARGET_CATEGORIES[c], keys=[str(s.keys[good])] * 2, actions=[MOVE_AHEAD]
        )
    )  # no Done: not counted
    (ev / "trajectories.jsonl").write_text("".join(t.to_json() + "\n" for t in trajs))
    out = tmp_path / "s.json"
    assert (
        mod.main(
            [
                "--data",
                str(pixel_world),
                "--detections",
                "oracle",
                "--threshold",
                "0.5",
                "--eval",
                str(ev),
                "--json",
                str(out),
            ]
        )
        == 0
    )
    res = json.loads(out.read_text())["tables"]["oracle"]
    assert res["agent's Dones"] == {"successful": 1, "failed": 1, "failed, below the switch threshold": 0}
    for k, v in res.items():
        if k.startswith("keeping"):
            assert v["agent's successful Dones rejected"] in (0, 1) and v["agent's failed Dones rejected"] in (0, 1)
    capsys.readouterr()
    assert mod.main(["--data", str(pixel_world), "--detections", "oracle", "--eval", str(tmp_path)]) == 2
    assert "no trajectories.jsonl" in capsys.readouterr().err
