"""The detector shipped with tsnav (:mod:`tsnav.detect.shipped`): its weights match the fingerprint recorded
beside them, it was trained on the ithor-real training rooms only and calibrated on the val rooms, it refuses a
world of another frame size and damaged weights in one line, and in real rooms it never saw in training it
finds the targets (issue 14: the demo's stage switch fires)."""

import shutil

import numpy as np
import pytest

from tsnav.constants import C_TARGET
from tsnav.data.names import ithor_scenes
from tsnav.data.reader import list_scenes, load_scene
from tsnav.detect import shipped
from tsnav.detect.evaluate import average_precision
from tsnav.detect.oracle import ground_truth
from tsnav.detect.quality import scene_targets
from tsnav.errors import CommandError

pytestmark = pytest.mark.usefixtures("one_torch_thread")


ITHOR_SHIPPED = sorted(n for n in shipped.SHIPPED if not n.startswith("robothor"))


@pytest.mark.parametrize("name", ITHOR_SHIPPED)
def test_weights_match_their_fingerprint_and_provenance(name):
    det = shipped.shipped_detector(128, name=name)
    meta = shipped.shipped_meta(name)
    assert det.fingerprint == meta["fingerprint"] and det.fingerprint.startswith("learned-") and meta["name"] == name
    assert det.image_size == 128 and det.temperature == pytest.approx(meta["temperature"])
    assert det.class_set == "ithor22"
    assert meta["calibration_split"] == "val" and meta["calibrated_step"] == meta["step"]
    # trained on the 80 training rooms, none of the val or test rooms
    assert sorted(meta["train_scenes"]) == sorted(ithor_scenes(split="train"))
    # learned4 continues learned3 with stronger class balancing
    assert shipped.DEFAULT_SHIPPED == "learned4" and shipped.shipped_meta("learned4")["step"] == 41000
    assert shipped.shipped_meta("learned3")["step"] == 29000
    # learned6 continues learned4 with the classes in view weighted 4x in the presence loss
    l6 = shipped.shipped_meta("learned6")
    assert l6["step"] == 43000 and l6["loss_changes"][0]["step"] == 41000
    assert l6["loss_changes"][0]["presence_pos_weight"] == 4.0
    # learned7: a wider backbone trained from nothing with learned6's loss
    l7 = shipped.shipped_meta("learned7")
    assert l7["model"]["widths"] == [64, 128, 256] and l7["step"] == 18000
    assert l7["train"]["loss"]["presence_pos_weight"] == 4.0 and l7["train"]["loss"]["focal_alpha"] == 0.5
    with pytest.raises(CommandError, match="no shipped detector named 'learned9'"):
        shipped.shipped_detector(name="learned9")


@pytest.mark.parametrize("name", ["robothor1", "robothor2", "robothor3", "robothor4", "robothor5", "robothor5hr"])
def test_robothor_detectors_saw_only_the_train_apartments(name):
    """robothor1 to robothor5hr: the 12 RoboTHOR targets, trained on the 60 train apartments and on nothing
    of the 15 val ones (they are the benchmark): not calibrated, temperature 1. robothor5hr reads 256-px frames."""
    side = 256 if name == "robothor5hr" else 128
    assert shipped.shipped_side(name) == side
    det = shipped.shipped_detector(side, name=name)
    meta = shipped.shipped_meta(name)
    assert det.fingerprint == meta["fingerprint"] and meta["name"] == name
    assert det.class_set == "robothor12" and det.num_classes == 12 and det.image_size == side
    train = [f"FloorPlan_Train{i}_{v}" for i in range(1, 13) for v in range(1, 6)]
    assert sorted(meta["train_scenes"]) == sorted(train)
    assert meta["calibration_split"] is None and meta["calibrated_step"] == -1 and det.temperature == 1.0
    assert meta["train"]["loss"]["presence_pos_weight"] == 4.0 and meta["model"]["widths"] == [32, 64, 128]
    # robothor2 is robothor1 trained on to 15,000 steps with class-balanced sampling; robothor3 is robothor2 trained
    # on to 20,000 steps in the train apartments rebuilt the val way, robothor4 robothor3 on to 25,000 there, robothor5
    # the same with the surfaces redrawn
    steps, repeat = {
        "robothor1": (5000, 0.0),
        "robothor2": (15000, 0.5),
        "robothor3": (20000, 0.5),
        "robothor4": (25000, 0.5),
        "robothor5": (25000, 0.5),
        "robothor5hr": (30000, 0.5),
    }[name]
    assert meta["step"] == steps and meta["train"]["repeat_threshold"] == repeat
    later = ("robothor3", "robothor4", "robothor5", "robothor5hr")
    assert ("rebuilt the val way" in meta.get("train_world", "")) == (name in later)
    assert ("redrawn per scene" in meta.get("train_world", "")) == (name in ("robothor5", "robothor5hr"))
    # robothor5hr: robothor5's weights carried over to 256-px frames at step 25,000
    assert meta.get("size_changes", []) == ([{"from": 128, "step": 25000, "to": 256}] if side == 256 else [])


def test_refuses_other_frame_sizes_and_damaged_weights(tmp_path, monkeypatch):
    with pytest.raises(CommandError, match=r"reads 128x128 frames .* this world has 64x64"):
        shipped.shipped_detector(64)
    from safetensors.torch import load_file, save_file

    bad = tmp_path / "weights"
    shutil.copytree(shipped.SHIPPED_DIR, bad)
    tensors = load_file(bad / "model.safetensors")
    name = sorted(tensors)[0]
    tensors[name] = tensors[name] + 1e-3
    save_file(tensors, bad / "model.safetensors")
    monkeypatch.setitem(shipped.SHIPPED, shipped.DEFAULT_SHIPPED, bad)
    with pytest.raises(CommandError, match="do not match their recorded fingerprint"):
        shipped.shipped_detector()


def test_finds_the_targets_of_rooms_it_never_saw(tiny_real):
    """On the val and test bathrooms (not among its training rooms) every target class is found: presence AP
    >= 0.9 (measured 0.95-0.99) and, for each target, a state with the target in view scoring above C_target;
    a class not in view rarely scores above 0.9 (measured: 0.08 % and 0 % of the states)."""
    det = shipped.shipped_detector(128)
    unseen = [load_scene(p) for p in list_scenes(tiny_real) if load_scene(p).meta.get("split") in ("val", "test")]
    assert len(unseen) == 2
    for s in unseen:
        d = det.detect_scene(s)
        present = ground_truth(s).present
        targets = np.flatnonzero(scene_targets(s))
        assert len(targets) == 3
        for c in targets:
            assert present[:, c].any()
            assert average_precision(d.scores[:, c], present[:, c]) >= 0.9
            assert (d.scores[present[:, c], c] > C_TARGET).any()
        assert ((d.scores > 0.9) & ~present).any(axis=1).mean() < 0.02


def test_detect_command_writes_the_shipped_tables(tmp_path, tiny_real, tiny_world, capsys):
    """``tsnav detect --detector shipped`` writes ``detections_learned.hdf5`` with the shipped fingerprint (the
    same table as the one the demo writes), and refuses a 64-px world in one line."""
    from tsnav.cli import main
    from tsnav.data.detections import load_detections, read_fingerprint

    data = tmp_path / "data"
    val = next(p for p in list_scenes(tiny_real) if load_scene(p).meta.get("split") == "val")
    shutil.copytree(val, data / val.name)
    assert main(["detect", "--data", str(data), "--detector", "shipped", "--no-eval", "--threads", "1"]) == 0
    assert read_fingerprint(data / val.name, "learned") == shipped.shipped_meta()["fingerprint"]
    direct = shipped.shipped_detector(128).detect_scene(load_scene(data / val.name))
    assert np.array_equal(load_detections(data / val.name, "learned").scores, direct.scores)
    # the other shipped detector, by name, under another table name
    assert (
        main(
            [
                "detect",
                "--data",
                str(data),
                "--detector",
                "shipped",
                "--shipped",
                "learned3",
                "--name",
                "l3",
                "--no-eval",
                "--threads",
                "1",
            ]
        )
        == 0
    )
    assert read_fingerprint(data / val.name, "l3") == shipped.shipped_meta("learned3")["fingerprint"]
    # without --shipped, a table named after a shipped detector is written by that detector
    assert (
        main(
            [
                "detect",
                "--data",
                str(data),
                "--detector",
                "shipped",
                "--name",
                "learned3",
                "--no-eval",
                "--threads",
                "1",
            ]
        )
        == 0
    )
    assert read_fingerprint(data / val.name, "learned3") == shipped.shipped_meta("learned3")["fingerprint"]
    capsys.readouterr()
    assert main(["detect", "--data", str(tiny_world), "--detector", "shipped", "--no-eval", "--name", "shipped_x"]) == 2
    err = capsys.readouterr().err.strip()
    assert "reads 128x128 frames" in err and "64x64" in err and len(err.splitlines()) == 1
    assert not any((p / "detections_shipped_x.hdf5").exists() for p in list_scenes(tiny_world))


def test_experiments_take_the_shipped_tables(tmp_path, tiny_real, tiny_world):
    """``tsnav experiment ... --detector shipped``: the missing learned tables are written by the shipped detector
    (nothing trained, no detector folder); a 64-px world is refused in one line; another source is refused."""
    from tsnav.data.detections import read_fingerprint
    from tsnav.pipeline.experiment import Experiment
    from tsnav.pipeline.config import ExperimentConfig, ScaleConfig
    from tsnav.pipeline.steps import ensure_detections

    data = tmp_path / "data"
    val = next(p for p in list_scenes(tiny_real) if load_scene(p).meta.get("split") == "val")
    shutil.copytree(val, data / val.name)
    ensure_detections(data, "learned", tmp_path / "never_used", None, shipped=True)
    assert read_fingerprint(data / val.name, "learned") == shipped.shipped_meta()["fingerprint"]
    assert not (tmp_path / "never_used").exists()
    ensure_detections(data, "learned", None, None, shipped=True)  # complete: nothing to write, no error
    with pytest.raises(CommandError, match="reads 128x128 frames"):
        ensure_detections(tiny_world, "shipped_y", None, None, shipped=True)
    # a table named after a shipped detector is that detector's: written by it, and taken as shipped when complete
    ensure_detections(data, "learned3", None, None, shipped=True)
    assert read_fingerprint(data / val.name, "learned3") == shipped.shipped_meta("learned3")["fingerprint"]
    ensure_detections(data, "learned3", None, None, shipped=True)  # complete: no "another detector's" error
    # a run that trains its detector refuses the default shipped detector's tables, as it always did
    with pytest.raises(
        CommandError, match="holds the shipped detector's detections_learned.hdf5, not from --detector train"
    ):
        ensure_detections(data, "learned", tmp_path / "det", ScaleConfig(), shipped=False)
    assert not (tmp_path / "det").exists()
    # another shipped detector's tables under a shipped detector's name are refused in one line, not overwritten
    shutil.copy(data / val.name / "detections_learned3.hdf5", data / val.name / "detections_learned7.hdf5")
    with pytest.raises(CommandError, match="another learned detector's .* not from --detector shipped"):
        ensure_detections(data, "learned7", None, None, shipped=True)
    assert read_fingerprint(data / val.name, "learned7") == shipped.shipped_meta("learned3")["fingerprint"]
    with pytest.raises(ValueError, match="--detector must be train or shipped"):
        Experiment(ExperimentConfig(experiment="ablation", data=str(data), out=str(tmp_path / "x"), detector="bogus"))
