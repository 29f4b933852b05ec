"""``tsnav show SCENE_DIR``: a PNG of a scene: top-down map beside first-person RGB / depth / id views; and the
first-person frames of given states (:func:`frame_images`, read from ``images.hdf5`` or rendered), which the report's
gallery and the evaluation's clips (:mod:`tsnav.eval.video`) show."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Sequence

import h5py
import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Polygon as MplPolygon

from ..atomic import atomic_save_figure
from ..constants import TARGET_CATEGORIES, camera_height_of
from ..data.reader import SceneFormatError, load_scene
from ..errors import CommandError
from ..render.gl import Renderer


def category_colors() -> dict[str, tuple]:
    """A colour per target category (tab20, then Set1)."""
    cmap = matplotlib.colormaps["tab20"]
    return {
        c: cmap(i % 20) if i < 20 else matplotlib.colormaps["Set1"](i - 20) for i, c in enumerate(TARGET_CATEGORIES)
    }


def draw_topdown(ax, scene, show_grid: bool = True, label_objects: bool = True) -> None:
    """Floor, furniture footprints, target objects by category and (optionally) the reachable grid."""
    meta = scene.meta
    for poly in scene.floor:
        ax.add_patch(MplPolygon(poly, closed=True, facecolor="#f3efe6", edgecolor="#444", lw=1.5, zorder=0))
    for f in meta.get("furniture", []):
        if not f.get("blocks", True):  # small things on receptacles, wall fixtures: outline only, no label
            ax.add_patch(MplPolygon(f["footprint"], closed=True, fill=False, edgecolor="#a89a86", lw=0.4, zorder=1))
            continue
        ax.add_patch(
            MplPolygon(f["footprint"], closed=True, facecolor="#b9aa94", edgecolor="#6b5d49", lw=0.8, zorder=1)
        )
        c = np.mean(f["footprint"], axis=0)
        ax.text(c[0], c[1], f["category"], fontsize=5, ha="center", va="center", color="#3b3226", zorder=2)
    if show_grid:
        pos = np.unique(np.stack([scene.x, scene.z], 1), axis=0)
        ax.scatter(pos[:, 0], pos[:, 1], s=2, c="#7a9cc6", zorder=2, linewidths=0)
    colors = category_colors()
    for o in meta.get("objects", []):
        p = o["position"]
        cat = o["objectType"]
        ax.scatter([p["x"]], [p["z"]], s=28, color=colors.get(cat, "k"), edgecolors="k", linewidths=0.5, zorder=4)
        if label_objects:
            ax.annotate(cat, (p["x"], p["z"]), fontsize=5.5, xytext=(3, 3), textcoords="offset points", zorder=5)
    xs = np.concatenate([np.asarray(p)[:, 0] for p in scene.floor]) if scene.floor else scene.x
    zs = np.concatenate([np.asarray(p)[:, 1] for p in scene.floor]) if scene.floor else scene.z
    ax.set_xlim(xs.min() - 0.2, xs.max() + 0.2)
    ax.set_ylim(zs.min() - 0.2, zs.max() + 0.2)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")


def scene_poses(scene, idx=None) -> np.ndarray:
    """``(V, 4)`` rows ``(x, z, rotation, horizon)`` of a scene's states (``idx``: those rows only; default all),
    what :meth:`tsnav.render.gl.Renderer.render` takes."""
    sel = slice(None) if idx is None else np.asarray(idx)
    return np.stack([scene.x[sel], scene.z[sel], scene.rotation[sel], scene.horizon[sel]], 1).astype(np.float64)


def render_views(scene, poses: np.ndarray, size: int = 128):
    """Render ``poses`` (V, 4: x, z, rotation, horizon) of a tsnav scene folder with the scene's parts, from the
    camera height it was built with."""
    r = Renderer(size, tiles=max(1, len(poses)))
    try:
        r.set_scene(np.array(scene.meta["parts"], dtype=np.float32), scene.meta.get("light"))
        return r.render(poses, height=camera_height_of(scene.meta))
    finally:
        r.release()


def frame_images(scene, keys: Sequence[str]) -> np.ndarray:
    """``(K, H, W, 3)`` uint8 first-person frames of ``keys``: from ``images.hdf5`` when the scene has it,
    else rendered from ``scene.json`` (needs EGL); ``ValueError`` when neither is possible."""
    p = scene.images_path()
    if p is not None:
        with h5py.File(p, "r") as f:
            return np.stack([f[k][()] for k in keys]).astype(np.uint8)
    if "parts" not in scene.meta:
        raise ValueError(f"{scene.path}: no images.hdf5 and no render parts: no first-person frames")

    rgb, _, _ = render_views(scene, scene_poses(scene, scene.indices(list(keys))), size=scene.image_size or 128)
    return np.asarray(rgb, dtype=np.uint8)


def id_colors(ids: np.ndarray) -> np.ndarray:
    rng = np.random.default_rng(0)
    lut = (rng.uniform(0.15, 1.0, (int(ids.max()) + 1, 3)) * 255).astype(np.uint8)
    lut[0] = 0
    return lut[ids]


def show_scene(scene_dir: str | Path, out: str | Path, size: int = 128) -> Path:
    scene = load_scene(scene_dir)
    if "parts" not in scene.meta:
        raise CommandError(f"{scene_dir}: no tsnav scene.json with render parts (imported data cannot be re-rendered)")
    pos = np.unique(np.stack([scene.x, scene.z], 1), axis=0)
    centre = pos[np.argmin(np.linalg.norm(pos - pos.mean(0), axis=1))]
    poses = np.array([[centre[0], centre[1], r, 0] for r in (0, 90, 180, 270)] + [[centre[0], centre[1], 45, 30]])
    rgb, depth, ids = render_views(scene, poses, size)
    fig = Figure(figsize=(15, 6.2), dpi=110)
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(3, 7, width_ratios=[2.2, 2.2, 1, 1, 1, 1, 1])
    ax = fig.add_subplot(gs[:, :2])
    draw_topdown(ax, scene)
    for k, (r, h) in enumerate(poses[:, 2:]):
        dx, dz = np.sin(np.deg2rad(r)), np.cos(np.deg2rad(r))
        ax.arrow(centre[0], centre[1], 0.4 * dx, 0.4 * dz, head_width=0.08, color="crimson", zorder=6)
    ax.set_title(
        f"{scene.name} ({scene.room_type}, {scene.meta.get('split')}): {scene.num_states} states, "
        f"{len(scene.object_ids)} targets",
        fontsize=9,
    )
    for k in range(len(poses)):
        for row, (img, cmap) in enumerate(((rgb[k], None), (depth[k], "viridis"), (id_colors(ids[k]), None))):
            a = fig.add_subplot(gs[row, 2 + k])
            a.imshow(img, cmap=cmap)
            a.set_xticks([])
            a.set_yticks([])
            if row == 0:
                a.set_title(f"rot {int(poses[k, 2])} hor {int(poses[k, 3])}", fontsize=7)
            if k == 0:
                a.set_ylabel(("RGB", "depth (m)", "instance ids")[row], fontsize=8)
    fig.tight_layout()
    out = atomic_save_figure(fig, out)
    return out


def build_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene_dir", help="a scene folder written by `tsnav world`")
    p.add_argument("--out", default=None, help="PNG path (default: SCENE_DIR/show.png)")
    p.add_argument("--size", type=int, default=160, help="first-person view size, pixels")


def run(args) -> int:
    out = args.out or str(Path(args.scene_dir) / "show.png")
    try:
        path = show_scene(args.scene_dir, out, args.size)
    except SceneFormatError as e:
        raise CommandError(str(e)) from None
    print(f"wrote {path}")
    return 0
