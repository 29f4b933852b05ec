"""Build a dataset of many scenes, in parallel worker processes, resumably."""

from __future__ import annotations

import multiprocessing as mp
import os
import shutil
from dataclasses import replace
from pathlib import Path

from ..data.writer import BuildConfig, SceneStats, build_scene, write_index
from .house import scene_info
from .presets import PRESETS, preset_scenes

_RENDERER = None
_INIT_ERROR: Exception | None = None


def _init_worker(size: int, tiles: int) -> None:
    # An initializer that raises makes multiprocessing respawn workers forever: keep the error for the task.
    global _RENDERER, _INIT_ERROR
    os.environ.setdefault("LP_NUM_THREADS", "1")
    from ..render.gl import Renderer

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


def build_dataset(out: str | Path, preset: str | None = "tiny", scenes: list[str] | None = None,
                  cfg: BuildConfig | None = None, workers: int = 1, progress: bool = True) -> list[SceneStats]:
    """Build ``scenes`` (default: the preset's) into ``out``; finished scenes are skipped."""
    out = Path(out)
    names = list(scenes) if scenes else preset_scenes(preset or "tiny")
    for n in names:
        scene_info(n)  # validates the name
    if cfg is None:
        p = PRESETS.get(preset or "", {})
        cfg = BuildConfig(image_size=p.get("image_size", 64), compact=p.get("compact", False),
                          world=p.get("world", "procedural"))
    check_output_dir(out)
    # Leftovers of interrupted builds are never complete: remove them.
    for stale in out.glob(".*.partial-*"):
        shutil.rmtree(stale, ignore_errors=True)
    write_index(out, preset or "custom", names, cfg)
    from tqdm import tqdm

    todo = [(n, out, cfg) for n in names]
    results: list[SceneStats] = []
    bar = tqdm(total=len(todo), desc=f"world {preset or 'custom'}", unit="scene", disable=not progress)
    try:
        if workers <= 1:
            from ..render.gl import Renderer

            renderer = Renderer(cfg.image_size, cfg.tiles)
            try:
                for t in todo:
                    results.append(build_scene(*t, renderer=renderer))
                    bar.set_postfix(states=sum(r.states for r in results))
                    bar.update()
            finally:
                renderer.release()
        else:
            from ..render.gl import Renderer

            Renderer(16, 1).release()  # fail fast, in this process, when EGL is missing
            ctx = mp.get_context("spawn")
            with ctx.Pool(workers, initializer=_init_worker, initargs=(cfg.image_size, cfg.tiles)) as pool:
                for r in pool.imap_unordered(_build_one, todo):
                    results.append(r)
                    bar.set_postfix(states=sum(x.states for x in results))
                    bar.update()
    finally:
        bar.close()
    order = {n: i for i, n in enumerate(names)}
    return sorted(results, key=lambda r: order[r.name])


__all__ = ["build_dataset", "BuildConfig", "check_output_dir", "replace"]
