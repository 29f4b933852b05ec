"""tsnav analyze lever-table: paired differences from a base run with bootstrap intervals."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tsnav.analyze import lever_table as lt
from tsnav.metrics import EpisodeRecord, metrics, write_records


def _records(success: list[bool], path: list[int], k_offset: int = 0) -> list[EpisodeRecord]:
    return [
        EpisodeRecord(
            success=s,
            path_length=p,
            optimal_length=4 + (i % 5),
            entered_pathfinding=bool(i % 3),
            pathfinding_start_step=2 if i % 3 else None,
            search_path_length=2,
            optimal_search_length=2,
            pathfinding_path_length=p - 2 if i % 3 else None,
            optimal_pathfinding_length=2 + (i % 5) if i % 3 else None,
            scene=f"FloorPlan{22 + (i + k_offset) % 3}",
            start=f"{i}|0|0|0",
            target="Mug",
        )
        for i, (s, p) in enumerate(zip(map(bool, success), map(int, path)))
    ]


def _eval_folder(tmp_path, name, records, protocol="lineage"):
    d = tmp_path / name / protocol
    d.mkdir(parents=True)
    write_records(d / "records.jsonl", records)
    return tmp_path / name


def test_identical_lever_has_zero_difference(tmp_path):
    rng = np.random.default_rng(0)
    recs = _records(list(rng.random(60) < 0.6), list(rng.integers(4, 20, 60)))
    base, same = _eval_folder(tmp_path, "base", recs), _eval_folder(tmp_path, "same", recs)
    t = lt.lever_table(("base", base), [("same", same)], resamples=200)["lineage"]
    assert t["episodes"] == 60
    d = t["rows"][1]["delta"]
    for m in ("SR", "SPL", "NSNPL"):
        assert d[m]["value"] == 0.0 and d[m]["ci95"] == [0.0, 0.0]


def test_values_are_the_metrics_of_the_records_and_intervals_hold_them(tmp_path):
    rng = np.random.default_rng(1)
    succ = list(rng.random(200) < 0.5)
    paths = list(rng.integers(4, 25, 200))
    base_recs = _records(succ, paths)
    # the lever succeeds where the base did, and in 30 more episodes: a positive SR difference of 0.15
    more = [s or (i < 60 and not s and i % 2 == 0) for i, s in enumerate(succ)]
    gained = sum(m and not s for m, s in zip(more, succ))
    lever_recs = _records(more, paths)
    base = _eval_folder(tmp_path, "base", base_recs)
    lever = _eval_folder(tmp_path, "lever", lever_recs)
    t = lt.lever_table(("base", base), [("lever", lever)], resamples=400, seed=3)["lineage"]
    ref_b, ref_l = metrics(base_recs, "lineage"), metrics(lever_recs, "lineage")
    b, v = t["rows"][0]["ALL"], t["rows"][1]["ALL"]
    for m in ("SR", "SPL", "SSR", "SSSPL", "NSNPL"):
        assert b[m]["value"] == pytest.approx(ref_b[m]) and v[m]["value"] == pytest.approx(ref_l[m])
        lo, hi = v[m]["ci95"]
        assert lo <= v[m]["value"] <= hi
    d = t["rows"][1]["delta"]["SR"]
    assert d["value"] == pytest.approx(gained / 200)
    lo, hi = d["ci95"]
    assert 0 < lo <= d["value"] <= hi  # every resample keeps the gain non-negative; pairing keeps it narrow
    assert hi - lo < v["SR"]["ci95"][1] - v["SR"]["ci95"][0]  # narrower than the unpaired interval
    assert t["rows"][1]["L>=5"]["SR"]["value"] == pytest.approx(
        metrics([r for r in lever_recs if r.optimal_length + 1 >= 5], "lineage")["SR"]
    )


def test_other_episodes_are_refused(tmp_path):
    base = _eval_folder(tmp_path, "base", _records([True] * 10, [5] * 10))
    other = _eval_folder(tmp_path, "other", _records([True] * 10, [5] * 10, k_offset=1))
    with pytest.raises(ValueError, match="not the base's episodes"):
        lt.lever_table(("base", base), [("other", other)], resamples=100)


def test_command_writes_json_and_names_a_missing_folder(tmp_path, capsys):
    recs = _records([True, False] * 20, [6] * 40)
    base = _eval_folder(tmp_path, "base", recs)
    lever = _eval_folder(tmp_path, "lever", list(recs))
    out = tmp_path / "levers.json"
    argv = ["--out", str(out), "--title", "t", "--base", f"base={base}", "--lever", f"lever={lever}"]
    assert lt.main([*argv, "--resamples", "100", "--setting", "seed=3"]) == 0
    d = json.loads(out.read_text())
    assert d["format"] == "tsnav-lever-table" and d["setting"] == {"seed": "3"}
    assert [r["row"] for r in d["protocols"]["lineage"]["rows"]] == ["base", "lever"]
    assert lt.main(["--out", str(out), "--title", "t", "--base", f"base={tmp_path / 'nowhere'}"]) == 2
    assert "no records.jsonl" in capsys.readouterr().err
    assert json.loads(out.read_text()) == d  # the earlier output is kept
