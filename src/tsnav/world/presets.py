"""Named scene sets of the embedded world (``tsnav world --preset``)."""

from __future__ import annotations

from ..data.names import ithor_scenes, robothor_scenes
from .house import generate
from .real import real_spec
from .robothor_real import robothor_spec
from .spec import SceneSpec

#: Where a scene's layout comes from: ``procedural`` (generated from its name), ``ithor-real`` (the real
#: iTHOR scene's recorded object layout, :mod:`tsnav.world.real`) or ``robothor-real`` (RoboTHOR's apartments from
#: their plans, records and challenge episodes, :mod:`tsnav.world.robothor_real`).
WORLDS = ("procedural", "ithor-real", "robothor-real")

PRESETS = {
    # a handful of small rooms, seconds to build: for tests
    "tiny": {
        "scenes": ["FloorPlan1", "FloorPlan2", "FloorPlan201", "FloorPlan21", "FloorPlan22"],
        "compact": True,
        "image_size": 64,
    },
    # three small real bathrooms (train, val, test) at 128x128, seconds to build: for tests of the real-room paths
    "tiny-real": {
        "scenes": ["FloorPlan408", "FloorPlan424", "FloorPlan425"],
        "compact": False,
        "image_size": 128,
        "world": "ithor-real",
    },
    # a few scenes of each room type (3 train, 1 val, 1 test), minutes to build
    "demo": {
        "scenes": [f"FloorPlan{b + i}" for b in (0, 200, 300, 400) for i in (1, 2, 3, 21, 22)],
        "compact": False,
        "image_size": 64,
    },
    # the demo's real rooms (tsnav demo): 4 of the smallest training rooms of each type (FloorPlan409 is left out:
    # no reachable state sees its targets), one validation and two test rooms of each type, of ithor-real at
    # 128x128 (28 rooms, 42 k states)
    "demo-real": {
        "scenes": [
            f"FloorPlan{i}"
            for i in (
                4,
                11,
                17,
                19,
                27,
                24,
                30,
                202,
                206,
                211,
                217,
                221,
                222,
                226,
                302,
                310,
                316,
                320,
                321,
                322,
                328,
                403,
                408,
                412,
                419,
                423,
                424,
                426,
            )
        ],
        "compact": False,
        "image_size": 128,
        "world": "ithor-real",
    },
    # the quick demo's real rooms (the default of tsnav demo): of demo-real, the 2 smallest training rooms of each
    # type, its 4 validation rooms and its smaller test room of each type (16 rooms, 23.5 k states)
    "demo-real-small": {
        "scenes": [
            f"FloorPlan{i}" for i in (11, 17, 24, 27, 206, 217, 221, 226, 302, 316, 321, 328, 408, 419, 423, 424)
        ],
        "compact": False,
        "image_size": 128,
        "world": "ithor-real",
    },
    "ithor": {"scenes": ithor_scenes(), "compact": False, "image_size": 128},
    # the 120 real iTHOR scenes rebuilt from their recorded object layouts (same names and splits as ithor)
    "ithor-real": {"scenes": ithor_scenes(), "compact": False, "image_size": 128, "world": "ithor-real"},
    "robothor": {"scenes": robothor_scenes(), "compact": False, "image_size": 128},
    # the 75 real RoboTHOR apartments rebuilt from their plans, object records and challenge episodes
    "robothor-real": {"scenes": robothor_scenes(), "compact": False, "image_size": 128, "world": "robothor-real"},
}


def preset_scenes(name: str) -> list[str]:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r} (choose from {', '.join(PRESETS)})")
    return list(PRESETS[name]["scenes"])


def scene_spec(
    name: str,
    world: str = "procedural",
    seed: int = 0,
    compact: bool = False,
    version: int | None = None,
    infer_train: str | None = None,
) -> SceneSpec:
    """The scene description of ``name`` in ``world`` (:data:`WORLDS`); ``seed`` draws a procedural scene and a
    ``robothor-real`` train scene's floor and wall materials (:func:`~tsnav.world.robothor_real.surface_rng`);
    ``ithor-real`` refuses any but 0; ``compact`` applies to procedural scenes only, ``version`` (of the rules,
    :data:`tsnav.world.real.VERSIONS`; None: the newest) to ``ithor-real`` and ``robothor-real`` only; ``infer_train`` (the challenge's episode folder: train scenes rebuilt
    the way the val ones are, :func:`~tsnav.world.robothor_real.robothor_spec`) to ``robothor-real`` only."""
    if infer_train is not None and world != "robothor-real":
        raise ValueError(f"inferring the train scenes' objects applies to the robothor-real world, not {world!r}")
    if world == "procedural":
        if version is not None:
            raise ValueError("a world version applies to the ithor-real world only")
        return generate(name, seed=seed, compact=compact)
    if world == "ithor-real":
        if seed:
            raise ValueError(f"the ithor-real world has no seed (its rooms are their records), got seed {seed}")
        return real_spec(name, version)
    if world == "robothor-real":
        return robothor_spec(name, version, infer_train, seed)
    raise ValueError(f"unknown world {world!r} (choose from {', '.join(WORLDS)})")
