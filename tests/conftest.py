"""Shared fixtures. ``tiny_world``: the `tiny` preset built once per test session (a few seconds)."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "2")


@pytest.fixture(scope="session")
def tiny_world(tmp_path_factory):
    """Dataset root of the `tiny` preset (5 compact rendered scenes, 64x64 images)."""
    from tsnav.world.build import build_dataset

    root = tmp_path_factory.mktemp("tiny_world")
    build_dataset(root, "tiny", workers=1, progress=False)
    return root


@pytest.fixture(scope="session")
def tiny_scenes(tiny_world):
    from tsnav.data.reader import list_scenes, load_scene

    return [load_scene(p) for p in list_scenes(tiny_world)]
