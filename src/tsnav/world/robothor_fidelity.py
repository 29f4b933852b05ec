"""Fidelity of a built ``robothor-real`` world against the RoboTHOR ObjectNav challenge's episodes (issue 46).

Per scene, over the challenge's episodes of that scene (a folder ``EPISODES/{train,val}/SCENE.json.gz``, the
format of ``allenai/robothor-challenge`` ``dataset/{train,val}/episodes/``):

* **starts kept**: the share of episode start positions (on the 0.25 m grid) that are positions of tsnav's graph
  (distinct positions too);
* **path ratio**: tsnav's shortest path from the start position to a success state of the episode's target type
  (Done with an object of that type visible, at least the writer's ``min_pixels``, and its footprint within
  :data:`SUCCESS_DISTANCE` m: the ``paper`` protocol), in metres along the grid (0.25 m per axis move, 0.25 * sqrt 2
  per diagonal one; turns and looks cost no metres), over the challenge's ``shortest_path_length`` (metres along
  the navmesh to where the target is within 1 m). Episodes whose challenge length is 0 (the start already succeeds)
  are counted apart; a start that is not a state, or a type no state of the scene succeeds for, has no ratio and
  counts as outside every band;
* **end ratio** (a diagnostic that leaves the success rule out): tsnav's shortest path from the start position to
  the position where the challenge's shortest path ends (its last point rounded to the 0.25 m grid), over
  ``shortest_path_length``. The challenge's paths end at a position from which the target succeeds, the one nearest
  the start of those its episodes end at; so where the path ratio is far from 1 and the end ratio is not, the walls,
  furniture and grid metric agree and the two worlds' success positions do not. An end that is not a tsnav position
  has no end ratio (``end_missing``); episodes without ``shortest_path`` have none either.
* **generator ratio** (a diagnostic of which success position the challenge measured to): AI2-THOR's
  ``GetShortestPath`` to an object does not head for the nearest position from which it succeeds. It searches
  breadth-first from the start over 0.25 m moves along the world axes (+x, +z, -x, -z, in that order; a point is
  tested when taken from the queue, a neighbour is considered once, whether its move is free or not) and ends at
  the first point from which the object is visible, then measures the navmesh path there. :func:`generator_ends`
  runs that search on tsnav's positions and success positions; the ratio is tsnav's metres to the position it
  ends at over ``shortest_path_length``. Close to the path ratio, it says the rule that chose the challenge's ends
  is not what separates the two worlds' lengths.

:func:`path_lengths` computes the lengths with a multi-source Dijkstra over the position graph (scipy);
:func:`path_lengths_reference` is the slow reference (heap Dijkstra per start) the tests hold it to.
"""

from __future__ import annotations

import gzip
import heapq
import json
import math
from pathlib import Path

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from ..atomic import atomic_save_figure, atomic_write_text
from ..constants import GRID_SIZE, ROTATIONS
from ..data.reader import is_complete, load_scene
from .fidelity import cell, scene_moves
from .spec import box_footprint

#: The challenge's success distance, metres.
SUCCESS_DISTANCE = 1.0
#: Band around 1 within which a path ratio counts as close (the issue's goal: 90 % of episodes within +-25 %).
BAND = 0.25


class EpisodesError(ValueError):
    """An episodes folder or file is malformed; the message is one line naming it and the problem."""


def load_episodes(folder: str | Path, scene: str) -> list[dict]:
    """The challenge episodes of ``scene`` from ``folder/{train,val}/SCENE.json.gz`` ([] when there is none)."""
    folder = Path(folder)
    for split in ("train", "val"):
        p = folder / split / f"{scene}.json.gz"
        if p.exists():
            try:
                eps = json.loads(gzip.decompress(p.read_bytes()))
            except (OSError, ValueError) as e:
                raise EpisodesError(f"{p}: unreadable ({e})") from None
            if not isinstance(eps, list):
                raise EpisodesError(f"{p}: expected a list of episodes")
            for k, e in enumerate(eps):
                for f in ("object_type", "initial_position", "shortest_path_length"):
                    if f not in e:
                        raise EpisodesError(f"{p}: episode {k} has no {f!r}")
            return eps
    return []


def step_lengths(positions: np.ndarray, move: np.ndarray) -> csr_matrix:
    """The position graph as a sparse matrix of metres: ``[a, b]`` the length of MoveAhead from ``a`` to ``b``."""
    src, k = np.nonzero(move >= 0)
    dst = move[src, k]
    length = np.hypot(*(positions[dst] - positions[src]).T)
    n = len(positions)
    return csr_matrix((length, (src, dst)), shape=(n, n))


def path_lengths(positions: np.ndarray, move: np.ndarray, goals: np.ndarray) -> np.ndarray:
    """``(P,)`` metres from every position to the nearest position of ``goals`` (bool ``(P,)``) along MoveAheads;
    inf when none is reachable."""
    if not goals.any():
        return np.full(len(positions), np.inf)
    g = step_lengths(positions, move).T.tocsr()  # reversed edges: distances *to* the goals
    d = dijkstra(g, directed=True, indices=np.flatnonzero(goals), min_only=True)
    return np.asarray(d, dtype=np.float64)


def path_lengths_reference(positions: np.ndarray, move: np.ndarray, goals: np.ndarray, start: int) -> float:
    """Slow reference of :func:`path_lengths` for one start: a heap Dijkstra over MoveAheads."""
    dist = {start: 0.0}
    heap = [(0.0, start)]
    while heap:
        d, p = heapq.heappop(heap)
        if d > dist.get(p, math.inf):
            continue
        if goals[p]:
            return d
        for q in move[p]:
            q = int(q)
            if q < 0:
                continue
            nd = d + math.hypot(*(positions[q] - positions[p]))
            if nd < dist.get(q, math.inf) - 1e-12:
                dist[q] = nd
                heapq.heappush(heap, (nd, q))
    return math.inf


def type_goals(scene, positions: np.ndarray, distance: float = SUCCESS_DISTANCE) -> dict[str, np.ndarray]:
    """Per object type of the scene: ``(P,)`` bool, the positions with a state where an object of that type is
    visible (``min_pixels``) and within ``distance`` m (the ``paper`` success rule; any heading and horizon)."""
    ok = scene.visible_at_any_range() & (scene.distance <= distance)
    cells = np.round(np.stack([scene.x, scene.z], axis=1) / GRID_SIZE).astype(np.int64)
    index = {(int(a), int(b)): n for n, (a, b) in enumerate(np.round(positions / GRID_SIZE).astype(np.int64))}
    pos_of_state = np.array([index[(int(a), int(b))] for a, b in cells])
    out: dict[str, np.ndarray] = {}
    for j, oid in enumerate(scene.object_ids.tolist()):
        t = oid.split("|", 1)[0]
        g = out.setdefault(t, np.zeros(len(positions), bool))
        g[pos_of_state[ok[:, j]]] = True
    return out


def end_lengths(positions: np.ndarray, move: np.ndarray, ends: list[int]) -> dict[int, np.ndarray]:
    """Per position id of ``ends``: ``(P,)`` metres from every position to it along MoveAheads (inf when it cannot
    be reached); one Dijkstra over the reversed graph for all of them."""
    ends = sorted(set(ends))
    if not ends:
        return {}
    g = step_lengths(positions, move).T.tocsr()
    d = np.atleast_2d(dijkstra(g, directed=True, indices=ends))
    return {e: np.asarray(d[k], dtype=np.float64) for k, e in enumerate(ends)}


#: The order in which AI2-THOR's search for a path's end takes a point's neighbours: +x, +z, -x, -z (grid cells).
GENERATOR_ORDER = ((1, 0), (0, 1), (-1, 0), (0, -1))


def axis_moves(positions: np.ndarray, move: np.ndarray) -> dict[int, dict[tuple[int, int], int]]:
    """Per position id: its free moves along the world axes, ``{(di, dj) grid step: position id}``."""
    cells = np.round(positions / GRID_SIZE).astype(np.int64)
    axis: dict[int, dict[tuple[int, int], int]] = {}
    src, k = np.nonzero(move >= 0)
    for a, b in zip(src.tolist(), move[src, k].tolist()):
        d = (int(cells[b, 0] - cells[a, 0]), int(cells[b, 1] - cells[a, 1]))
        if d in GENERATOR_ORDER:
            axis.setdefault(a, {})[d] = b
    return axis


def generator_ends(
    positions: np.ndarray,
    move: np.ndarray,
    goals: dict[str, np.ndarray],
    start: int,
    axis: dict[int, dict[tuple[int, int], int]] | None = None,
) -> dict[str, int]:
    """Per type of ``goals`` (``(P,)`` bool success positions): the position AI2-THOR's shortest-path generator ends
    at from ``start`` (module docstring, generator ratio): a breadth-first search over moves along the world axes in
    :data:`GENERATOR_ORDER`, each point tested when taken from the queue (the start first), each neighbour cell
    considered once (marked when first looked at, even when the move there is blocked). Types with no success
    position the search reaches are left out. ``axis``: :func:`axis_moves` of the scene, when already made."""
    cells = np.round(positions / GRID_SIZE).astype(np.int64)
    axis = axis_moves(positions, move) if axis is None else axis
    left = {t: g for t, g in goals.items() if g.any()}
    found: dict[str, int] = {}
    queue, done, seen = [start], set(), set()
    head = 0
    while head < len(queue) and left:
        p = queue[head]
        head += 1
        if p in done:
            continue
        done.add(p)
        for t in [t for t, g in left.items() if g[p]]:
            found[t] = p
            del left[t]
        c = (int(cells[p, 0]), int(cells[p, 1]))
        for d in GENERATOR_ORDER:
            q = (c[0] + d[0], c[1] + d[1])
            if q in seen:
                continue
            seen.add(q)
            n = axis.get(p, {}).get(d)
            if n is not None:
                queue.append(n)
    return found


def path_end(e: dict) -> tuple[int, int] | None:
    """The grid cell where the challenge episode ``e``'s shortest path ends (None when it has no path)."""
    path = e.get("shortest_path") or []
    if not path:
        return None
    return cell(float(path[-1]["x"]), float(path[-1]["z"]))


def measure_scene(scene, episodes: list[dict]) -> dict:
    """The fidelity of one loaded scene folder against its episodes (module docstring): counts, per-episode
    ratios (to a success state, and to the challenge's path end), and the start positions tsnav lacks."""
    positions, move = scene_moves(scene)
    index = {cell(float(x), float(z)): n for n, (x, z) in enumerate(positions)}
    goals = type_goals(scene, positions)
    dist = {t: path_lengths(positions, move, g) for t, g in goals.items()}
    to_end = end_lengths(positions, move, [index[c] for c in map(path_end, episodes) if c in index])
    kept_starts = sorted(
        {
            index[c]
            for c in (cell(float(e["initial_position"]["x"]), float(e["initial_position"]["z"])) for e in episodes)
            if c in index
        }
    )
    metres = dijkstra(step_lengths(positions, move), directed=True, indices=kept_starts) if kept_starts else []
    from_start = dict(zip(kept_starts, np.atleast_2d(metres)))
    axis = axis_moves(positions, move)
    gen_ends = {s: generator_ends(positions, move, goals, s, axis) for s in kept_starts}
    gen_ratios = []
    end_ratios, end_missing = [], 0
    starts, kept, missing = 0, 0, set()
    ratios, zero, zero_ok, no_goal = [], 0, 0, 0
    rows = []
    for e in episodes:
        p = e["initial_position"]
        c = cell(float(p["x"]), float(p["z"]))
        starts += 1
        s = index.get(c)
        L = float(e["shortest_path_length"])
        t = e["object_type"]
        if s is None:
            missing.add(c)
            rows.append([t, L, None])
            continue
        kept += 1
        d = float(dist[t][s]) if t in dist else math.inf
        if not math.isfinite(d):
            no_goal += 1
        if L <= 1e-6:
            zero += 1
            zero_ok += d == 0.0
            rows.append([t, L, d if math.isfinite(d) else None])
            continue
        ratios.append(d / L)
        g = gen_ends[s].get(t)
        gen_ratios.append(float(from_start[s][g]) / L if g is not None else math.inf)
        k = index.get(path_end(e)) if e.get("shortest_path") else None
        de = float(to_end[k][s]) if k is not None else math.inf
        if e.get("shortest_path"):
            end_missing += k is None
            end_ratios.append(de / L)
        rows.append(
            [t, round(L, 4), round(d, 4) if math.isfinite(d) else None, round(de, 4) if math.isfinite(de) else None]
        )
    distinct = {cell(float(e["initial_position"]["x"]), float(e["initial_position"]["z"])) for e in episodes}
    return {
        "scene": scene.name,
        "episodes": starts,
        "starts_kept": kept,
        "distinct_starts": len(distinct),
        "distinct_kept": sum(c in index for c in distinct),
        "positions": len(positions),
        "zero_length": zero,
        "zero_length_ok": int(zero_ok),
        "no_success_state": no_goal,
        "ratios": [round(r, 4) if math.isfinite(r) else None for r in ratios],
        "end_ratios": [round(r, 4) if math.isfinite(r) else None for r in end_ratios],
        "generator_ratios": [round(r, 4) if math.isfinite(r) else None for r in gen_ratios],
        "end_missing": end_missing,
        "missing_starts": sorted([i * GRID_SIZE, j * GRID_SIZE] for i, j in missing),
        "episodes_table": rows,
    }


def ratio_summary(ratios: list, episodes: int, kept: int) -> dict:
    """Summary figures of ``ratios`` (None: no tsnav path), with the start shares."""
    r = np.array([np.inf if v is None else v for v in ratios], dtype=np.float64)
    fin = r[np.isfinite(r)]
    return {
        "episodes": episodes,
        "starts_kept": kept,
        "starts_kept_pct": round(100.0 * kept / max(episodes, 1), 2),
        "ratios": int(len(r)),
        "median": round(float(np.median(r)), 4) if len(r) else None,
        "mean_finite": round(float(fin.mean()), 4) if len(fin) else None,
        "p10": round(float(np.percentile(r, 10, method="lower")), 4) if len(r) else None,
        "p90": round(float(np.percentile(r, 90, method="higher")), 4) if len(r) else None,
        "within_25_pct": round(100.0 * float((np.abs(r - 1) <= BAND).mean()), 2) if len(r) else None,
        "within_10_pct": round(100.0 * float((np.abs(r - 1) <= 0.10).mean()), 2) if len(r) else None,
        "no_path": int((~np.isfinite(r)).sum()),
    }


def band_summary(ratios: list, prefix: str) -> dict:
    """Figures of a diagnostic ratio (None: no tsnav path), each key ``PREFIX_...``: count, median, shares within
    +-25 % and +-10 %, and how many have no path."""
    r = np.array([np.inf if v is None else v for v in ratios], dtype=np.float64)
    if not len(r):
        return {f"{prefix}_ratios": 0}
    return {
        f"{prefix}_ratios": int(len(r)),
        f"{prefix}_median": round(float(np.median(r)), 4),
        f"{prefix}_within_25_pct": round(100.0 * float((np.abs(r - 1) <= BAND).mean()), 2),
        f"{prefix}_within_10_pct": round(100.0 * float((np.abs(r - 1) <= 0.10).mean()), 2),
        f"{prefix}_no_path": int((~np.isfinite(r)).sum()),
    }


def end_summary(end_ratios: list) -> dict:
    """Figures of the end ratios (None: the end is not a tsnav position or cannot be reached)."""
    return band_summary(end_ratios, "end")


def generator_summary(ratios: list) -> dict:
    """Figures of the generator ratios (None: the search reaches no success position)."""
    return band_summary(ratios, "generator")


def summarise(scenes: list[dict], split: str) -> dict:
    """Totals over the scenes of one split (``train`` or ``val``)."""
    mine = [s for s in scenes if s["split"] == split]
    out = ratio_summary(
        [v for s in mine for v in s["ratios"]], sum(s["episodes"] for s in mine), sum(s["starts_kept"] for s in mine)
    )
    out.update(end_summary([v for s in mine for v in s.get("end_ratios", [])]))
    out.update(generator_summary([v for s in mine for v in s.get("generator_ratios", [])]))
    out.update(
        {
            "scenes": len(mine),
            "distinct_starts": sum(s["distinct_starts"] for s in mine),
            "distinct_kept": sum(s["distinct_kept"] for s in mine),
            "zero_length": sum(s["zero_length"] for s in mine),
            "zero_length_ok": sum(s["zero_length_ok"] for s in mine),
        }
    )
    return out


# ------------------------------------------------------------------------------------------------ picture
def draw_scene(ax, plan: np.ndarray, meta: dict, positions: np.ndarray, missing: list) -> None:
    """The plan with tsnav's reachable positions (green dots), walls (cyan), blocking footprints (yellow),
    objects of the scene (red: on the floor, magenta: elsewhere; labelled) and the challenge's start positions
    that are not tsnav states (red crosses), on ``ax`` in world metres (x right, z up)."""
    from matplotlib.patches import Polygon as MplPolygon

    from . import plans as P

    r = 0.5 * P.PIXEL
    ax.imshow(
        plan,
        extent=(
            P.X0 - r,
            P.X0 + (P.PLAN_PX - 0.5) * P.PIXEL,
            P.Z0 + P.SPAN - (P.PLAN_PX - 0.5) * P.PIXEL,
            P.Z0 + P.SPAN + r,
        ),
        interpolation="nearest",
    )
    insts = meta.get("instances", [])
    wall = {i for i, n in enumerate(insts) if n == "Wall"}
    for row in meta.get("parts", []):
        if int(row[15]) in wall:
            ax.add_patch(
                MplPolygon(
                    box_footprint(row[0:3], row[3:6], row[6]),
                    closed=True,
                    facecolor="cyan",
                    alpha=0.55,
                    edgecolor="none",
                )
            )
    for f in meta.get("furniture", []):
        if f.get("blocks", True):
            ax.add_patch(MplPolygon(f["footprint"], closed=True, fill=False, edgecolor="yellow", lw=0.6))
    for o in meta.get("objects", []):
        b = o["bbox"]
        ax.add_patch(
            MplPolygon(
                box_footprint(b["center"], b["size"], b.get("yaw", 0.0)),
                closed=True,
                fill=False,
                edgecolor="red" if o["support"] == "floor" else "magenta",
                lw=0.9,
            )
        )
        ax.text(b["center"][0], b["center"][2], o["objectType"], color="white", fontsize=5)
    ax.plot(positions[:, 0], positions[:, 1], ".", color="lime", ms=2.5, label="tsnav positions")
    if missing:
        m = np.asarray(missing, dtype=np.float64)
        ax.plot(m[:, 0], m[:, 1], "x", color="red", ms=4, label="challenge starts tsnav lacks")
    floor = meta.get("floor") or [[[0, 0]]]
    xs = [p[0] for poly in floor for p in poly]
    zs = [p[1] for poly in floor for p in poly]
    ax.set_xlim(min(xs) - 0.4, max(xs) + 0.4)
    ax.set_ylim(min(zs) - 0.4, max(zs) + 0.4)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=6)


def save_scene_png(
    path: str | Path, plan: np.ndarray, meta: dict, positions: np.ndarray, missing: list, title: str
) -> Path:
    """One scene's :func:`draw_scene` as a PNG (written atomically)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9.0, 4.6), dpi=90)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.05, 0.08, 0.92, 0.84))
    draw_scene(ax, plan, meta, positions, missing)
    ax.set_title(title, fontsize=8)
    ax.legend(fontsize=6, loc="lower right", framealpha=0.6)
    return atomic_save_figure(fig, path)


def markdown(doc: dict) -> str:
    """The report's tables: per split, then per scene."""
    lines = [
        "| split | scenes | episodes | starts kept % | distinct starts kept | ratio median | p10-p90 | "
        "within +-25 % | within +-10 % | no tsnav path | L = 0 (tsnav 0 too) | end ratio median | "
        "end ratio within +-25 % | generator ratio median | generator ratio within +-25 % |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for split in ("train", "val"):
        s = doc["summary"].get(split)
        if not s or not s["scenes"]:
            continue
        lines.append(
            f"| {split} | {s['scenes']} | {s['episodes']} | {s['starts_kept_pct']:.2f} | "
            f"{s['distinct_kept']}/{s['distinct_starts']} | {s['median']} | {s['p10']}-{s['p90']} | "
            f"{s['within_25_pct']} | {s['within_10_pct']} | {s['no_path']} | {s['zero_length']} "
            f"({s['zero_length_ok']}) | {s.get('end_median')} | {s.get('end_within_25_pct')} | "
            f"{s.get('generator_median')} | {s.get('generator_within_25_pct')} |"
        )
    lines += [
        "",
        "| scene | positions | starts kept % | ratio median | within +-25 % | no tsnav path | end ratio within +-25 % | "
        "generator ratio within +-25 % |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for sc in doc["scenes"]:
        s = ratio_summary(sc["ratios"], sc["episodes"], sc["starts_kept"])
        s.update(end_summary(sc.get("end_ratios", [])))
        s.update(generator_summary(sc.get("generator_ratios", [])))
        lines.append(
            f"| {sc['scene']} | {sc['positions']} | {s['starts_kept_pct']:.1f} | {s['median']} | "
            f"{s['within_25_pct']} | {s['no_path']} | {s.get('end_within_25_pct')} | "
            f"{s.get('generator_within_25_pct')} |"
        )
    return "\n".join(lines) + "\n"


def robothor_fidelity_report(
    data: str | Path, episodes: str | Path, out: str | Path | None = None, pictures: bool = True
) -> tuple[dict, Path]:
    """Measure every complete scene of ``data`` that ``episodes`` has episodes for; write ``fidelity.json``,
    ``fidelity.md`` and (with ``pictures``) ``SCENE.png`` into ``out`` (default ``DATA/fidelity``)."""
    from .robothor_real import load_plan

    data = Path(data)
    if not data.is_dir():
        raise FileNotFoundError(f"{data}: no such dataset folder")
    names = sorted(p.name for p in data.iterdir() if p.is_dir() and is_complete(p))
    out = Path(out) if out is not None else data / "fidelity"
    out.mkdir(parents=True, exist_ok=True)
    scenes = []
    for name in names:
        eps = load_episodes(episodes, name)
        if not eps:
            continue
        scene = load_scene(data / name)
        res = measure_scene(scene, eps)
        res["split"] = scene.meta.get("split", "train" if "_Train" in name else "val")
        scenes.append(res)
        if pictures:
            positions, _ = scene_moves(scene)
            s = ratio_summary(res["ratios"], res["episodes"], res["starts_kept"])
            title = (
                f"{name}: {len(positions)} positions; starts kept {s['starts_kept_pct']:.1f} %; path ratio median "
                f"{s['median']}, within +-25 % {s['within_25_pct']} %"
            )
            save_scene_png(out / f"{name}.png", load_plan(name), scene.meta, positions, res["missing_starts"], title)
    if not scenes:
        raise EpisodesError(f"{episodes}: no episodes for any complete scene of {data}")
    doc = {
        "format": "tsnav-robothor-fidelity",
        "version": 3,
        "data": str(data),
        "episodes": str(episodes),
        "success_distance": SUCCESS_DISTANCE,
        "rotations": list(ROTATIONS),
        "summary": {split: summarise(scenes, split) for split in ("train", "val")},
        "scenes": scenes,
    }
    atomic_write_text(out / "fidelity.json", json.dumps(doc, separators=(",", ":")))
    atomic_write_text(out / "fidelity.md", markdown(doc))
    return doc, out


__all__ = [
    "EpisodesError",
    "axis_moves",
    "band_summary",
    "end_lengths",
    "generator_ends",
    "end_summary",
    "load_episodes",
    "measure_scene",
    "path_lengths",
    "path_lengths_reference",
    "ratio_summary",
    "robothor_fidelity_report",
    "summarise",
    "type_goals",
]
