"""Named scene sets of the embedded world (``tsnav world --preset``)."""

from __future__ import annotations

from ..data.names import ithor_scenes, robothor_scenes

PRESETS = {
    # a handful of small rooms, seconds to build: for tests
    "tiny": {"scenes": ["FloorPlan1", "FloorPlan2", "FloorPlan201", "FloorPlan21", "FloorPlan22"],
             "compact": True, "image_size": 64},
    # a few scenes of each room type (3 train, 1 val, 1 test), minutes to build
    "demo": {"scenes": [f"FloorPlan{b + i}" for b in (0, 200, 300, 400) for i in (1, 2, 3, 21, 22)],
             "compact": False, "image_size": 64},
    "ithor": {"scenes": ithor_scenes(), "compact": False, "image_size": 128},
    "robothor": {"scenes": robothor_scenes(), "compact": False, "image_size": 128},
}


def preset_scenes(name: str) -> list[str]:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r} (choose from {', '.join(PRESETS)})")
    return list(PRESETS[name]["scenes"])
