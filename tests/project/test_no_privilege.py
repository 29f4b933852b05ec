"""Nothing privileged reaches the agent (issue 14, item 2): the agent's observation on the trainer's path is a
function of the image features and the named detection table only; the oracle's feature carries no distance;
without a named table the agent stage refuses instead of falling back to ground truth."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from conftest import PIXEL_FEATURES
from tsnav.agent import DetectionTable
from tsnav.data.detections import read_fingerprint, write_detections
from tsnav.data.reader import list_scenes, load_scene
from tsnav.detect.oracle import GroundTruth, OracleConfig, oracle_detections, oracle_features
from tsnav.pipeline.steps import ensure_oracle_detections
from tsnav.rl.assemble import load_bank, make_observer
from tsnav.rl.config import TrainConfig
from tsnav.sim.batch import SceneBank

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _all_obs(observer, bank):
    """Observation of every (state, target) pair of the bank, as numpy arrays per field."""
    s = np.repeat(np.arange(bank.num_states), 22)
    g = np.tile(np.arange(22), bank.num_states)
    obs = observer(s, g)
    assert obs.det_depth is None  # no depth input by default (AgentConfig.target_depth is off)
    return {f: getattr(obs, f).numpy().copy() for f in obs.__dataclass_fields__ if getattr(obs, f) is not None}


def test_agent_observation_ignores_privileged_sources(pixel_world):
    """Build the trainer's bank and Observer (oracle table named explicitly), then permute / zero every
    privileged source (scene distances, pixel counts, boxes, the in-frame flags and the stage-switch
    confidence): an Observer made the same way afterwards gives bit-identical observations."""
    cfg = TrainConfig(data=str(pixel_world), features=PIXEL_FEATURES, detections="oracle", device="cpu")
    bank, det = load_bank(cfg)
    before = _all_obs(make_observer(bank, cfg, det_features=det), bank)
    # The observation really is the table's: score, box and per-class feature of the target.
    table = DetectionTable(bank, det)
    assert np.array_equal(before["det_score"], table.score.reshape(-1))
    assert np.array_equal(before["det_feat"], table.features.float().numpy().reshape(-1, det.shape[-1]))

    rng = np.random.default_rng(0)
    in_frame0, conf0 = bank.in_frame.copy(), bank.stage_confidence.copy()
    for scene in bank.scenes:
        scene.distance[:] = rng.permutation(scene.distance.reshape(-1)).reshape(scene.distance.shape)
        scene.pixels[:] = 0
        scene.boxes[:] = 0
    bank.in_frame[:] = rng.permutation(bank.in_frame.reshape(-1)).reshape(bank.in_frame.shape)
    # the bank copies distances and success states when it is built: change its own copies too
    dist0, success0 = bank.dist.copy(), bank.success.copy()
    bank.dist[:] = rng.permutation(bank.dist.reshape(-1)).reshape(bank.dist.shape)
    bank.success[:] = rng.permutation(bank.success.reshape(-1)).reshape(bank.success.shape)
    bank.set_confidence(np.zeros_like(conf0))
    # The mutation is not vacuous: the privileged sources did change.
    assert not np.array_equal(bank.in_frame, in_frame0) and not np.array_equal(bank.stage_confidence, conf0)
    assert not np.array_equal(bank.dist, dist0) and not np.array_equal(bank.success, success0)
    assert conf0.max() > 0 and in_frame0.any()

    after = _all_obs(make_observer(bank, cfg, det_features=det), bank)
    for f in before:
        assert np.array_equal(before[f], after[f]), f


def test_no_silent_fallback_to_ground_truth(tiny_scenes, pixel_world):
    bank = SceneBank(tiny_scenes)  # no detection table installed
    with pytest.raises(ValueError, match=r"no detection table.*tsnav detect.*--detections oracle") as e:
        DetectionTable(bank)
    assert "\n" not in str(e.value)
    cfg = TrainConfig(data=str(pixel_world), features=PIXEL_FEATURES, device="cpu")  # detections not named
    with pytest.raises(ValueError, match="no detection table"):
        load_bank(cfg)


def test_oracle_feature_does_not_vary_with_distance(tiny_scenes):
    """At fixed box, pixels and score the oracle's feature is the same whatever the true distance; on a
    rendered scene slot 59 (the distance until version 1) is zero."""
    S, C = 3, 22
    boxes = np.full((S, C, 4), -1.0, np.float32)
    boxes[:, 5] = [10, 12, 30, 40]
    present = np.zeros((S, C), bool)
    present[:, 5] = True
    pixels = np.where(present, 200, 0).astype(np.int32)
    inst = np.where(present, 0, -1)
    conf = np.where(present, 0.8, 0.0).astype(np.float32)
    feats = [
        oracle_features(GroundTruth(present, boxes, pixels, np.full((S, C), d, np.float32), inst), conf, 64)
        for d in (0.3, 1.7, 4.9, np.nan)
    ]
    for f in feats[1:]:
        np.testing.assert_array_equal(f, feats[0])
    assert (feats[0][:, 5] != 0).any()  # the present class does have a feature
    f = oracle_detections(tiny_scenes[0]).features
    assert (f[..., 59] == 0).all() and (f[..., 56] != 0).any()


def test_stale_oracle_table_is_recomputed(tiny_world, tmp_path):
    """A table of the version-1 oracle (its features held the distance) is rewritten, not reused."""
    src = list_scenes(tiny_world)[0]
    root = tmp_path / "w"
    shutil.copytree(src, root / src.name, ignore=shutil.ignore_patterns("features_*", "detections_*"))
    old = OracleConfig(version=1)
    assert old.fingerprint() != OracleConfig().fingerprint()
    write_detections(root / src.name, "oracle", oracle_detections(load_scene(root / src.name), old))
    assert read_fingerprint(root / src.name, "oracle") == old.fingerprint()
    assert ensure_oracle_detections(root, "oracle") == 1
    assert read_fingerprint(root / src.name, "oracle") == OracleConfig().fingerprint()
    assert ensure_oracle_detections(root, "oracle") == 0
