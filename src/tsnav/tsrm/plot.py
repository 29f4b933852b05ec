"""Top-down picture of one episode under the Two-Stage Reward Mechanism (paper Fig. 2, section III-B).

Draws the floor, furniture footprints (``scene.json`` ``furniture[].footprint`` when present), the searched
region ``RG`` (shapely union of the searching-stage trapezoids, clipped to the floor), the path coloured by
stage, the stage-switch frame, and the instances of the target category.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import shapely
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import PathPatch, Polygon as MplPolygon
from matplotlib.path import Path as MplPath

from ..atomic import atomic_save_figure
from ..constants import C_TARGET
from ..sim.stage import switch_frame
from .area import scene_floor, trapezoid
from .reward import RewardConfig


SEARCH_COLOR = "#1f77b4"
PATH_COLOR = "#d62728"


@dataclass
class EpisodeStages:
    """Stage bookkeeping of one episode (frames 0..T: the start frame, then one frame per step).

    ``switch_frame``: first frame whose target confidence exceeds C_target (the start frame counts), or -1.
    ``searching_frames``: the frames whose views form ``RG`` - the start frame and every frame reached by a
    searching-stage step, the switching frame included (see :mod:`tsnav.tsrm.reward`).
    """

    switch_frame: int
    searching_frames: np.ndarray


def episode_stages(
    states: Sequence[int], target: int, confidence: np.ndarray, c_target: float = C_TARGET
) -> EpisodeStages:
    """Stages of the frames ``states`` (scene-local ids, start first) for ``target`` (category id)."""
    states = np.asarray(states, dtype=np.int64)
    switch = switch_frame(np.asarray(confidence)[states, int(target)], c_target)
    if switch == 0:
        frames = np.zeros(0, dtype=np.int64)  # the episode starts in the pathfinding stage: nothing searched
    else:
        frames = np.arange(len(states) if switch < 0 else switch + 1)
    return EpisodeStages(switch, frames)


def searched_region(scene, states: Sequence[int], config: RewardConfig = RewardConfig()):
    """``RG`` of the given frames: the union of their trapezoids clipped to the floor (shapely geometry)."""
    states = np.asarray(states, dtype=np.int64)
    if len(states) == 0:
        return shapely.Polygon()
    traps = [
        trapezoid(float(scene.x[s]), float(scene.z[s]), int(scene.rotation[s]), int(scene.horizon[s]), config.area)
        for s in np.unique(states)
    ]
    return shapely.intersection(shapely.union_all(traps), scene_floor(scene))


def _fill(ax, geom, **kw) -> None:
    polys = (
        [geom]
        if isinstance(geom, shapely.Polygon)
        else [g for g in getattr(geom, "geoms", []) if isinstance(g, shapely.Polygon)]
    )
    for p in polys:
        if p.is_empty:
            continue
        rings = [np.asarray(p.exterior.coords)] + [np.asarray(r.coords) for r in p.interiors]
        verts = np.concatenate(rings)
        codes = np.concatenate(
            [[MplPath.MOVETO] + [MplPath.LINETO] * (len(r) - 2) + [MplPath.CLOSEPOLY] for r in rings]
        )
        ax.add_patch(PathPatch(MplPath(verts, codes), **kw))


def draw_episode(
    scene,
    states: Sequence[int],
    target: int | str,
    path: str | Path,
    confidence: np.ndarray | None = None,
    config: RewardConfig = RewardConfig(),
    title: str | None = None,
    dpi: int = 120,
    c_target: float = C_TARGET,
) -> Path:
    """Write a PNG of one episode of ``scene`` and return its path.

    ``states``: scene-local state ids of the frames, start first; ``target``: category name or id;
    ``confidence``: ``(S, C)`` target confidence per state (default: 1.0 where the category is in frame);
    the stages switch above ``c_target``; ``config.area`` is the observable trapezoid.
    """
    g = scene.class_set.index[target] if isinstance(target, str) else int(target)
    states = np.asarray(states, dtype=np.int64)
    if states.ndim != 1 or len(states) == 0:
        raise ValueError("draw_episode needs at least the start state")
    if states.min() < 0 or states.max() >= scene.num_states:
        raise ValueError(f"state ids must be in [0, {scene.num_states}) for scene {scene.name}")
    if confidence is None:
        seen = scene.visible_at_any_range()
        confidence = np.zeros((scene.num_states, scene.num_categories), dtype=np.float32)
        cols = np.flatnonzero(scene.object_category == g)
        confidence[:, g] = seen[:, cols].any(axis=1) if len(cols) else 0.0
    st = episode_stages(states, g, confidence, c_target)
    region = searched_region(scene, states[st.searching_frames], config)

    fig = Figure(figsize=(7.5, 5.5), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(111)
    floor = scene_floor(scene)
    _fill(ax, floor, facecolor="#f3efe6", edgecolor="#444", lw=1.5, zorder=0)
    for f in scene.meta.get("furniture", []):
        if "footprint" in f:
            ax.add_patch(
                MplPolygon(
                    np.asarray(f["footprint"]), closed=True, facecolor="#b9aa94", edgecolor="#6b5d49", lw=0.8, zorder=1
                )
            )
    _fill(ax, region, facecolor=SEARCH_COLOR, alpha=0.18, edgecolor=SEARCH_COLOR, lw=0.6, zorder=2)

    px, pz = scene.x[states].astype(float), scene.z[states].astype(float)
    cut = len(states) if st.switch_frame < 0 else st.switch_frame + 1
    ax.plot(px[:cut], pz[:cut], "-", color=SEARCH_COLOR, lw=2, zorder=4, label="searching")
    if st.switch_frame >= 0:
        ax.plot(
            px[st.switch_frame :], pz[st.switch_frame :], "-", color=PATH_COLOR, lw=2, zorder=4, label="pathfinding"
        )
        ax.scatter(
            [px[st.switch_frame]],
            [pz[st.switch_frame]],
            marker="*",
            s=220,
            color="gold",
            edgecolors="k",
            zorder=6.5,
            label="stage switch",
        )  # above the start marker, below the hollow end
    rad = np.deg2rad(scene.rotation[states[0]])
    ax.annotate(
        "",
        xy=(px[0] + 0.3 * np.sin(rad), pz[0] + 0.3 * np.cos(rad)),
        xytext=(px[0], pz[0]),
        arrowprops=dict(arrowstyle="->", color="k", lw=1.5),
        zorder=6,
    )
    ax.scatter([px[0]], [pz[0]], marker="o", s=50, color="white", edgecolors="k", zorder=6, label="start")
    ax.scatter(
        [px[-1]], [pz[-1]], marker="s", s=40, facecolors="none", edgecolors="k", linewidths=1.5, zorder=7, label="end"
    )  # hollow, so a stage-switch star under it stays visible
    name = scene.class_set.categories[g]
    objs = [
        o
        for o in scene.meta.get("objects", [])
        if o.get("objectType", str(o.get("objectId", "")).split("|")[0]) == name and "position" in o
    ]
    if objs:
        ax.scatter(
            [o["position"]["x"] for o in objs],
            [o["position"]["z"] for o in objs],
            marker="X",
            s=120,
            color="#2ca02c",
            edgecolors="k",
            zorder=7,
            label=f"target: {name}",
        )

    x0, z0, x1, z1 = floor.bounds
    xs = np.concatenate([[x0, x1], px])
    zs = np.concatenate([[z0, z1], pz])
    ax.set_xlim(xs.min() - 0.3, xs.max() + 0.3)
    ax.set_ylim(zs.min() - 0.3, zs.max() + 0.3)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    fig.legend(loc="outside right upper", fontsize=7, framealpha=0.8)
    ax.set_title(
        title or f"{scene.name}: target {name}, {len(states) - 1} steps, searched {region.area:.2f} m$^2$", fontsize=9
    )
    return atomic_save_figure(fig, path, dpi=dpi)
