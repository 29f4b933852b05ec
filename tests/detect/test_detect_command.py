"""``tsnav detect`` on a copy of the tiny world: tables for every scene, skip on rerun, evaluation, errors."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from tsnav.cli import main
from tsnav.data.reader import list_scenes, load_scene
from tsnav.data.detections import load_detections


@pytest.fixture()
def world(tiny_world, tmp_path):
    root = tmp_path / "w"
    shutil.copytree(tiny_world, root, ignore=shutil.ignore_patterns("detections_*"))  # other tests write some
    return root


def test_oracle_command(world, capsys):
    assert main(["detect", "--data", str(world), "--detector", "oracle", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "5 scenes written, 0 already done" in out and "presence AP" in out and "ECE" in out
    for p in list_scenes(world):
        det = load_detections(p, "oracle")
        np.testing.assert_array_equal(det.keys, load_scene(p).keys)
        assert det.detector == "oracle"
    rep = json.loads((world / "detectors" / "oracle_eval_val.json").read_text())
    assert rep["mean_presence_ap"] == pytest.approx(1.0) and rep["mean_box_ap50"] == pytest.approx(1.0)
    assert main(["detect", "--data", str(world), "--detector", "oracle", "--quiet", "--no-eval"]) == 0
    assert "0 scenes written, 5 already done" in capsys.readouterr().out


def test_learned_command_trains_resumes_and_refuses_stale_tables(world, capsys):
    ck = world / "ck"
    args = [
        "detect",
        "--data",
        str(world),
        "--detector",
        "learned",
        "--checkpoint",
        str(ck),
        "--quiet",
        "--max-states-per-scene",
        "16",
        "--batch-size",
        "8",
        "--threads",
        "1",
    ]
    assert main(args + ["--train-steps", "3"]) == 0
    out = capsys.readouterr().out
    assert "trained the detector 0 -> 3 steps" in out and "temperature" in out and "box AP@0.5" in out
    newest = ck / "checkpoints" / "ckpt_000000003"
    assert (newest / "model.safetensors").exists() and (newest / "optimizer.safetensors").exists()
    meta = json.loads((newest / "state.json").read_text())
    assert meta["step"] == 3 and meta["calibrated_step"] == 3
    for p in list_scenes(world):
        det = load_detections(p, "learned")
        assert det.fingerprint == meta["fingerprint"] and det.feature_dim == meta["model"]["dim"]
    # Same checkpoint again: nothing to train, nothing to write.
    assert main(args + ["--no-eval"]) == 0
    out = capsys.readouterr().out
    assert "at step 3" in out and "0 scenes written, 5 already done" in out
    # Training on changes the detector: the old tables are refused unless --overwrite.
    assert main(args + ["--train-steps", "4", "--no-eval"]) == 2
    assert "made by another detector" in capsys.readouterr().err
    assert main(args + ["--train-steps", "4", "--no-eval", "--overwrite"]) == 0
    assert "5 scenes written" in capsys.readouterr().out
    # Two worker processes write the same tables as this process did
    one = {p.name: load_detections(p, "learned") for p in list_scenes(world)}
    for p in list_scenes(world):
        (p / "detections_learned.hdf5").unlink()
    assert main(args + ["--no-eval", "--workers", "2"]) == 0
    assert "5 scenes written" in capsys.readouterr().out
    for p in list_scenes(world):
        two = load_detections(p, "learned")
        assert two.fingerprint == one[p.name].fingerprint
        np.testing.assert_array_equal(two.scores, one[p.name].scores)
        np.testing.assert_array_equal(two.boxes, one[p.name].boxes)
        np.testing.assert_array_equal(two.features, one[p.name].features)
    assert main(args + ["--no-eval", "--workers", "0"]) == 2
    assert "--workers must be at least 1" in capsys.readouterr().err
    # Hard-negative sampling from the command line: applies from the checkpoint's step, mined and recorded there.
    assert (
        main(
            args
            + [
                "--train-steps",
                "5",
                "--no-eval",
                "--overwrite",
                "--hard-negative-weight",
                "3",
                "--hard-negative-threshold",
                "0.2",
            ]
        )
        == 0
    )
    meta = json.loads((ck / "checkpoints" / "ckpt_000000005" / "state.json").read_text())
    assert meta["train"]["hard_negative_weight"] == 3.0 and meta["train"]["hard_negative_threshold"] == 0.2
    assert meta["sampling_changes"][-1] == {"step": 4, "hard_negative_weight": 3.0, "hard_negative_threshold": 0.2}
    assert json.loads((ck / "hard_negatives.json").read_text())["step"] == 4


def test_bad_input_is_one_line(world, tmp_path, capsys):
    assert main(["detect", "--data", str(tmp_path / "nope"), "--detector", "oracle"]) == 2
    err = capsys.readouterr().err.strip()
    assert "no such dataset folder" in err and len(err.splitlines()) == 1
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["detect", "--data", str(world), "--detector", "learned", "--checkpoint", str(f)]) == 2
    assert "is a file" in capsys.readouterr().err
    assert main(["detect", "--data", str(world), "--detector", "oracle", "--name", "a/b"]) == 2
    assert "detector name" in capsys.readouterr().err
    assert main(["detect", "--data", str(world), "--detector", "learned", "--train-steps", "0"]) == 2
    assert "--train-steps" in capsys.readouterr().err
    assert main(["detect", "--data", str(world), "--detector", "learned", "--repeat-threshold", "-0.5"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--repeat-threshold must be >= 0" in err and len(err.splitlines()) == 1
    for flags, says in (
        (["--hard-negative-weight", "-2"], "--hard-negative-weight must be a finite number >= 0"),
        (["--hard-negative-weight", "inf"], "--hard-negative-weight must be a finite number >= 0"),
        (
            ["--hard-negative-weight", "4", "--hard-negative-threshold", "1.5"],
            "--hard-negative-threshold must be in (0, 1)",
        ),
        (["--hard-negative-threshold", "0.6"], "--hard-negative-threshold needs --hard-negative-weight"),
        (["--presence-pos-weight", "0"], "--presence-pos-weight must be a finite number > 0"),
        (["--focal-alpha", "1"], "--focal-alpha must be in (0, 1)"),
    ):
        assert main(["detect", "--data", str(world), "--detector", "learned", *flags]) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and len(err.splitlines()) == 1


def test_learned_command_fits_nothing_on_val_without_test_scenes(world, capsys):
    """In a world without test scenes (robothor-real: its val scenes are the benchmark) the learned detector keeps
    temperature 1 instead of being calibrated on val; --no-calibrate does the same in any world."""
    args = ["detect", "--data", str(world), "--detector", "learned", "--quiet", "--max-states-per-scene", "16"]
    args += ["--batch-size", "8", "--threads", "1", "--train-steps", "2", "--no-eval"]
    assert main([*args, "--checkpoint", str(world / "ck1"), "--name", "a", "--no-calibrate"]) == 0
    assert "no calibration (--no-calibrate)" in capsys.readouterr().out
    from tsnav.detect.train import val_is_benchmark

    test = list_scenes(world, "test")
    assert test and not val_is_benchmark(world)
    for p in test:
        shutil.rmtree(p)
    if (world / "index.json").exists():
        (world / "index.json").unlink()
    assert val_is_benchmark(world)
    assert main([*args, "--checkpoint", str(world / "ck2"), "--name", "b"]) == 0
    assert "this world has no test scenes" in capsys.readouterr().out
    for ck in ("ck1", "ck2"):
        meta = json.loads((world / ck / "checkpoints" / "ckpt_000000002" / "state.json").read_text())
        assert meta["calibrated_step"] == -1 and meta["temperature"] == 1.0
    # the refusal lives in calibrate itself, for every caller, and writes nothing
    from tsnav.detect.train import BenchmarkSplit, calibrate

    with pytest.raises(BenchmarkSplit, match="no test scenes"):
        calibrate(world, world / "ck2", split="val")
    meta = json.loads((world / "ck2" / "checkpoints" / "ckpt_000000002" / "state.json").read_text())
    assert meta["calibrated_step"] == -1


def test_finished_checkpoint_writes_tables_for_a_world_without_train_scenes(world, tmp_path, capsys):
    """A trained checkpoint applies to a benchmark's val world (no train scenes): it keeps its own architecture and
    writes the tables; asked to train on there, it is refused in one line naming its step."""
    ck = tmp_path / "ck"
    args = ["detect", "--detector", "learned", "--checkpoint", str(ck), "--quiet", "--threads", "1"]
    args += ["--max-states-per-scene", "16", "--batch-size", "8", "--no-eval", "--no-calibrate"]
    assert main([*args, "--data", str(world), "--train-steps", "2", "--name", "a"]) == 0
    val_only = tmp_path / "val_only"
    val_only.mkdir()
    for p in list_scenes(world, "val"):
        shutil.copytree(p, val_only / p.name)
    assert not list_scenes(val_only, "train")
    capsys.readouterr()
    assert main([*args, "--data", str(val_only), "--train-steps", "2", "--name", "a"]) == 0
    assert "detector checkpoint" in capsys.readouterr().out
    for p in list_scenes(val_only):
        np.testing.assert_array_equal(load_detections(p, "a").scores, load_detections(world / p.name, "a").scores)
    assert main([*args, "--data", str(val_only), "--train-steps", "5", "--name", "b"]) == 2
    err = capsys.readouterr().err
    assert "no complete train scene to train the detector on" in err and "at step 2 of 5" in err
    assert not any((p / "detections_b.hdf5").exists() for p in list_scenes(val_only))


def test_training_on_from_a_copy_of_a_shipped_detector_uses_what_it_trained(world, tmp_path, capsys):
    """A copy of a shipped detector (its files at the top of the folder, no optimiser state) trained on writes its
    checkpoints under checkpoints/, and from then on the folder means the newest of those, not the copy."""
    args = ["detect", "--data", str(world), "--detector", "learned", "--quiet", "--threads", "1"]
    args += ["--max-states-per-scene", "16", "--batch-size", "8", "--no-eval", "--no-calibrate"]
    assert main([*args, "--checkpoint", str(tmp_path / "ck"), "--train-steps", "2", "--name", "a"]) == 0
    flat = tmp_path / "flat"  # the shipped layout: model.safetensors and state.json at the top
    flat.mkdir()
    for name in ("model.safetensors", "state.json"):
        shutil.copy(tmp_path / "ck" / "checkpoints" / "ckpt_000000002" / name, flat / name)
    start = json.loads((flat / "state.json").read_text())["fingerprint"]
    capsys.readouterr()
    assert main([*args, "--checkpoint", str(flat), "--train-steps", "4", "--name", "b"]) == 0
    assert "trained the detector 2 -> 4 steps" in capsys.readouterr().out
    trained = json.loads((flat / "checkpoints" / "ckpt_000000004" / "state.json").read_text())["fingerprint"]
    assert trained != start
    p = list_scenes(world)[0]
    assert load_detections(p, "b").fingerprint == trained
    assert main([*args, "--checkpoint", str(flat), "--train-steps", "4", "--name", "c"]) == 0
    assert "at step 4" in capsys.readouterr().out and load_detections(p, "c").fingerprint == trained


def test_a_broken_newest_checkpoint_is_set_aside_and_training_resumes(world, tmp_path, capsys):
    """With train scenes at hand, a newest checkpoint whose JSON is broken is set aside and training resumes from
    the one before it (the check for a world without train scenes reads nothing then)."""
    ck = tmp_path / "ck"
    args = ["detect", "--data", str(world), "--detector", "learned", "--checkpoint", str(ck), "--quiet"]
    args += ["--threads", "1", "--max-states-per-scene", "16", "--batch-size", "8", "--no-eval", "--no-calibrate"]
    assert main([*args, "--train-steps", "2", "--name", "a"]) == 0
    assert main([*args, "--train-steps", "4", "--name", "b"]) == 0
    (ck / "checkpoints" / "ckpt_000000004" / "state.json").write_text("{not json")
    capsys.readouterr()
    assert main([*args, "--train-steps", "5", "--name", "c"]) == 0
    assert "trained the detector 2 -> 5 steps" in capsys.readouterr().out


def test_a_shipped_detector_is_its_own_files_whatever_was_trained_from_it(world, tmp_path, monkeypatch):
    """A shipped name means the files at the top of its folder: checkpoints trained on from that folder (say, with
    --checkpoint pointing into an editable install) do not replace it."""
    from tsnav.detect import shipped

    folder = tmp_path / "robothor3"
    shutil.copytree(shipped.SHIPPED["robothor3"], folder)
    want = shipped.shipped_meta("robothor3")
    monkeypatch.setitem(shipped.SHIPPED, "robothor3", folder)
    args = ["detect", "--data", str(world), "--detector", "learned", "--checkpoint", str(tmp_path / "ck"), "--quiet"]
    args += ["--threads", "1", "--max-states-per-scene", "16", "--batch-size", "8", "--no-eval", "--no-calibrate"]
    assert main([*args, "--train-steps", "2", "--name", "a"]) == 0
    shutil.copytree(tmp_path / "ck" / "checkpoints", folder / "checkpoints")
    det = shipped.shipped_detector(128, name="robothor3")
    assert det.fingerprint == want["fingerprint"] and det.meta["step"] == want["step"] == 20000
    assert shipped.shipped_meta("robothor3")["step"] == 20000
