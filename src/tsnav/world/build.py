"""Build offline datasets: generate, lay out the state graph, render every state, write scene folders.

:func:`build_scene` makes one scene (written through :mod:`tsnav.data.writer`, atomically: running the build
again skips finished scenes and redoes the rest); :func:`build_dataset` many, in parallel worker processes.
Files follow the lineage layout (DESIGN.md "The offline dataset").
"""

from __future__ import annotations

import json
import os
import shutil
import time
from contextlib import ExitStack
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..atomic import atomic_write_text
from ..constants import CAMERA_HEIGHT, FIELD_OF_VIEW, HORIZONS, ROTATIONS, VISIBILITY_DISTANCE, camera_height_of
from ..data.lineage import visible_object_map
from ..data.reader import COMPLETE_MARKER
from ..data.writer import (
    DEFAULT_COMPRESSION,
    DEFAULT_COMPRESSION_LEVEL,
    GRID_Y,
    MIN_PIXEL_FRACTION,
    FrameWriter,
    box_distance,
    min_pixels,
    object_stats,
    scene_folder,
    write_graph,
    write_json,
    write_states,
)
from ..distributed import spawn_context
from ..render.gl import Renderer
from ..data.names import scene_info
from .navgrid import graph_edges, reachable_positions, state_keys, state_poses
from .presets import PRESETS, preset_scenes, scene_spec
from .spec import SceneSpec


@dataclass
class BuildConfig:
    """Settings of one dataset build."""

    image_size: int = 64  #: side of the square frames, pixels
    store_images: bool = True  #: write images.hdf5 and depth.hdf5 (needed for pretraining and features)
    depth_dtype: str = "float16"  #: dtype of depth.hdf5 (metres); float16 keeps datasets small
    #: HDF5 filter of images.hdf5 / depth.hdf5 (tsnav.data.writer.FRAME_COMPRESSIONS: "gzip", "lzf" or None for
    #: raw frames; only filters stock h5py reads) and the gzip level
    compression: str | None = DEFAULT_COMPRESSION
    compression_level: int = DEFAULT_COMPRESSION_LEVEL
    compact: bool = False  #: small rooms (the `tiny` preset)
    world: str = "procedural"  #: layout source: "procedural", "ithor-real" or "robothor-real" (presets.WORLDS)
    #: version of the ithor-real rules (tsnav.world.real.VERSIONS) or of the robothor-real rules
    #: (tsnav.world.robothor_real.VERSIONS); None: the newest; ithor-real 1 rebuilds worlds made before issue 24
    world_version: int | None = None
    #: world seed; the same name and seed give the same scene (robothor-real: the train apartments' floor and wall
    #: materials' draw, 0 the benchmark's, the val apartments always 0's; ithor-real: 0 only)
    seed: int = 0
    #: robothor-real: the challenge's episode folder; the train scenes are then rebuilt the way the val ones are
    #: (furniture from the plans, targets inferred from their challenge train episodes), not from their records
    infer_train: str | None = None
    tiles: int = 16  #: views rendered per framebuffer read
    #: height of the camera above the floor, metres (the lineage's 1.5 m; the RoboTHOR challenge's LoCoBot sees from
    #: about 0.87 m): the frames and the visibility tables are rendered from it
    camera_height: float = CAMERA_HEIGHT

    def __post_init__(self):
        if not 0.1 <= self.camera_height <= 3.0:
            raise ValueError(f"camera_height must be between 0.1 and 3.0 metres, got {self.camera_height}")

    def min_pixels(self) -> int:
        return min_pixels(self.image_size)

    @classmethod
    def from_preset(cls, preset: str | None, **overrides) -> "BuildConfig":
        """The settings of ``preset`` (:data:`~tsnav.world.presets.PRESETS`: image size, compact rooms, world;
        the defaults for ``None`` or a name that is not a preset), then ``overrides`` (field values)."""
        p = PRESETS.get(preset or "", {})
        return replace(
            cls(
                image_size=p.get("image_size", 64), compact=p.get("compact", False), world=p.get("world", "procedural")
            ),
            **overrides,
        )


@dataclass
class SceneStats:
    name: str
    states: int = 0
    positions: int = 0
    objects: int = 0
    render_s: float = 0.0
    write_s: float = 0.0
    other_s: float = 0.0
    skipped: bool = False
    extra: dict = field(default_factory=dict)


def build_scene(name: str, out_dir: str | Path, cfg: BuildConfig, renderer: Renderer | None = None) -> SceneStats:
    """Generate, render and write scene ``name`` into ``out_dir/name`` (skipped when already complete)."""
    out_dir = Path(out_dir)
    final = out_dir / name
    stats = SceneStats(name)
    if (final / COMPLETE_MARKER).exists():
        stats.skipped = True
        return stats
    t0 = time.perf_counter()
    spec: SceneSpec = scene_spec(
        name, cfg.world, seed=cfg.seed, compact=cfg.compact, version=cfg.world_version, infer_train=cfg.infer_train
    )
    positions, move = reachable_positions(spec)
    js = spec.to_json()
    objects = spec.objects
    object_ids = [o.objectId for o in objects]
    O = len(objects)
    lut = np.full(len(spec.instances), -1, np.int64)
    for j, o in enumerate(objects):
        lut[o.inst] = j
    # Render order = node order: position, rotation, horizon; the tables are stored in sorted key order.
    poses = state_poses(positions)
    keys = state_keys(positions)
    order = np.argsort(keys, kind="stable")
    stats.other_s += time.perf_counter() - t0

    own = renderer is None
    if own:
        renderer = Renderer(cfg.image_size, cfg.tiles)
    try:
        renderer.set_scene(np.array(js["parts"], dtype=np.float32), js["light"])
        V = len(poses)
        pixels = np.zeros((V, O), np.int32)
        boxes = np.full((V, O, 4), -1, np.int16)
        with scene_folder(final) as tmp:
            with ExitStack() as stack:
                frames = (
                    stack.enter_context(FrameWriter(tmp, cfg.depth_dtype, cfg.compression, cfg.compression_level))
                    if cfg.store_images
                    else None
                )
                chunk = renderer.tiles * 4
                for start in range(0, V, chunk):
                    t1 = time.perf_counter()
                    rgb, depth, ids = renderer.render(poses[start : start + chunk], height=cfg.camera_height)
                    px, bx = (
                        object_stats(ids, lut, O)
                        if O
                        else (np.zeros((len(ids), 0), np.int32), np.zeros((len(ids), 0, 4), np.int16))
                    )
                    pixels[start : start + len(ids)] = px
                    boxes[start : start + len(ids)] = bx
                    t2 = time.perf_counter()
                    stats.render_s += t2 - t1
                    if frames is not None:
                        frames.add_many(keys[start : start + len(ids)], rgb, depth)
                    stats.write_s += time.perf_counter() - t2
            t3 = time.perf_counter()
            # Distances: agent position to the nearest point of each object's footprint (floor plane); per position.
            if O:
                dist_pos = box_distance(
                    positions,
                    np.array([o.center for o in objects]),
                    np.array([o.size for o in objects]),
                    np.array([o.yaw for o in objects]),
                )
            else:
                dist_pos = np.zeros((len(positions), 0))
            per_pos = len(ROTATIONS) * len(HORIZONS)
            distance = np.repeat(dist_pos, per_pos, axis=0).astype(np.float32)
            keys_s, pixels_s, boxes_s, distance_s = keys[order], pixels[order], boxes[order], distance[order]
            min_px = cfg.min_pixels()
            vis = (pixels_s >= min_px) & (distance_s <= VISIBILITY_DISTANCE)
            write_json(tmp / "visible_object_map_1.5.json", visible_object_map(object_ids, keys_s, vis))
            write_json(tmp / "grid.json", [{"x": float(x), "y": GRID_Y, "z": float(z)} for x, z in positions])
            src, dst = graph_edges(move)
            write_graph(tmp, keys_s.tolist(), zip(keys[src].tolist(), keys[dst].tolist()))
            write_states(
                tmp, keys_s, object_ids, pixels_s, boxes_s, distance_s, image_size=cfg.image_size, min_pixels=min_px
            )
            js.update(
                {
                    "image_size": cfg.image_size,
                    "compact": cfg.compact,
                    "camera": {"height": cfg.camera_height, "field_of_view": FIELD_OF_VIEW},
                    "visibility": {
                        "min_pixels": min_px,
                        "min_pixel_fraction": MIN_PIXEL_FRACTION,
                        "distance": VISIBILITY_DISTANCE,
                    },
                    "num_states": len(keys),
                    "num_positions": len(positions),
                    "figures": scene_figures(spec, len(positions), len(keys), vis.any(axis=0)),
                }
            )
            write_json(tmp / "scene.json", js)
        stats.write_s += time.perf_counter() - t3
    finally:
        if own:
            renderer.release()
    stats.states, stats.positions, stats.objects = len(keys), len(positions), O
    return stats


def scene_figures(spec: SceneSpec, positions: int, states: int, seen: np.ndarray) -> dict:
    """The figures that describe a built scene (``scene.json`` ``figures``): reachable positions, states, objects
    (all recorded or generated objects, and those that block the agent), target-class objects, the target
    categories present in the scene and those seen from at least one state (``seen``: per object of
    ``spec.objects``, in the visible object map), and where the scene comes from."""
    furniture_ids = {f.id for f in spec.furniture}
    present = sorted({o.objectType for o in spec.objects})
    seen_cats = sorted({o.objectType for o, s in zip(spec.objects, seen) if s})
    return {
        "positions": int(positions),
        "states": int(states),
        "objects": len(furniture_ids) + len(spec.objects),
        "blocking_objects": len({f.id for f in spec.furniture if f.blocks})
        + sum(o.support == "floor" for o in spec.objects),
        "target_objects": len(spec.objects),
        "targets_present": present,
        "targets_seen": seen_cats,
        "generator": spec.generator or {"world": "procedural"},
    }


def finished_train_generators(out: Path) -> list[tuple[Path, dict]]:
    """``(folder, generator)`` of every finished train scene of a robothor-real folder (a scene built before
    generators were recorded gives {})."""
    found = []
    for d in sorted(out.iterdir()) if out.is_dir() else []:
        gen = finished_generator(d)
        try:
            split = scene_info(d.name)[1]
        except ValueError:
            continue  # not a scene folder
        if gen is not None and split == "train":
            found.append((d, gen))
    return found


def check_train_objects(out: Path, cfg: BuildConfig) -> None:
    """Refuse to build robothor-real train scenes into a folder whose finished train scenes (any of them, not only
    those of this build) were built the other way: recorded objects against ``--infer-train-objects``. One-line
    ``ValueError``; a scene built before the option existed is recorded."""
    if cfg.world != "robothor-real":
        return
    for d, gen in finished_train_generators(out):
        inferred = gen.get("train_objects") == "inferred"
        if inferred != (cfg.infer_train is not None):
            raise ValueError(
                f"{d} was built with its train objects {'inferred' if inferred else 'recorded'}, this build "
                f"{'infers' if cfg.infer_train is not None else 'records'} them: use another --out"
            )


def check_surface_seed(out: Path, cfg: BuildConfig) -> None:
    """Refuse to build robothor-real scenes into a folder whose finished train scenes drew their floor and wall
    materials with another seed (finished scenes are skipped, so the world would mix them): one-line
    ``ValueError``. Val scenes always draw with 0 (:func:`~tsnav.world.robothor_real.surface_seed`)."""
    if cfg.world != "robothor-real":
        return
    for d, gen in finished_train_generators(out):
        have = int(gen.get("surface_seed", 0))
        if have != cfg.seed:
            raise ValueError(
                f"{d} was built with surface seed {have}, this build with --seed {cfg.seed}: use another --out"
            )


def write_index(out_dir: Path, preset: str, names: list[str], cfg: BuildConfig) -> None:
    """``index.json`` of a dataset: preset, scene names and the build settings (written atomically)."""
    atomic_write_text(
        out_dir / "index.json",
        json.dumps(
            {"format": "tsnav-dataset", "preset": preset, "scenes": names, "config": asdict(cfg)}, separators=(",", ":")
        ),
    )


_RENDERER = None
_INIT_ERROR: Exception | None = None


def _init_worker(size: int, tiles: int) -> None:
    # An initializer that raises makes multiprocessing respawn workers forever: keep the error for the task.
    global _RENDERER, _INIT_ERROR
    os.environ.setdefault("LP_NUM_THREADS", "1")
    try:
        _RENDERER = Renderer(size, tiles)
    except Exception as e:  # noqa: BLE001 - re-raised in _build_one
        _INIT_ERROR = e


def _build_one(args) -> SceneStats:
    if _INIT_ERROR is not None:
        raise _INIT_ERROR
    name, out, cfg = args
    return build_scene(name, out, cfg, renderer=_RENDERER)


def check_output_dir(out: Path) -> None:
    """Create ``out`` if needed and make sure files can be written there; one-line error otherwise."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".write-test-{os.getpid()}"
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        raise PermissionError(f"cannot write to output folder {out}: {e.strerror or e}") from None


def finished_meta(folder: Path) -> dict | None:
    """A finished scene folder's ``scene.json``; None when the folder is not finished or its scene.json is
    unreadable (the reader's problem, not a build mismatch)."""
    if not (folder / COMPLETE_MARKER).exists():
        return None
    try:
        meta = json.loads((folder / "scene.json").read_text())
    except (OSError, ValueError):
        return None
    return meta if isinstance(meta, dict) else None


def finished_generator(folder: Path) -> dict | None:
    """The ``generator`` record of a finished scene folder's ``scene.json`` ({} when it has none); None as
    :func:`finished_meta`."""
    meta = finished_meta(folder)
    return None if meta is None else meta.get("generator") or {}


def check_camera(out: Path, cfg: BuildConfig) -> None:
    """Refuse to build into a folder whose finished scenes were rendered from another camera height (finished
    scenes are skipped, so the world would mix them): one-line ``ValueError``. A scene that records no camera was
    rendered from :data:`~tsnav.constants.CAMERA_HEIGHT`."""
    for d in sorted(p for p in out.iterdir() if p.is_dir()):
        meta = finished_meta(d)
        if meta is None:
            continue
        have = camera_height_of(meta)
        if abs(have - cfg.camera_height) > 1e-6:
            raise ValueError(
                f"{d} was rendered from a camera {have} m high, this build from {cfg.camera_height} m: use another --out"
            )


def check_world_version(out: Path, names: list[str], cfg: BuildConfig) -> None:
    """Refuse to add ``ithor-real`` rooms of one rules version to a folder whose finished rooms were built with
    another (finished rooms are skipped, so the world would mix versions): one-line ``ValueError``. A room
    without a recorded ``generator`` was built before versions were recorded: version 1."""
    if cfg.world not in ("ithor-real", "robothor-real"):
        return
    from .real import check_version as check_ithor
    from .robothor_real import check_version as check_robothor

    want = (check_ithor if cfg.world == "ithor-real" else check_robothor)(cfg.world_version)
    for n in names:
        gen = finished_generator(out / n)
        if gen is None:
            continue
        have = int(gen.get("version", 1))
        if gen.get("world", cfg.world) != cfg.world:
            raise ValueError(
                f"{out / n} was built by world {gen.get('world')!r}, this build makes {cfg.world!r}: use another --out"
            )
        if have != want:
            raise ValueError(
                f"{out / n} was built with {cfg.world} version {have}, this build makes version {want}: "
                f"pass --world-version {have} to finish that world, or use another --out"
            )


def build_dataset(
    out: str | Path,
    preset: str | None = "tiny",
    scenes: list[str] | None = None,
    cfg: BuildConfig | None = None,
    workers: int = 1,
    progress: bool = True,
) -> list[SceneStats]:
    """Build ``scenes`` (default: the preset's) into ``out``; finished scenes are skipped."""
    out = Path(out)
    names = list(scenes) if scenes else preset_scenes(preset or "tiny")
    for n in names:
        scene_info(n)  # validates the name
    if cfg is None:
        cfg = BuildConfig.from_preset(preset)
    check_output_dir(out)
    # Leftovers of interrupted builds are never complete: remove them.
    for stale in out.glob(".*.partial-*"):
        shutil.rmtree(stale, ignore_errors=True)
    check_world_version(out, names, cfg)
    check_train_objects(out, cfg)
    check_surface_seed(out, cfg)
    check_camera(out, cfg)
    write_index(out, preset or "custom", names, cfg)
    todo = [(n, out, cfg) for n in names]
    results: list[SceneStats] = []
    bar = tqdm(total=len(todo), desc=f"world {preset or 'custom'}", unit="scene", disable=not progress)
    try:
        if workers <= 1:
            renderer = Renderer(cfg.image_size, cfg.tiles)
            try:
                for t in todo:
                    results.append(build_scene(*t, renderer=renderer))
                    bar.set_postfix(states=sum(r.states for r in results))
                    bar.update()
            finally:
                renderer.release()
        else:
            Renderer(16, 1).release()  # fail fast, in this process, when EGL is missing
            pool = spawn_context().Pool(workers, initializer=_init_worker, initargs=(cfg.image_size, cfg.tiles))
            with pool:
                for r in pool.imap_unordered(_build_one, todo):
                    results.append(r)
                    bar.set_postfix(states=sum(x.states for x in results))
                    bar.update()
    finally:
        bar.close()
    order = {n: i for i, n in enumerate(names)}
    return sorted(results, key=lambda r: order[r.name])


__all__ = ["build_dataset", "BuildConfig", "check_output_dir", "replace"]
