"""The registries that name tsnav's extension points once: metrics (metrics.py), encoders (pretrain/encoders.py,
pretrain/archs.py) and detectors (detect/registry.py). Each holds the built-in entries, refuses what it cannot run
with a one-line error, and is what its readers read (reward terms: tests/tsrm/test_tsrm_terms.py; how a user adds one
of each: tests/project/test_howto_extend.py)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from tsnav import metrics


@pytest.fixture
def metric_registry():
    saved = dict(metrics.METRIC_REGISTRY)
    yield metrics
    metrics.METRIC_REGISTRY.clear()
    metrics.METRIC_REGISTRY.update(saved)


def test_one_metric_registry_read_by_tables_claims_logger_and_curves(metric_registry):
    from tsnav.pipeline.convergence import curve_points
    from tsnav.report import claims
    from tsnav.rl.logger import tag_group

    assert metrics.METRICS == metrics.PAPER_METRICS == ("SR", "SPL", "SSR", "SSSPL", "NSNPL")
    assert claims.METRICS == metrics.PAPER_METRICS
    assert metrics.curve_metrics() == ("SR", "SPL", "SSSPL", "NSNPL")  # SSR is not drawn
    cols = [[1, 0, 1], [1, 1, 0], [4, 9, 6], [4, 3, 5], [2, 9, 6], [1, 3, 5], [2, 0, 0], [2, 0, 0]]
    before = metrics.metric_values(*cols)
    assert list(before) == list(metrics.METRICS)
    with pytest.raises(ValueError, match="not a tsnav.metrics.Metric"):
        metrics.register_metric("NSR")
    metrics.register_metric(
        metrics.Metric(
            "NSR", "successes among pathfinding episodes", lambda e: float(np.sum(e.success * e.entered) / e.k_nav)
        )
    )
    with pytest.raises(ValueError, match="already registered"):
        metrics.register_metric(metrics.Metric("NSR", "another", lambda e: 0.0))
    after = metrics.metric_values(*cols)
    assert {k: after[k] for k in before} == before and after["NSR"] == 0.5  # the five unchanged, bit for bit
    assert metrics.metric_values(*[[] for _ in cols])["NSR"] == 0.0
    assert tag_group("NSR") == "metrics" and tag_group("SR") == "metrics" and tag_group("loss") == "losses"
    assert tag_group("reward/slack") == "reward" and tag_group("fps") == "charts"
    assert "NSR" in metrics.curve_metrics() and "NSR" in metrics.METRICS
    records = [
        metrics.EpisodeRecord(success=bool(s), path_length=4, optimal_length=3, entered_pathfinding=bool(n))
        for s, n in ((1, 1), (0, 1), (1, 0))
    ]
    table = metrics.format_table(metrics.summarize(records, by_room_type=False))
    assert "NSR" in table.splitlines()[1] and table.splitlines()[3].split()[6] == "50.00"
    # a selection scored before the metric existed still draws (the new metric is left out)
    old = {"scores": {"1": {"update": 1, "env_steps": 8, "episodes": 2, "metrics": {"ALL": before}}}}
    assert "NSR" not in curve_points(old)[0] and curve_points(old)[0]["SR"] == before["SR"]


def test_encoder_registry_names_methods_architectures_and_specs(tmp_path):
    from pathlib import Path

    from tsnav.pipeline.config import SCALES, ExperimentConfig
    from tsnav.pipeline.steps import encoder_spec
    from tsnav.pretrain.archs import ENCODER_ARCHS, arch_of
    from tsnav.pretrain.encoders import ENCODERS, METHODS, describe_pretraining, encoder_kind, method_kind
    from tsnav.pretrain.train import PretrainConfig

    assert METHODS == ("demae", "mae", "demae-crop", "resnet18-sup")
    assert set(ENCODERS) == {"demae", "mae", "demae-crop", "resnet18", "vc1"}
    assert {k.arch for k in ENCODERS.values()} <= set(ENCODER_ARCHS)
    assert method_kind("demae-crop").depth and method_kind("demae-crop").crop and not method_kind("mae").depth
    assert method_kind("resnet18-sup").labels and PretrainConfig(method="resnet18-sup").resolved_base_lr == 1e-3
    assert PretrainConfig(method="mae").resolved_base_lr == 1.5e-4
    with pytest.raises(ValueError, match="unknown method 'dino'"):
        PretrainConfig(method="dino")
    with pytest.raises(ValueError, match="unknown encoder 'dino'"):
        encoder_kind("dino")
    with pytest.raises(ValueError, match="unknown encoder architecture"):
        arch_of("dino")
    assert describe_pretraining({"method": "resnet18-sup"}) == "ResNet18"
    assert describe_pretraining({"method": "demae", "model": "vit_tiny", "patch_size": 8}) == "vit_tiny, patch 8"
    cfg = ExperimentConfig(experiment="pretraining", data="d", out="o")
    small = SCALES["small"]
    es = encoder_spec("resnet18", small, Path("pre"), cfg)
    assert es.spec == str(Path("pre") / "resnet18-sup") and es.pretrain.method == "resnet18-sup"
    assert es.pretrain.base_lr is None
    assert encoder_spec("demae-crop", small, Path("pre"), cfg).pretrain.method == "demae-crop"
    with pytest.raises(ValueError, match="the VC-1 row needs --vc1-weights PATH"):
        encoder_spec("vc1", small, Path("pre"), cfg)
    given = ExperimentConfig(experiment="pretraining", data="d", out="o", resnet18_weights="r.pth", vc1_weights="v.pth")
    assert encoder_spec("resnet18", small, Path("pre"), given).spec == "resnet18:r.pth"
    assert encoder_spec("vc1", small, Path("pre"), given).spec == "vit:v.pth"


def test_detector_registry_is_the_detect_commands_choices():
    from tsnav.detect.registry import DETECTORS, detector_kind

    assert list(DETECTORS) == ["oracle", "learned", "shipped"]
    assert [DETECTORS[k].table for k in DETECTORS] == ["oracle", "learned", "learned"]
    assert [DETECTORS[k].trained for k in DETECTORS] == [False, True, True]
    with pytest.raises(ValueError, match="unknown detector 'yolo'"):
        detector_kind("yolo")
    out = subprocess.run(
        [sys.executable, "-m", "tsnav", "detect", "--help"], capture_output=True, text=True, check=True
    )
    assert "{oracle,learned,shipped}" in out.stdout


def test_registries_import_without_torch():
    """The encoder and detector registries and the metrics are read by reports and parsers: no torch on import."""
    code = (
        "import sys; import tsnav.pretrain.encoders, tsnav.detect.registry, tsnav.metrics, tsnav.tsrm.terms; "
        "print('torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
