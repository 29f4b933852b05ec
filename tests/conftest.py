"""Shared fixtures. ``tiny_world``: the `tiny` preset built once per test session (a few seconds); ``tiny_real``:
the `tiny-real` preset (three real bathrooms at 128x128, about ten seconds), also once;
``tiny_real_learned4``: a copy of it with the shipped detector's tables; ``pixel_world``: the same with small pixel features cached for the agent tests; ``one_torch_thread``: small
networks run fastest on one thread and do not fight other processes for the cores (modules opt in with
``pytestmark = pytest.mark.usefixtures("one_torch_thread")``)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "2")
# The tests live in one folder per package (tests/sim, tests/rl, ...); the helpers they share (sim_helpers,
# rl_helpers, script_helpers, thor_standin) and fixtures/ stay here, importable from every folder.
sys.path.insert(0, str(Path(__file__).resolve().parent))

#: Fixtures that build a world (directly or through another): a test using one is marked ``slow``
#: (``make test-fast`` leaves it out; ``make test`` and CI run it).
WORLD_FIXTURES = {"tiny_world", "tiny_real", "tiny_real_learned4", "tiny_scenes", "pixel_world"}


#: Tests that build a world or rooms of their own, or start processes (spawned workers, gloo ranks) and train in
#: them: also ``slow`` (each took 5 s or more of the fast set's two minutes; by module, or ``module::test``).
SLOW_TESTS = {
    "test_scene_pool.py",  # worker processes over built rooms
    "test_world.py::test_cli_errors_are_one_line",
    "test_world.py::test_interrupted_build_resumes",
    "test_world.py::test_compressed_frames_equal_raw_and_stay_lineage_readable",
    "test_real_world.py::test_real_scene_build_is_deterministic",
    "test_pretrain_train.py::test_two_gloo_processes_keep_replicas_identical_and_match_one_process",
    "test_pretrain_train.py::test_sigterm_stops_cleanly_at_a_step_boundary",
    "test_pretrain_train.py::test_truncated_newest_checkpoint_resumes_from_the_previous_one",
    "test_pretrain_resnet.py::test_supervised_pretraining_lowers_the_loss",
    "test_rl_procs.py::test_a_failing_rank_is_reported_by_rank_0",
    "test_report.py::test_pretrain_progress_is_read_progress_without_torch",
    "test_tsrm_plot.py::test_draw_episode_writes_png",
}


def pytest_collection_modifyitems(config, items):
    for item in items:
        module = item.nodeid.split("::")[0].rsplit("/", 1)[-1]
        name = item.nodeid.split("[")[0].rsplit("/", 1)[-1]
        if WORLD_FIXTURES & set(getattr(item, "fixturenames", ())) or module in SLOW_TESTS or name in SLOW_TESTS:
            item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="session")
def tiny_world(tmp_path_factory):
    """Dataset root of the `tiny` preset (5 compact rendered scenes, 64x64 images)."""
    from tsnav.world.build import build_dataset

    root = tmp_path_factory.mktemp("tiny_world")
    build_dataset(root, "tiny", workers=1, progress=False)
    return root


@pytest.fixture(scope="session")
def tiny_real(tmp_path_factory):
    """Dataset root of the `tiny-real` preset (3 real iTHOR bathrooms: train, test, val; 128x128 images)."""
    from tsnav.world.build import build_dataset

    root = tmp_path_factory.mktemp("tiny_real")
    build_dataset(root, "tiny-real", workers=1, progress=False)
    return root


@pytest.fixture(scope="session")
def tiny_real_learned4(tiny_real, tmp_path_factory):
    """A copy of ``tiny_real`` with the shipped ``learned4`` detector's tables (and no other tables or features),
    for the scripts that derive new tables from it; each test writes its tables under its own names."""
    import shutil

    from tsnav.detect.shipped import shipped_detector
    from tsnav.pipeline.detector_steps import write_learned_tables

    root = tmp_path_factory.mktemp("tiny_real_learned4") / "world"
    shutil.copytree(tiny_real, root, ignore=shutil.ignore_patterns("detections_*", "features_*"))
    write_learned_tables(root, "learned4", shipped_detector(128, "learned4"), progress=False)
    return root


@pytest.fixture(scope="session")
def tiny_scenes(tiny_world):
    from tsnav.data.reader import list_scenes, load_scene

    return [load_scene(p) for p in list_scenes(tiny_world)]


PIXEL_FEATURES = "rltest_px"
"""Name of the 3x4x4 pixel-feature cache that :func:`pixel_world` writes into the tiny world."""


@pytest.fixture(scope="session")
def pixel_world(tiny_world):
    """The tiny world with :data:`PIXEL_FEATURES` cached (4x4 colour grids: agents train in seconds) and the
    oracle detector's tables ``detections_oracle.hdf5`` (the agent needs a named detection table)."""
    from tsnav.pipeline.steps import ensure_oracle_detections
    from tsnav.pretrain.pixels import cache_pixel_features

    cache_pixel_features(tiny_world, PIXEL_FEATURES, grid=4)
    ensure_oracle_detections(tiny_world, "oracle")
    return tiny_world


@pytest.fixture
def one_torch_thread():
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
