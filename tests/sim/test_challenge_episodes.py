"""The RoboTHOR challenge's episodes as tsnav episode lists (tsnav.sim.challenge, `tsnav thor challenge-episodes`):
the heading rule by hand, off-graph starts counted per scene and dropped, both protocols, grid metres against
their slow reference; and the real challenge files in ../shared (skipped when that folder is missing)."""

from __future__ import annotations

import gzip
import json
import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from tsnav.cli import main
from tsnav.constants import ROBOTHOR12
from tsnav.data.toy import toy_scene
from tsnav.sim.batch import SceneBank
from tsnav.sim.challenge import (
    challenge_episodes,
    challenge_heading,
    grid_metres,
    grid_metres_reference,
    read_challenge_episodes,
)
from tsnav.sim.episodes import episodes_to_arrays, read_episodes

from sim_helpers import write_scene_folder

SHARED = Path(__file__).resolve().parents[3] / "shared" / "robothor" / "challenge_episodes"
SCENE = "FloorPlan_Val1_1"


def scene():
    """2 x 1.5 m room; an Apple in the far corner, a HousePlant on the left wall, a Vase too far away to be seen
    from any state; three blocked cells."""
    return toy_scene(
        2.0,
        1.5,
        {"Apple|1": (2.0, 1.5), "HousePlant|1": (0.0, 0.75), "Vase|1": (9.0, 9.0)},
        blocked=[(1.0, 0.5), (1.0, 0.75), (1.0, 1.0)],
        name=SCENE,
        class_set="robothor12",
    )


def record(i, target, x, z, orientation, length=1.0, scene_name=SCENE):
    return {
        "id": f"{scene_name}_{target}_{i}",
        "scene": scene_name,
        "object_type": target,
        "initial_position": {"x": x, "y": 0.9, "z": z},
        "initial_orientation": orientation,
        "initial_horizon": 30,
        "shortest_path": [],
        "shortest_path_length": length,
    }


RECORDS = [
    record(0, "Apple", 0.0, 0.0, 30, 2.4),  # -> 0.00|0.00|45|30
    record(1, "HousePlant", 2.0, 1.5, 150, 2.0),  # -> 2.00|1.50|135|30
    record(2, "Apple", 1.0, 0.75, 0),  # a blocked cell: not a state
    record(3, "Apple", 1.0, 0.5, 240),  # blocked too
    record(4, "Mug", 0.5, 0.5, 60),  # no Mug in the room
    record(5, "Apple", 1.75, 1.25, 60, 0.3),  # -> 45: facing the Apple 0.35 m away (already succeeds)
    record(6, "Apple", 0.5, 0.5, 90, 1.0, "FloorPlan_Val2_1"),  # a scene not in the dataset
    record(7, "Vase", 0.5, 0.5, 0),  # a Vase no state sees
]


def test_heading_rule_by_hand():
    # the 12 challenge headings: the nearest multiple of 45 (never a tie); every heading is one of tsnav's 8
    want = {
        0: 0,
        30: 45,
        60: 45,
        90: 90,
        120: 135,
        150: 135,
        180: 180,
        210: 225,
        240: 225,
        270: 270,
        300: 315,
        330: 315,
    }
    assert {o: challenge_heading(o) for o in want} == want
    for o in range(0, 360, 30):
        assert abs((challenge_heading(o) - o + 180) % 360 - 180) == (0 if o % 90 == 0 else 15)
    assert challenge_heading(22.5) == 45 and challenge_heading(337.5) == 0 and challenge_heading(359) == 0


def test_conversion_counts_and_protocols():
    for protocol, kept_ids in (("paper", ["0", "1"]), ("lineage", ["0", "1", "5"])):
        bank = SceneBank([scene()], protocol=protocol)
        eps, st = challenge_episodes(RECORDS, bank)
        assert [e.challenge["id"].rsplit("_", 1)[1] for e in eps] == kept_ids
        assert st.read == 8 and st.kept == len(kept_ids)
        dropped = {
            "start not a state": 2,
            "target not in scene": 1,
            "scene not in DATA": 1,
            "target has no success state": 1,
        }
        if protocol == "paper":
            dropped["start already succeeds"] = 1
        assert st.dropped == dropped
        assert st.per_scene[SCENE]["start not a state"] == 2 and st.per_scene[SCENE]["read"] == 7
        assert st.per_scene["FloorPlan_Val2_1"] == Counter({"read": 1, "scene not in DATA": 1})
        assert st.starts_on_graph == (5, 7) and "5 / 7 starts are states" in st.summary()
        assert st.start_success == (protocol == "lineage")
        a, b = eps[0], eps[1]
        assert (a.start, a.target) == ("0.00|0.00|45|30", "Apple") and a.challenge["initial_orientation"] == 30
        assert (b.start, b.target) == ("2.00|1.50|135|30", "HousePlant")
        assert a.challenge["shortest_path_length"] == 2.4
        # L* is the bank's (the list reads back through episodes_to_arrays' check)
        scene_idx, target, start = episodes_to_arrays(bank, eps)
        assert [ROBOTHOR12.categories[t] for t in target] == [e.target for e in eps]
        for e, s, t in zip(eps, start, target):
            assert e.optimal_length == bank.dist[s, t]
            assert e.optimal_metres == pytest.approx(grid_metres_reference(bank, int(s), int(t)), abs=1e-4)
        if protocol == "lineage":
            assert eps[2].optimal_length == 0 and eps[2].optimal_metres == 0.0


def test_grid_metres_against_reference_and_by_hand():
    bank = SceneBank([scene()])
    apple = ROBOTHOR12.index["Apple"]
    fast = grid_metres(bank, apple)
    rng = np.random.default_rng(0)
    for s in rng.choice(bank.num_states, 40, replace=False):
        assert fast[s] == pytest.approx(grid_metres_reference(bank, int(s), apple), abs=1e-9)
    # by hand: from (0, 0) to the nearest position that succeeds for the Apple at (2.0, 1.5) (in view within 1 m)
    ok = np.unique(np.stack([bank.x, bank.z], 1)[bank.success[:, apple]], axis=0)
    start = bank.global_state(0, "0.00|0.00|0|0")
    # the diagonal walk (0,0) -> (0.75, 0.75) costs 3 * 0.25 * sqrt(2); the blocked column x = 1.0 at z 0.5-1.0
    # is passed below or above it
    assert math.isclose(fast[start], min(_dijkstra_by_hand(bank, start, set(map(tuple, ok.round(2))))), rel_tol=1e-9)
    assert np.isinf(grid_metres(bank, ROBOTHOR12.index["Mug"])).all()


def _dijkstra_by_hand(bank, start, goals):
    """Positions only: the eight grid steps between free cells (the toy room's graph has every rotation)."""
    import heapq

    free = set(zip(np.round(bank.x, 2).tolist(), np.round(bank.z, 2).tolist()))
    s0 = (round(float(bank.x[start]), 2), round(float(bank.z[start]), 2))
    best, heap = {s0: 0.0}, [(0.0, s0)]
    while heap:
        d, p = heapq.heappop(heap)
        if p in goals:
            yield d
            return
        for dx in (-0.25, 0, 0.25):
            for dz in (-0.25, 0, 0.25):
                q = (round(p[0] + dx, 2), round(p[1] + dz, 2))
                if q != p and q in free and d + math.hypot(dx, dz) < best.get(q, math.inf):
                    best[q] = d + math.hypot(dx, dz)
                    heapq.heappush(heap, (best[q], q))


def _write_challenge(root: Path, records) -> Path:
    folder = root / "val"
    folder.mkdir(parents=True)
    by_scene: dict = {}
    for r in records:
        by_scene.setdefault(r["scene"], []).append(r)
    for name, rs in by_scene.items():
        with gzip.open(folder / f"{name}.json.gz", "wt") as f:
            json.dump(rs, f)
    return root


def test_command_writes_both_protocols_and_reports(tmp_path, capsys):
    data = tmp_path / "world"
    write_scene_folder(scene(), data / SCENE)
    challenge = _write_challenge(tmp_path / "challenge", RECORDS)
    for protocol, n in (("paper", 2), ("lineage", 3)):
        out = tmp_path / f"{protocol}.json"
        assert (
            main(
                [
                    "thor",
                    "challenge-episodes",
                    "--challenge",
                    str(challenge),
                    "--split",
                    "val",
                    "--data",
                    str(data),
                    "--protocol",
                    protocol,
                    "--out",
                    str(out),
                ]
            )
            == 0
        )
        text = capsys.readouterr().out
        assert "5 / 7 starts are states" in text and f"{SCENE}: {n} of 7 kept" in text and "2 start not a state" in text
        eps, meta = read_episodes(out)
        assert len(eps) == n and meta["protocol"] == protocol and meta["class_set"] == "robothor12"
        assert meta["conversion"]["per_scene"][SCENE]["start not a state"] == 2
        assert "45 * floor(o / 45 + 1/2)" in meta["heading_rule"] and meta["lengths"]["episodes"] == n
        raw = json.loads(out.read_text())["episodes"][0]
        assert set(raw) >= {"optimal_length", "optimal_metres", "challenge"}
        # the list evaluates on the world (its L* checked against the bank's)
        assert (
            main(
                [
                    "eval",
                    "--data",
                    str(data),
                    "--episodes",
                    str(out),
                    "--policy",
                    "oracle",
                    "--out",
                    str(tmp_path / f"ev_{protocol}"),
                ]
            )
            == 0
        )
        capsys.readouterr()
    assert (
        main(
            [
                "thor",
                "challenge-episodes",
                "--challenge",
                str(challenge),
                "--split",
                "val",
                "--data",
                str(data),
                "--out",
                str(tmp_path / "paper.json"),
            ]
        )
        == 2
    )
    assert "exists" in capsys.readouterr().err
    assert (
        main(
            [
                "thor",
                "challenge-episodes",
                "--challenge",
                str(tmp_path),
                "--split",
                "val",
                "--data",
                str(data),
                "--out",
                str(tmp_path / "x.json"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert "no challenge episode files" in err and len(err.splitlines()) == 1
    ithor = tmp_path / "ithor"
    write_scene_folder(toy_scene(name=SCENE), ithor / SCENE)
    assert (
        main(
            [
                "thor",
                "challenge-episodes",
                "--challenge",
                str(challenge),
                "--split",
                "val",
                "--data",
                str(ithor),
                "--out",
                str(tmp_path / "y.json"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert "declares class set ithor22" in err and "robothor12" in err and len(err.splitlines()) == 1


def test_plain_episode_lists_are_written_as_before(tmp_path):
    from tsnav.sim.episodes import Episode, write_episodes

    write_episodes(tmp_path / "e.json", [Episode("FloorPlan1", "Bowl", "0.00|0.00|0|0", 3, "kitchen")])
    assert json.loads((tmp_path / "e.json").read_text())["episodes"] == [
        {"scene": "FloorPlan1", "target": "Bowl", "start": "0.00|0.00|0|0", "optimal_length": 3, "room_type": "kitchen"}
    ]


@pytest.mark.skipif(
    not SHARED.is_dir(),
    reason=f"the shared RoboTHOR records are not at {SHARED} (CI copies shared/ beside the clone as ../shared)",
)
def test_real_challenge_files():
    val = read_challenge_episodes(SHARED, "val")
    train = read_challenge_episodes(SHARED, "train")
    assert len(val) == 1800 and len(train) == 108000
    assert len({r["scene"] for r in val}) == 15 and len({r["scene"] for r in train}) == 60
    assert Counter(r["scene"] for r in val) == {f"FloorPlan_Val{a}_{b}": 120 for a in (1, 2, 3) for b in range(1, 6)}
    for rs in (val, train):
        assert {r["object_type"] for r in rs} == set(ROBOTHOR12.categories)
        assert {r["initial_horizon"] for r in rs} == {30}
        assert {int(r["initial_orientation"]) % 30 for r in rs} == {0}
        assert {challenge_heading(r["initial_orientation"]) for r in rs} <= set(range(0, 360, 45))
        pos = np.array([[r["initial_position"]["x"], r["initial_position"]["z"]] for r in rs])
        assert np.abs(pos * 4 - np.round(pos * 4)).max() < 1e-6  # on the 0.25 m grid
        assert min(r["shortest_path_length"] for r in rs) >= 0
    # the challenge's own start-success episodes (navmesh length 0): 108 of val's, 6,172 of train's
    assert sum(r["shortest_path_length"] == 0 for r in val) == 108
    assert sum(r["shortest_path_length"] == 0 for r in train) == 6172


def test_command_sample_is_the_pipelines_draw(tmp_path, capsys):
    """--sample N --seed S keeps the sample tsnav release make scores checkpoints on (ensure_challenge_episodes with
    per_room_type N and seed S), recorded in the list; a sample below 1 is refused in one line, nothing written."""
    from tsnav.pipeline.steps import ensure_challenge_episodes

    data = tmp_path / "world"
    write_scene_folder(scene(), data / SCENE)
    challenge = _write_challenge(tmp_path / "challenge", RECORDS)
    args = ["thor", "challenge-episodes", "--challenge", str(challenge), "--split", "val", "--data", str(data)]
    out = tmp_path / "sample.json"
    assert main([*args, "--protocol", "lineage", "--sample", "2", "--seed", "1", "--out", str(out)]) == 0
    assert "kept a sample of 2 of the 3 converted episodes (seed 1)" in capsys.readouterr().out
    eps, meta = read_episodes(out)
    ref, ref_meta = read_episodes(
        ensure_challenge_episodes(
            data, "val", tmp_path / "ref.json", "lineage", challenge=challenge, scenes=[SCENE], per_room_type=2, seed=1
        )
    )
    assert [(e.scene, e.start, e.target) for e in eps] == [(e.scene, e.start, e.target) for e in ref]
    assert meta["sample"] == ref_meta["sample"] == {"per_room_type": 2, "seed": 1, "of": 3}
    bad = tmp_path / "bad.json"
    assert main([*args, "--sample", "0", "--out", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert "--sample must be >= 1" in err and len(err.splitlines()) == 1 and not bad.exists()
