"""Linear probes: AP by hand and against a slow reference, ridge recovers a linear map, end-to-end run."""

import math

import numpy as np
import pytest

from tsnav.pretrain.features import load_encoder
from tsnav.pretrain.probe import ProbeConfig, average_precision, probe_encoder, ridge_fit, ridge_predict
from tsnav.pretrain.synthetic import write_synthetic_dataset


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def slow_ap(s, y):
    order = sorted(range(len(s)), key=lambda i: -s[i])
    hits, total = 0, 0.0
    for rank, i in enumerate(order, 1):
        if y[i]:
            hits += 1
            total += hits / rank
    return total / hits if hits else math.nan


def test_average_precision_by_hand_and_reference():
    s = np.array([[0.9], [0.8], [0.7], [0.1]])
    y = np.array([[1], [0], [1], [0]])
    assert average_precision(s, y)[0] == pytest.approx((1 / 1 + 2 / 3) / 2)
    rng = np.random.default_rng(0)
    s = rng.normal(size=(50, 4))
    y = rng.random((50, 4)) < 0.3
    got = average_precision(s, y)
    for k in range(4):
        assert got[k] == pytest.approx(slow_ap(s[:, k], y[:, k]))
    assert np.isnan(average_precision(s[:, :1], np.zeros((50, 1)))[0])


def test_ridge_recovers_a_linear_map():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(200, 5)) * 3 + 1
    y = x @ np.array([1.0, -2.0, 0.5, 0.0, 3.0]) + 4.0
    m = ridge_fit(x, y, 1e-9)
    np.testing.assert_allclose(ridge_predict(x, m), y, atol=1e-6)


def test_probe_runs_end_to_end(tmp_path):
    root = write_synthetic_dataset(tmp_path / "d", size=32)
    enc = load_encoder("untrained:vit_micro", patch_size=8, img_size=32)
    res = probe_encoder(enc, root, ProbeConfig(max_images=64))
    assert res["n_fit"] == 64 and res["n_eval"] == 32
    assert 0 < res["depth_rmse_m"] < 10 and res["depth_rmse_baseline_m"] > 0
    assert 0 < res["depth_rmse_heldout_m"] < 10 and res["depth_rmse_heldout_baseline_m"] > 0
    assert res["categories"] == 0 or 0 <= res["map"] <= 1
