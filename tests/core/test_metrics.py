"""Metrics of paper IV-A on hand-computed record sets, and against a plain-Python reference."""

import json

import numpy as np
import pytest

from tsnav.metrics import (
    EpisodeRecord,
    format_table,
    metrics,
    nsnpl,
    read_records,
    sr,
    spl,
    ssr,
    ssspl,
    summarize,
    write_records,
)


def _records():
    return [
        # success, L=10 vs L*=5; searched 4 vs 2; pathfinding 6 vs 3
        EpisodeRecord(True, 10, 5, True, 4, 4, 2, 6, 3, room_type="kitchen"),
        # failure after entering pathfinding: searching 3 vs 3 counts for SSSPL, nothing for NSNPL
        EpisodeRecord(False, 20, 8, True, 3, 3, 3, 17, 4, room_type="kitchen"),
        # target detected in the first frame (0 / 0 searching), optimal pathfinding
        EpisodeRecord(True, 3, 3, True, 0, 0, 0, 3, 3, room_type="bedroom"),
        # never found the target
        EpisodeRecord(False, 100, 4, False, None, 100, 2, None, None, room_type="bedroom"),
    ]


def test_hand_computed_all():
    r = _records()
    assert sr(r) == pytest.approx(0.5)
    assert spl(r) == pytest.approx((0.5 + 0 + 1 + 0) / 4)
    assert ssr(r) == pytest.approx(0.75)
    assert ssspl(r) == pytest.approx((0.5 + 1 + 1 + 0) / 4)
    # NSNPL divides by K_Nav = 3, not K = 4
    assert nsnpl(r) == pytest.approx((0.5 + 0 + 1) / 3)


def test_hand_computed_long_subset_and_rooms():
    s = summarize(_records())
    long_ = s["L>=5"]
    assert long_["episodes"] == 2 and long_["K_nav"] == 2
    assert long_["SR"] == pytest.approx(0.5)
    assert long_["SPL"] == pytest.approx(0.25)
    assert long_["SSR"] == pytest.approx(1.0)
    assert long_["SSSPL"] == pytest.approx(0.75)
    assert long_["NSNPL"] == pytest.approx(0.25)
    assert s["rooms"]["bedroom"]["ALL"]["SPL"] == pytest.approx(0.5)
    assert s["rooms"]["bedroom"]["L>=5"]["episodes"] == 0
    table = format_table(s)
    assert "SSSPL" in table and "37.50" in table  # SPL ALL in percent


def test_empty_and_no_pathfinding():
    assert metrics([])["SR"] == 0.0 and nsnpl([]) == 0.0
    r = [EpisodeRecord(False, 5, 5, False, None, 5, 3)]
    assert nsnpl(r) == 0.0 and ssspl(r) == 0.0 and ssr(r) == 0.0


def _reference(records):
    """Plain-Python transcription of the paper's formulas."""

    def ratio(o, a):
        return 1.0 if max(a, o) == 0 else o / max(a, o)

    k = len(records)
    k_nav = sum(1 for r in records if r.entered_pathfinding)
    out = {
        "SR": sum(r.success for r in records) / k,
        "SPL": sum(r.success * ratio(r.optimal_length, r.path_length) for r in records) / k,
        "SSR": k_nav / k,
        "SSSPL": sum(ratio(r.optimal_search_length, r.search_path_length) for r in records if r.entered_pathfinding)
        / k,
        "NSNPL": (
            sum(
                ratio(r.optimal_pathfinding_length, r.pathfinding_path_length)
                for r in records
                if r.entered_pathfinding and r.success
            )
            / k_nav
        )
        if k_nav
        else 0.0,
    }
    return out


def test_random_records_match_reference():
    rng = np.random.default_rng(0)
    recs = []
    for _ in range(300):
        opt = int(rng.integers(1, 15))
        length = int(opt + rng.integers(0, 30))
        nav = bool(rng.random() < 0.7)
        ls = int(rng.integers(0, length + 1)) if nav else length
        ols = int(rng.integers(0, ls + 1)) if nav else int(rng.integers(0, 10))
        recs.append(
            EpisodeRecord(
                success=bool(nav and rng.random() < 0.6),
                path_length=length,
                optimal_length=opt,
                entered_pathfinding=nav,
                pathfinding_start_step=ls if nav else None,
                search_path_length=ls,
                optimal_search_length=ols,
                pathfinding_path_length=(length - ls) if nav else None,
                optimal_pathfinding_length=int(rng.integers(0, length - ls + 1)) if nav else None,
            )
        )
    got, ref = metrics(recs), _reference(recs)
    for k, v in ref.items():
        assert got[k] == pytest.approx(v, abs=1e-12), k


def test_jsonl_round_trip(tmp_path):
    recs = _records()
    p = tmp_path / "out" / "records.jsonl"
    write_records(p, recs)
    assert read_records(p) == recs
    assert len(p.read_text().splitlines()) == 4
    bad = tmp_path / "bad.jsonl"
    bad.write_text(json.dumps({"success": True, "nonsense": 1}) + "\n")
    with pytest.raises(ValueError, match="bad.jsonl:1"):
        read_records(bad)
