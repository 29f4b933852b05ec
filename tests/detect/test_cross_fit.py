"""Cross-fitting (``tsnav detect --fold I/K``): folds of whole apartments, each fold's train tables written by a
detector that never trained on it, and the same tables as a detector trained in a world holding only the others."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

from tsnav.cli import main
from tsnav.data.detections import load_detections, read_fingerprint
from tsnav.data.folds import apartment_of, assign_folds, parse_fold
from tsnav.data.reader import list_scenes
from tsnav.detect.train import read_meta


def test_apartments_keep_their_variants_together_and_alternate():
    assert apartment_of("FloorPlan_Train3_2") == "FloorPlan_Train3"
    assert apartment_of("FloorPlan_Val1_5") == "FloorPlan_Val1"
    assert apartment_of("FloorPlan12") == "FloorPlan12"
    names = [f"FloorPlan_Train{a}_{v}" for a in (1, 2, 3) for v in (1, 2, 3, 4, 5)]
    folds = assign_folds(names, 2)
    for a in (1, 2, 3):
        assert len({folds[f"FloorPlan_Train{a}_{v}"] for v in range(1, 6)}) == 1
    assert [folds[f"FloorPlan_Train{a}_1"] for a in (1, 2, 3)] == [0, 1, 0]  # sorted apartments dealt in turn
    assert assign_folds(["FloorPlan2", "FloorPlan1", "FloorPlan201"], 2) == {
        "FloorPlan1": 0,
        "FloorPlan2": 1,
        "FloorPlan201": 0,
    }
    with pytest.raises(ValueError, match="cannot fill 3 folds"):
        assign_folds(["FloorPlan1", "FloorPlan2"], 3)


@pytest.mark.parametrize("text,message", [("1", "give I/K"), ("0/1", "at least 2"), ("2/2", "0 to 1"), ("a/b", "I/K")])
def test_bad_folds_are_named(text, message):
    with pytest.raises(ValueError, match=message):
        parse_fold(text)
    assert parse_fold(" 1 / 3 ") == (1, 3)


@pytest.fixture()
def world(tiny_world, tmp_path):
    root = tmp_path / "w"
    shutil.copytree(tiny_world, root, ignore=shutil.ignore_patterns("detections_*"))
    return root


def _detect(world, ck, *extra):
    args = ["detect", "--data", str(world), "--detector", "learned", "--checkpoint", str(ck), "--quiet"]
    args += ["--max-states-per-scene", "16", "--batch-size", "8", "--threads", "1", "--train-steps", "3"]
    return main([*args, "--no-calibrate", *extra])


def test_each_fold_is_written_by_the_detector_that_did_not_train_on_it(world, tmp_path, capsys):
    train = [p.name for p in list_scenes(world, split="train")]
    folds = assign_folds(train, 2)
    assert sorted(set(folds.values())) == [0, 1]
    for i in (0, 1):
        assert _detect(world, tmp_path / f"ck{i}", "--name", "cf", "--fold", f"{i}/2") == 0
        out = capsys.readouterr().out
        assert f"evaluation of cf on fold {i}/2 scenes" in out
        assert (world / "detectors" / f"cf_eval_fold{i}of2.json").exists()
        meta = read_meta(tmp_path / f"ck{i}")
        assert sorted(meta["train_scenes"]) == sorted(n for n in train if folds[n] != i)
    fp = {n: read_fingerprint(world / n, "cf") for n in train}
    for n in train:  # every train scene has a table, made by its own fold's detector
        assert fp[n] is not None
        assert fp[n] == fp[next(m for m in train if folds[m] == folds[n])]
    assert len(set(fp.values())) == 2
    assert not any((p / "detections_cf.hdf5").exists() for p in list_scenes(world) if p.name not in train)


def test_a_fold_matches_a_detector_trained_in_a_world_of_the_other_folds(world, tmp_path):
    """The slow reference: the other folds' train scenes alone in a world of their own (links), a detector trained
    there with the same settings writes fold 0's tables; ``--fold 0/2`` must write the same ones."""
    train = [p.name for p in list_scenes(world, split="train")]
    folds = assign_folds(train, 2)
    assert _detect(world, tmp_path / "ck", "--name", "cf", "--fold", "0/2", "--no-eval") == 0
    view = tmp_path / "view"
    view.mkdir()
    for n in train:
        if folds[n] != 0:
            os.symlink(world / n, view / n)
    ref = tmp_path / "ref"
    assert _detect(view, ref, "--name", "ref", "--no-eval") == 0
    assert _detect(world, ref, "--name", "ref", "--split", "train", "--no-eval") == 0  # trained: writes only
    for n in train:
        if folds[n] == 0:
            assert read_fingerprint(world / n, "cf") == read_fingerprint(world / n, "ref")
            a, b = load_detections(world / n, "cf"), load_detections(world / n, "ref")
            np.testing.assert_array_equal(a.scores, b.scores)
            np.testing.assert_array_equal(a.boxes, b.boxes)


def test_cross_fitting_refuses_what_would_leak_or_cannot_work(world, tmp_path, capsys):
    assert _detect(world, tmp_path / "ck0", "--name", "cf", "--fold", "0/2", "--no-eval") == 0
    capsys.readouterr()
    assert _detect(world, tmp_path / "ck0", "--name", "cf", "--fold", "1/2", "--no-eval") == 2
    err = capsys.readouterr().err
    assert "was trained on scenes of fold 1/2" in err and "its own checkpoint" in err
    assert main(["detect", "--data", str(world), "--detector", "oracle", "--fold", "0/2"]) == 2
    assert "needs --detector learned" in capsys.readouterr().err
    assert _detect(world, tmp_path / "x", "--fold", "0/2", "--split", "val") == 2
    assert "train scenes only" in capsys.readouterr().err
    assert _detect(world, tmp_path / "x", "--fold", "2/2") == 2
    assert "--fold: fold '2/2'" in capsys.readouterr().err
    assert _detect(world, tmp_path / "x", "--fold", "0/9") == 2
    assert "cannot fill 9 folds" in capsys.readouterr().err


def test_a_checkpoint_that_saw_the_fold_in_any_earlier_segment_is_refused(world, tmp_path, capsys):
    """Trained outside fold 0 (so on fold 1), then on fold 0 alone: its last segment never saw fold 1, its history
    did; ``--fold 1/2`` is refused before it trains, and nothing is written."""
    train = [p.name for p in list_scenes(world, split="train")]
    folds = assign_folds(train, 2)
    ck = tmp_path / "ck"
    assert _detect(world, ck, "--name", "cf", "--fold", "0/2", "--no-eval") == 0
    view = tmp_path / "fold0"
    view.mkdir()
    for n in train:
        if folds[n] == 0:
            os.symlink(world / n, view / n)

    def run(data, steps, *extra):
        args = ["detect", "--data", str(data), "--detector", "learned", "--checkpoint", str(ck), "--quiet"]
        args += ["--max-states-per-scene", "16", "--batch-size", "8", "--threads", "1", "--train-steps", str(steps)]
        return main([*args, "--no-calibrate", *extra])

    assert run(view, 5, "--name", "seg2", "--no-eval") == 0
    meta = read_meta(ck)
    assert sorted(meta["train_scenes"]) == sorted(n for n in train if folds[n] == 0)
    assert sorted(meta["seen_scenes"]) == sorted(train)
    capsys.readouterr()
    assert run(world, 6, "--name", "cf1", "--fold", "1/2") == 2
    err = capsys.readouterr().err
    assert "was trained on scenes of fold 1/2" in err and len(err.strip().splitlines()) == 1
    assert read_meta(ck)["step"] == 5  # refused before training
    assert not any((world / n / "detections_cf1.hdf5").exists() for n in train)
