"""The learned detector as a stage of the experiments and the demo (issue 14 item 4), on a copy of the tiny world
with a few training steps: tables are trained and written when missing, used as they are when every scene has
one of a single learned detector, and never overwritten when another detector made them (one-line error naming
the file); the detector's quality on the val rooms is recorded."""

import json
import shutil

import numpy as np
import pytest

from tsnav.data.detections import load_detections, read_fingerprint
from tsnav.data.reader import list_scenes
from tsnav.detect.learned import LearnedDetector
from tsnav.errors import CommandError
from tsnav.pipeline.detector_steps import (
    detection_quality,
    detector_configs,
    ensure_detector,
    ensure_learned_detections,
    record_quality,
    tables_complete,
)
from tsnav.pipeline.config import SCALES, ScaleConfig
from tsnav.pipeline.steps import ensure_oracle_detections

SMALL = ScaleConfig().override(detector=dict(steps=3, batch_size=8, max_states_per_scene=24))

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture
def world(tiny_world, tmp_path):
    root = tmp_path / "world"
    shutil.copytree(tiny_world, root, ignore=shutil.ignore_patterns("detections_*"))
    return root


def _fps(root, name="learned"):
    return {p.name: read_fingerprint(p, name) for p in list_scenes(root)}


def test_tables_trained_when_missing_then_reused(world, tmp_path):
    import torch

    torch.set_num_threads(2)
    det_dir = tmp_path / "det"
    done = ensure_learned_detections(world, "learned", det_dir, SMALL, progress=False, say=lambda m: None)
    assert done["trained"] and done["written"] == len(list_scenes(world))
    assert torch.get_num_threads() == 2  # the detector ran on one thread; the caller's count is restored
    fp = done["fingerprint"]
    assert set(_fps(world).values()) == {fp} and tables_complete(world, "learned") == fp
    det = LearnedDetector.load(det_dir)
    assert det.fingerprint == fp and det.meta["step"] == SMALL.detector.steps
    assert det.meta["calibrated_step"] == SMALL.detector.steps and det.meta["calibration_split"] == "val"
    assert det.model.cfg.stem == 1 and det.model.cfg.image_size == 64
    # what was written is the detector's own table
    scene = list_scenes(world)[0]
    assert load_detections(scene, "learned").fingerprint == fp

    # present in every scene: used as they are, nothing trained (another, empty detector folder stays untouched)
    other = tmp_path / "other"
    again = ensure_learned_detections(
        world, "learned", other, SMALL.override(detector=dict(steps=5)), progress=False, say=lambda m: None
    )
    assert again == {"fingerprint": fp, "written": 0, "trained": False} and not other.exists()

    # a scene lost its table: the same detector folder (finished) writes it, nothing else changes
    mtimes = {p.name: (p / "detections_learned.hdf5").stat().st_mtime_ns for p in list_scenes(world)}
    (scene / "detections_learned.hdf5").unlink()
    fill = ensure_learned_detections(world, "learned", det_dir, SMALL, progress=False, say=lambda m: None)
    assert fill["written"] == 1 and fill["fingerprint"] == fp
    assert all(
        (p / "detections_learned.hdf5").stat().st_mtime_ns == mtimes[p.name] for p in list_scenes(world) if p != scene
    )

    # quality on the val rooms, recorded per table and reused while the fingerprint is unchanged
    ensure_oracle_detections(world)
    doc = record_quality(tmp_path / "exp", world, ["learned", "oracle"], say=lambda m: None)
    q = doc["learned"]
    assert q["fingerprint"] == fp and q["split"] == "val" and q["scenes"] == len(list_scenes(world, split="val"))
    assert 0.0 <= q["presence_ap"] <= 1.0 and 0 <= q["reached"] <= q["pairs"] and q["pairs"] > 0
    assert set(q["fp_states"]) == {"0.5", "0.7", "0.9"}
    assert doc["oracle"]["fingerprint"].startswith("oracle-")
    # the oracle's confidence is a function of what is in view: no false positives at all
    assert all(v == 0.0 for v in doc["oracle"]["fp_states"].values())
    assert q == detection_quality(world, "learned")
    (tmp_path / "exp" / "detector_quality.json").write_text(json.dumps({"learned": dict(q, presence_ap=-1.0)}))
    assert record_quality(tmp_path / "exp", world, ["learned"], say=lambda m: None)["learned"]["presence_ap"] == -1.0


def test_tables_of_another_detector_are_refused(world, tmp_path):
    det_dir = tmp_path / "det"
    done = ensure_learned_detections(world, "learned", det_dir, SMALL, progress=False, say=lambda m: None)
    scenes = list_scenes(world)
    before = {p.name: (p / "detections_learned.hdf5").read_bytes() for p in scenes}

    # one scene lacks its table and the detector folder holds another detector (more steps): refused, naming a
    # table, nothing written or overwritten
    (scenes[0] / "detections_learned.hdf5").unlink()
    with pytest.raises(CommandError, match=r"detections_learned.hdf5 was made by another learned detector") as e:
        ensure_learned_detections(
            world,
            "learned",
            tmp_path / "det5",
            SMALL.override(detector=dict(steps=5)),
            progress=False,
            say=lambda m: None,
        )
    assert len(str(e.value).splitlines()) == 1 and str(world) in str(e.value)
    assert not (scenes[0] / "detections_learned.hdf5").exists()
    assert all((p / "detections_learned.hdf5").read_bytes() == before[p.name] for p in scenes[1:])

    # an oracle's table under the learned name: refused, naming the file
    shutil.copy(scenes[1] / "detections_learned.hdf5", scenes[0] / "detections_learned.hdf5")
    ensure_oracle_detections(world)
    shutil.copy(scenes[2] / "detections_oracle.hdf5", scenes[2] / "detections_learned.hdf5")
    with pytest.raises(
        CommandError,
        match=rf"{scenes[2].name}/detections_learned.hdf5 was made by another "
        r"detector \(oracle-",
    ):
        ensure_learned_detections(world, "learned", det_dir, SMALL, progress=False, say=lambda m: None)

    # tables of two learned detectors in one world: refused
    shutil.copy(scenes[1] / "detections_learned.hdf5", scenes[2] / "detections_learned.hdf5")
    other = tmp_path / "w2"
    shutil.copytree(world, other)
    for p in list_scenes(other):
        (p / "detections_learned.hdf5").unlink()
    ensure_learned_detections(
        other, "learned", tmp_path / "det5", SMALL.override(detector=dict(steps=5)), progress=False, say=lambda m: None
    )
    shutil.copy(other / scenes[3].name / "detections_learned.hdf5", scenes[3] / "detections_learned.hdf5")
    with pytest.raises(CommandError, match="another learned detector .* than other scenes'"):
        tables_complete(world, "learned")
    assert done["fingerprint"] != read_fingerprint(scenes[3], "learned")

    # a detector folder trained on other rooms is refused
    (scenes[3] / "detections_learned.hdf5").unlink()
    sub = tmp_path / "sub"
    sub.mkdir()
    train = list_scenes(world, split="train")
    (sub / train[0].name).symlink_to(train[0], target_is_directory=True)
    with pytest.raises(CommandError, match="holds a detector trained on other rooms"):
        ensure_detector(sub, world, det_dir, SMALL, progress=False, say=lambda m: None)


def test_scales_size_the_detector_by_frame_side():
    """64-px worlds (demo, small) use stem 1, the 128-px ithor-real scales stem 2; budgets are in steps."""
    assert SCALES["demo"].detector_model["stem"] == 1 and SCALES["small"].detector_model["stem"] == 1
    assert SCALES["medium"].detector_model["stem"] == 2 and SCALES["paper"].detector_model["stem"] == 2
    assert all(isinstance(sc.detector.steps, int) and sc.detector.steps > 0 for sc in SCALES.values())
    tc, mc = detector_configs(SCALES["medium"], 128)
    assert mc.image_size == 128 and mc.grid == 16 and tc.threads == 1 and tc.steps == SCALES["medium"].detector.steps
    assert np.array_equal(mc.widths, SCALES["medium"].detector_model["widths"])
    # the 128-px scales train what `tsnav detect` trains on a 128-px world, the 64-px ones its small default
    from tsnav.detect.model import default_config
    from tsnav.detect.train import default_train_steps

    assert mc == default_config(128) and tc.steps == default_train_steps(128)
    assert detector_configs(SCALES["demo"], 64)[1] == default_config(64)
