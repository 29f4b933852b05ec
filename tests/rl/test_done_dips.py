"""Done dips found in training logs (`tsnav.rl.done_dips`)."""

import json

import pytest

from tsnav.rl.done_dips import done_dips, done_share, run_done_dips


def rec(u, rate, length=30.0, p=None):
    return {"update": u, "done_rate": rate, "length": length, "done_prob": rate if p is None else p}


def test_share_of_episodes_ended_by_done():
    assert done_share(rec(1, 0.16, 6.0)) == pytest.approx(0.96)
    assert done_share(rec(1, 0.5, 6.0)) == 1.0 and done_share({"update": 1, "length": 3.0}) is None


def test_dips_found_measured_and_marked_recovered():
    log = [
        rec(10, 0.16, 6.0),
        rec(20, 0.001, p=0.004),
        rec(30, 0.0008),
        rec(40, 0.02, 24.0),
        rec(50, 0.0015),
        {"update": 55},
        rec(60, 0.0),
    ]
    d = done_dips(log)
    assert d == [
        {"start": 20, "end": 30, "min_done_prob": 0.0008, "recovered": True, "updates": 20},
        {"start": 50, "end": 60, "min_done_prob": 0.0, "recovered": False, "updates": 20},
    ]
    # a slow learner: Done rarely succeeds but most episodes still end with it
    assert done_dips([rec(10, 0.006, 27.0), rec(20, 0.01, 25.0)]) == [] and done_dips([]) == []
    assert done_dips([rec(10, 0.001)]) == [
        {"start": 10, "end": 10, "min_done_prob": 0.001, "recovered": False, "updates": 10}
    ]
    assert done_dips(log, threshold=0.03) == [
        {"start": 30, "end": 30, "min_done_prob": 0.0008, "recovered": True, "updates": 10},
        {"start": 60, "end": 60, "min_done_prob": 0.0, "recovered": False, "updates": 10},
    ]


def test_run_folder(tmp_path):
    (tmp_path / "log.jsonl").write_text("\n".join(json.dumps(r) for r in [rec(10, 0.5), rec(20, 0.001)]) + "\n{torn")
    assert run_done_dips(tmp_path) == [
        {"start": 20, "end": 20, "min_done_prob": 0.001, "recovered": False, "updates": 10}
    ]
    assert run_done_dips(tmp_path / "nothing") == []


def test_experiment_line():
    from tsnav.pipeline.experiment import dips_line

    assert dips_line({"jobs": 3, "with_dips": []}).endswith(": 0 of 3 jobs.")
    line = dips_line(
        {
            "jobs": 3,
            "with_dips": [
                {
                    "row": "tsrm",
                    "seed": 1,
                    "dips": [
                        {"start": 50, "end": 140, "recovered": True},
                        {"start": 900, "end": 990, "recovered": False},
                    ],
                }
            ],
        }
    )
    assert line.endswith("1 of 3 jobs: tsrm seed 1: updates 50-140, updates 900-990 (not recovered).")
