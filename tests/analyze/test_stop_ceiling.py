"""tsnav analyze stop-ceiling: an evaluation's SR and SPL with Done at the first success state reached."""

from __future__ import annotations

import json

import pytest

from tsnav.analyze import stop_ceiling as sc
from tsnav.cli import main
from tsnav.eval.runner import Trajectory, write_trajectories
from tsnav.metrics import EpisodeRecord, summarize, write_records

# (success, path, optimal, first success frame): a success that walked on 4 actions past its first success state; a
# failure that passed one at frame 3; a failure that never reached one; a success that stopped at once
EPISODES = [(True, 10, 6, 6), (False, 12, 2, 3), (False, 100, 5, -1), (True, 4, 4, 4)]


def _folder(tmp_path, protocol: str, frames=None):
    d = tmp_path / protocol
    d.mkdir(parents=True)
    records = [
        EpisodeRecord(success=s, path_length=p, optimal_length=o, scene="FloorPlan22", target="Mug", start=f"{i}|0|0|0")
        for i, (s, p, o, _) in enumerate(EPISODES)
    ]
    write_records(d / "records.jsonl", records)
    traj = [
        Trajectory(episode=i, scene="FloorPlan22", target="Mug", keys=["k"] * (p + 1), actions=[0] * p, success_frame=f)
        for i, (_, p, _, f) in enumerate(EPISODES)
    ]
    if frames is not None:
        for t, f in zip(traj, frames):
            t.success_frame = f
    write_trajectories(d / "trajectories.jsonl", traj)
    (d / "metrics.json").write_text(json.dumps({"protocol": protocol}))
    return d, records


def test_paper_protocol_by_hand(tmp_path):
    d, records = _folder(tmp_path, "paper")
    res = sc.stop_ceiling(d)
    # the agent row is the evaluation's own metrics
    assert res["rows"]["agent"]["SR"] == pytest.approx(50.0)
    assert res["rows"]["agent"]["SPL"] == pytest.approx(100 * summarize(records, protocol="paper")["ALL"]["SPL"])
    # stopped: 3 of 4 succeed, paths 6, 3 and 4 against optimal 6, 2 and 4 (paper: L* / max(L, L*))
    assert res["rows"]["stop at the first success state"]["SR"] == pytest.approx(75.0)
    assert res["rows"]["stop at the first success state"]["SPL"] == pytest.approx(100 * (1 + 2 / 3 + 1) / 4)


def test_lineage_protocol_counts_its_length_convention(tmp_path):
    d, _ = _folder(tmp_path, "lineage")
    res = sc.stop_ceiling(d)
    # lineage: both lengths count one more, (L* + 1) / (max(L, L*) + 1)
    assert res["rows"]["stop at the first success state"]["SPL"] == pytest.approx(100 * (1 + 3 / 4 + 1) / 4)


def test_command_and_refusals(tmp_path, capsys):
    d, _ = _folder(tmp_path, "paper")
    out = tmp_path / "c.json"
    assert main(["analyze", "stop-ceiling", str(d), "--json", str(out)]) == 0
    assert "Done at the first success state it reaches: SR 75.00" in capsys.readouterr().out
    assert json.loads(out.read_text())["results"][0]["rows"]["agent"]["SR"] == pytest.approx(50.0)
    assert main(["analyze", "stop-ceiling", str(tmp_path / "nothing")]) == 2
    assert "no records.jsonl" in capsys.readouterr().err
    old, _ = _folder(tmp_path / "old", "paper", frames=[None] * len(EPISODES))
    assert main(["analyze", "stop-ceiling", str(old)]) == 2
    assert "without success_frame" in capsys.readouterr().err
    with pytest.raises(ValueError, match="3 records for 4 trajectories"):
        sc.stopped_records([EpisodeRecord(success=False, path_length=1, optimal_length=1)] * 3, [0, 1, 2, 3])
