"""The lineage's episode lists read safely (issue 13, part 3): a restricted unpickler, hostile pickles refused
before their payload runs, and ``tsnav thor episodes`` keeping what exists in the dataset."""

from __future__ import annotations

import builtins
import os
import pickle

import numpy as np
import pytest

from tsnav.cli import main
from tsnav.data import lineage_splits as LS
from tsnav.data.reader import load_scene


class _System:
    """Unpickling this runs ``os.system(cmd)`` with a plain ``pickle.load``."""

    def __init__(self, cmd):
        self.cmd = cmd

    def __reduce__(self):
        return os.system, (self.cmd,)


class _Exec:
    def __init__(self, code):
        self.code = code

    def __reduce__(self):
        return builtins.exec, (self.code,)


class _Open:
    def __init__(self, path):
        self.path = path

    def __reduce__(self):
        return builtins.open, (str(self.path), "w")


def _records(scene, n=3):
    keys = scene.keys[scene.horizon == 30][:n].tolist()
    return [LS.split_record(scene.name, k, "Bowl", ["Bowl|+00.00|+00.90|+00.00"]) for k in keys]


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
def test_plain_lists_with_numpy_arrays_read_at_every_protocol(tmp_path, tiny_scenes, protocol):
    recs = _records(tiny_scenes[0])
    recs[0]["extra"] = (1, 2.5, True, None, {"a": [b"x", "y"]}, {3, 4}, np.float64(0.25), np.arange(3, dtype=np.int16))
    p = tmp_path / "kitchen_test_22.pkl"
    p.write_bytes(pickle.dumps(recs, protocol=protocol))
    back = LS.read_split(p)
    assert [r["state"] for r in back] == [r["state"] for r in recs]
    assert np.array_equal(back[0]["glove_embedding"], recs[0]["glove_embedding"])
    assert back[0]["glove_embedding"].dtype == np.float32 and back[0]["glove_embedding"].shape == (60, 1)
    assert back[0]["extra"][:4] == (1, 2.5, True, None) and back[0]["extra"][5] == {3, 4}
    assert np.array_equal(back[0]["extra"][7], np.arange(3, dtype=np.int16))


@pytest.mark.parametrize("make", ["system", "exec", "open", "nested", "object_array"])
def test_hostile_pickles_are_refused_before_their_payload_runs(tmp_path, tiny_scenes, make, capsys):
    target = tmp_path / "pwned.txt"
    payload = {
        "system": lambda: _System(f"touch {target}"),
        "exec": lambda: _Exec(f"open({str(target)!r}, 'w').write('x')"),
        "open": lambda: _Open(target),
        "nested": lambda: _records(tiny_scenes[0]) + [{"scene": _System(f"touch {target}")}],
        "object_array": lambda: [
            {"scene": "FloorPlan1", "glove_embedding": np.array([_Exec(f"open({str(target)!r}, 'w')")], dtype=object)}
        ],
    }[make]()
    p = tmp_path / "kitchen_test_22.pkl"
    p.write_bytes(pickle.dumps(payload, protocol=2 if make == "object_array" else 4))
    with pytest.raises(
        LS.SplitFormatError,
        match=r"refused: the pickle calls (posix|nt|os|builtins|__builtin__|io)\.(system|exec|open)",
    ) as e:
        LS.read_split(p)
    assert "\n" not in str(e.value)
    assert not target.exists()
    # the command: one line on stderr, exit 2, no output written, payload never run
    out = tmp_path / "eps.json"
    assert main(["thor", "episodes", str(p), "--data", str(tiny_scenes[0].path.parent), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "refused" in err
    assert not target.exists() and not out.exists()


def test_corrupt_and_wrong_shaped_pickles_give_one_line(tmp_path):
    p = tmp_path / "x.pkl"
    p.write_bytes(pickle.dumps([{"scene": "FloorPlan1"}] * 3)[:-5])
    with pytest.raises(LS.SplitFormatError, match="not a readable pickle"):
        LS.read_split(p)
    p.write_bytes(pickle.dumps({"scene": "FloorPlan1"}))
    with pytest.raises(LS.SplitFormatError, match="expected a list"):
        LS.read_split(p)
    p.write_bytes(pickle.dumps([{"scene": "FloorPlan1", "state": "0.00|0.00|0|0"}]))
    with pytest.raises(LS.SplitFormatError, match="episode 0 is not a dict with"):
        LS.read_split(p)
    with pytest.raises(LS.SplitFormatError, match="missing file"):
        LS.read_split(tmp_path / "nope.pkl")


def test_episodes_keep_what_the_dataset_has_and_count_the_rest(tiny_world, tmp_path, capsys):
    s = load_scene(tiny_world / "FloorPlan22")
    from tsnav.sim.batch import SceneBank

    bank = SceneBank([s], success_distance=1.0)
    succ, dist = bank.success, bank.dist
    present = [c for c in range(22) if succ[:, c].any()]
    c = present[0]
    from tsnav.constants import TARGET_CATEGORIES

    t = TARGET_CATEGORIES[c]
    ok = np.flatnonzero((dist[:, c] > 0) & (dist[:, c] < 10**6))
    at_goal = np.flatnonzero(dist[:, c] == 0)
    absent = next(x for x in TARGET_CATEGORIES if not succ[:, TARGET_CATEGORIES.index(x)].any())
    good = [LS.split_record("FloorPlan22", s.keys[i], t, []) for i in ok[:5]]
    recs = good + [
        LS.split_record("FloorPlan29", "0.00|0.00|0|0", t, []),  # scene not in DATA
        LS.split_record("FloorPlan22_physics", "9.75|9.75|0|0", t, []),  # start not a state
        LS.split_record("FloorPlan22", s.keys[ok[0]], absent, []),  # target not in scene
        LS.split_record("FloorPlan22", s.keys[at_goal[0]], t, []),  # already succeeds
        {"scene": "FloorPlan22", "state": str(s.keys[ok[1]]), "goal_object_type": "Vase", "task_data": []},  # no target
    ]
    a, b = tmp_path / "kitchen_test_22.pkl", tmp_path / "kitchen_val_22.pkl"
    LS.write_split(a, recs[:7])
    LS.write_split(b, recs[7:])
    out = tmp_path / "eps.json"
    assert main(["thor", "episodes", str(a), str(b), "--data", str(tiny_world), "--out", str(out)]) == 0
    line = capsys.readouterr().out.splitlines()[0]
    assert line == (
        "10 episodes read, 5 kept, 5 dropped (2 target not in scene, 1 scene not in DATA, "
        "1 start not a state, 1 start already succeeds)"
    )
    from tsnav.sim.episodes import episodes_to_arrays, read_episodes

    eps, meta = read_episodes(out)
    assert [e.start for e in eps] == [r["state"] for r in good] and {e.target for e in eps} == {t}
    assert [e.optimal_length for e in eps] == [int(dist[i, c]) for i in ok[:5]]
    assert meta["dropped"]["scene not in DATA"] == 1 and meta["success_distance"] == 1.0
    episodes_to_arrays(SceneBank.from_root(tiny_world, None), eps, check=True)
    # an existing output is kept unless --force
    assert main(["thor", "episodes", str(a), "--data", str(tiny_world), "--out", str(out)]) == 2
    assert main(["thor", "episodes", str(a), "--data", str(tiny_world), "--out", str(out), "--force"]) == 0
    # under the lineage's protocol the start that already sees the target is kept (L* = 0) and counted
    capsys.readouterr()
    lin = tmp_path / "eps_lineage.json"
    assert (
        main(
            ["thor", "episodes", str(a), str(b), "--data", str(tiny_world), "--out", str(lin), "--protocol", "lineage"]
        )
        == 0
    )
    lbank = SceneBank([s], protocol="lineage")
    zero = 1 + int((lbank.dist[ok[:5], c] == 0).sum())  # the paper's start-success one, and any the map adds
    line = capsys.readouterr().out.splitlines()[0]
    assert line == (
        f"10 episodes read, 6 kept ({zero} start already succeeds), 4 dropped (2 target not in scene, "
        "1 scene not in DATA, 1 start not a state)"
    )
    eps, meta = read_episodes(lin)
    assert meta["protocol"] == "lineage" and eps[-1].start == str(s.keys[at_goal[0]]) and eps[-1].optimal_length == 0
    assert [e.optimal_length for e in eps[:5]] == [int(lbank.dist[i, c]) for i in ok[:5]]
    assert (
        main(
            ["thor", "episodes", str(a), "--data", str(tiny_world), "--out", str(lin), "--force", "--protocol", "nope"]
        )
        == 2
    )
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
