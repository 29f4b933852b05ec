"""Fidelity of a built world against what real agents did in the real rooms (issue 24).

A trajectories file (format of ``../shared/ai2thor/real_trajectories/dev_scenes.json``) holds, per scene, the
unique ``[state, action, next_state]`` triples that real agents produced on the lineage's real AI2-THOR offline
graphs; a ``MoveAhead`` whose next state equals its state was blocked in the real room. Against a tsnav scene
(its reachable positions and, per position and heading, the position MoveAhead reaches or -1) three shares
are measured, all over the file's triples:

* **positions**: of the distinct positions real agents stood on (state and next state), the share tsnav has;
* **moves kept**: of the real successful MoveAheads, the share that are edges of tsnav's graph (same source
  and target position; the heading follows from them);
* **blocked kept blocked**: of the real blocked MoveAheads, the share tsnav does not let through (a blocked
  move from a position tsnav lacks counts as blocked: tsnav's agent cannot make it either).

Rotations and look actions depend on no geometry and are not measured. Positions tsnav has but no real agent
reached are listed too; they are weak evidence (real agents only went where they went).

Pose drift (:func:`drift_whatifs`): the scene is laid out again without each object behind a disagreement, or with
it moved a few centimetres, to show which poses the figures hang on and what the scene would reach without that
drift (what-ifs only: no rule moves a recorded object).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from shapely.geometry import Point, Polygon
from shapely.ops import unary_union

from ..atomic import atomic_save_figure, atomic_write_text
from ..constants import GRID_SIZE, MOVE_AHEAD, ROTATIONS
from ..data.reader import is_complete, load_scene
from ..errors import read_json
from .navgrid import AGENT_RADIUS, reachable_positions
from .spec import SceneSpec, box_footprint

#: Action names a trajectories file may hold (the lineage's, plus Done).
ACTIONS = ("MoveAhead", "RotateLeft", "RotateRight", "LookUp", "LookDown", "Done")


class TrajectoriesError(ValueError):
    """A trajectories file is malformed; the message is one line naming the file and the problem."""


Triple = tuple[str, str, str]
Cell = tuple[int, int]  # grid indices (round(x / 0.25), round(z / 0.25))


def _parse_key(key, where: str) -> tuple[int, int, int, int]:
    if not isinstance(key, str):
        raise TrajectoriesError(f"{where}: state key must be a string, got {key!r}")
    parts = key.split("|")
    if len(parts) != 4:
        raise TrajectoriesError(f"{where}: state key {key!r} is not x|z|rotation|horizon")
    try:
        x, z, r, h = (float(p) for p in parts)
    except ValueError:
        raise TrajectoriesError(f"{where}: state key {key!r} holds a non-number") from None
    if not all(math.isfinite(v) for v in (x, z, r, h)):
        raise TrajectoriesError(f"{where}: state key {key!r} holds a non-finite number")
    i, j = round(x / GRID_SIZE), round(z / GRID_SIZE)
    if abs(i * GRID_SIZE - x) > 1e-3 or abs(j * GRID_SIZE - z) > 1e-3:
        raise TrajectoriesError(f"{where}: state key {key!r} is off the {GRID_SIZE} m grid")
    if int(round(r)) % 360 not in ROTATIONS:
        raise TrajectoriesError(f"{where}: state key {key!r} has rotation {r:g}, not one of {ROTATIONS}")
    return i, j, int(round(r)) % 360, int(round(h))


def parse_trajectories(doc, where: str) -> dict[str, list[Triple]]:
    """A decoded trajectories document -> ``{scene: [(state, action, next_state), ...]}`` (checked)."""
    if not isinstance(doc, dict) or not isinstance(doc.get("scenes"), dict):
        raise TrajectoriesError(f"{where}: expected {{'scenes': {{SCENE: [[state, action, next_state], ...]}}}}")
    out: dict[str, list[Triple]] = {}
    for scene, triples in doc["scenes"].items():
        if not isinstance(triples, list):
            raise TrajectoriesError(f"{where}: scene {scene!r}: expected a list of triples")
        rows = []
        for n, t in enumerate(triples):
            w = f"{where}: scene {scene!r} triple {n}"
            if not isinstance(t, (list, tuple)) or len(t) != 3:
                raise TrajectoriesError(f"{w}: expected [state, action, next_state], got {t!r}"[:200])
            s, a, s2 = t
            if a not in ACTIONS:
                raise TrajectoriesError(f"{w}: unknown action {a!r} (expected one of {', '.join(ACTIONS)})")
            p0, p1 = _parse_key(s, w), _parse_key(s2, w)
            if a == "MoveAhead" and p0 != p1:
                di, dj = p1[0] - p0[0], p1[1] - p0[1]
                if p1[2:] != p0[2:] or (di, dj) != step(p0[2]):
                    raise TrajectoriesError(f"{w}: MoveAhead {s} -> {s2} is not one grid step ahead")
            rows.append((s, a, s2))
        out[str(scene)] = rows
    return out


def load_trajectories(path: str | Path) -> dict[str, list[Triple]]:
    """Read and check a trajectories file; :class:`TrajectoriesError` (one line) when it is malformed."""
    path = Path(path)
    doc = read_json(path, TrajectoriesError, missing="no such trajectories file")
    return parse_trajectories(doc, str(path))


def step(rotation: int) -> Cell:
    """Grid step ``(di, dj)`` of MoveAhead at heading ``rotation`` (0 faces +z, 90 faces +x)."""
    return int(round(math.sin(math.radians(rotation)))), int(round(math.cos(math.radians(rotation))))


def cell(x: float, z: float) -> Cell:
    return round(x / GRID_SIZE), round(z / GRID_SIZE)


@dataclass
class SceneFidelity:
    """The three shares of one scene and the disagreements behind them (cells are grid indices)."""

    scene: str
    positions: int = 0  #: distinct real positions
    positions_kept: int = 0
    moves: int = 0  #: real successful MoveAhead triples
    moves_kept: int = 0
    blocked: int = 0  #: real blocked MoveAhead triples
    blocked_kept: int = 0
    tsnav_positions: int = 0
    missing: list[Cell] = field(default_factory=list)  #: real positions tsnav lacks
    unvisited: list[Cell] = field(default_factory=list)  #: tsnav positions no real agent stood on
    lost_moves: list[tuple[Cell, Cell]] = field(default_factory=list)  #: real moves that are no tsnav edge
    leaks: list[tuple[Cell, int]] = field(default_factory=list)  #: real blocked (cell, heading) tsnav lets through

    @staticmethod
    def share(a: int, n: int) -> float:
        return 100.0 * a / n if n else float("nan")

    def shares(self) -> dict[str, float]:
        return {
            "positions": self.share(self.positions_kept, self.positions),
            "moves_kept": self.share(self.moves_kept, self.moves),
            "blocked_blocked": self.share(self.blocked_kept, self.blocked),
        }

    def to_json(self) -> dict:
        g = GRID_SIZE
        return {
            "scene": self.scene,
            **{k: round(v, 2) for k, v in self.shares().items()},
            "counts": {
                "positions": self.positions,
                "positions_kept": self.positions_kept,
                "moves": self.moves,
                "moves_kept": self.moves_kept,
                "blocked": self.blocked,
                "blocked_kept": self.blocked_kept,
                "tsnav_positions": self.tsnav_positions,
            },
            "missing_positions": [[i * g, j * g] for i, j in self.missing],
            "unvisited_positions": [[i * g, j * g] for i, j in self.unvisited],
            "lost_moves": [[[a[0] * g, a[1] * g], [b[0] * g, b[1] * g]] for a, b in self.lost_moves],
            "leaked_blocks": [[[c[0] * g, c[1] * g], r] for c, r in self.leaks],
        }


def measure(scene: str, positions: np.ndarray, move: np.ndarray, triples: list[Triple]) -> SceneFidelity:
    """The fidelity of one tsnav scene given as ``positions`` ((P, 2) x, z) and ``move`` ((P, 8): per heading
    of :data:`ROTATIONS`, the index of the position MoveAhead reaches, -1 when blocked) against ``triples``."""
    cells = [cell(float(x), float(z)) for x, z in np.asarray(positions, dtype=np.float64).reshape(-1, 2)]
    index = {c: n for n, c in enumerate(cells)}
    move = np.asarray(move).reshape(len(cells), len(ROTATIONS))
    f = SceneFidelity(scene, tsnav_positions=len(cells))
    real: set[Cell] = set()
    lost, leaks = set(), set()
    for s, a, s2 in triples:
        i, j, r, _ = _parse_key(s, scene)
        i2, j2, _, _ = _parse_key(s2, scene)
        real.add((i, j))
        real.add((i2, j2))
        if a != "MoveAhead":
            continue
        p = index.get((i, j), -1)
        tgt = int(move[p, ROTATIONS.index(r)]) if p >= 0 else -1
        if (i, j) == (i2, j2):
            f.blocked += 1
            if tgt < 0:
                f.blocked_kept += 1
            else:
                leaks.add(((i, j), r))
        else:
            f.moves += 1
            if tgt >= 0 and cells[tgt] == (i2, j2):
                f.moves_kept += 1
            else:
                lost.add(((i, j), (i2, j2)))
    f.positions = len(real)
    f.positions_kept = sum(c in index for c in real)
    f.missing = sorted(real - set(index))
    f.unvisited = sorted(set(index) - real)
    f.lost_moves = sorted(lost)
    f.leaks = sorted(leaks)
    return f


def scene_moves(scene) -> tuple[np.ndarray, np.ndarray]:
    """``(positions, move)`` of a loaded scene folder (:class:`~tsnav.data.reader.Scene`) in the form of
    :func:`~tsnav.world.navgrid.reachable_positions`: MoveAhead at horizon 0 (the graph's moves do not depend on
    the horizon in tsnav worlds; a position's move counts when either horizon has it)."""
    xz = np.stack([scene.x, scene.z], axis=1).astype(np.float64)
    cells = [cell(float(x), float(z)) for x, z in xz]
    uniq = sorted(set(cells))
    index = {c: n for n, c in enumerate(uniq)}
    move = np.full((len(uniq), len(ROTATIONS)), -1, dtype=np.int64)
    nxt = scene.next_state[:, MOVE_AHEAD]
    for s in range(scene.num_states):
        t = int(nxt[s])
        if t != s and cells[t] != cells[s]:
            move[index[cells[s]], ROTATIONS.index(int(scene.rotation[s]) % 360)] = index[cells[t]]
    return np.array(uniq, dtype=np.float64) * GRID_SIZE, move


def summary(results: list[SceneFidelity]) -> dict:
    """Totals over scenes (shares of the summed counts) and the worst scene of each share."""
    tot = SceneFidelity("all")
    for r in results:
        for k in ("positions", "positions_kept", "moves", "moves_kept", "blocked", "blocked_kept", "tsnav_positions"):
            setattr(tot, k, getattr(tot, k) + getattr(r, k))
    out = {k: round(v, 2) for k, v in tot.shares().items()}
    out["counts"] = tot.to_json()["counts"]
    for k in ("positions", "moves_kept", "blocked_blocked"):
        vals = [(r.shares()[k], r.scene) for r in results if not math.isnan(r.shares()[k])]
        if vals:
            v, s = min(vals)
            out[f"worst_{k}"] = {"scene": s, "share": round(v, 2)}
    return out


def markdown_table(results: list[SceneFidelity]) -> str:
    """The per-scene shares as a Markdown table, totals last."""
    lines = [
        "| scene | positions % (kept / real) | moves kept % (kept / real) | blocked blocked % (kept / real) | "
        "tsnav positions |",
        "| --- | --- | --- | --- | --- |",
    ]

    def row(name, r: SceneFidelity):
        s = r.shares()
        return (
            f"| {name} | {s['positions']:.1f} ({r.positions_kept}/{r.positions}) | {s['moves_kept']:.1f} "
            f"({r.moves_kept}/{r.moves}) | {s['blocked_blocked']:.1f} ({r.blocked_kept}/{r.blocked}) | "
            f"{r.tsnav_positions} |"
        )

    tot = SceneFidelity("all")
    for r in results:
        lines.append(row(r.scene, r))
        for k in ("positions", "positions_kept", "moves", "moves_kept", "blocked", "blocked_kept", "tsnav_positions"):
            setattr(tot, k, getattr(tot, k) + getattr(r, k))
    lines.append(row("**all**", tot))
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------------ picture
def draw_fidelity(
    ax,
    meta: dict,
    fid: SceneFidelity,
    positions: np.ndarray,
    triples: list[Triple],
    drift: dict | None = None,
    spec: SceneSpec | None = None,
) -> None:
    """Top-down map of one scene's disagreements on ``ax``: the room (floor polygon, blocking footprints filled
    and labelled, others outlined), tsnav's positions (grey dots), real positions tsnav has (small green dots),
    real positions tsnav lacks (red crosses), tsnav positions no real agent stood on (hollow blue circles),
    real moves that are no tsnav edge (orange segments), real blocked moves tsnav lets through (magenta arrows).
    With the scene's :func:`drift_whatifs` (``drift``) and its ``spec``, the objects it names are drawn too
    (:func:`draw_drift`)."""
    from matplotlib.patches import Polygon as MplPolygon

    g = GRID_SIZE
    for poly in meta.get("floor", []):
        ax.add_patch(MplPolygon(poly, closed=True, facecolor="#f6f3ec", edgecolor="#333", lw=1.4, zorder=0))
    for f in meta.get("furniture", []):
        if f.get("blocks", True):
            ax.add_patch(
                MplPolygon(
                    f["footprint"], closed=True, facecolor="#cdbfa9", edgecolor="#6b5d49", lw=0.6, alpha=0.85, zorder=1
                )
            )
            c = np.mean(f["footprint"], axis=0)
            ax.text(c[0], c[1], f["category"], fontsize=4.5, ha="center", va="center", color="#3b3226", zorder=2)
        else:
            ax.add_patch(MplPolygon(f["footprint"], closed=True, fill=False, edgecolor="#b3a794", lw=0.3, zorder=1))
    for o in meta.get("objects", []):
        b = o.get("bbox")
        if not b:
            continue
        fp = box_footprint(b["center"], b["size"], b.get("yaw", 0.0))
        floor = o.get("support") == "floor"
        ax.add_patch(
            MplPolygon(
                fp,
                closed=True,
                facecolor="#cdbfa9" if floor else "none",
                edgecolor="#6b5d49" if floor else "#b3a794",
                lw=0.5 if floor else 0.3,
                zorder=1,
            )
        )
        if floor:
            ax.text(b["center"][0], b["center"][2], o["objectType"], fontsize=4.5, ha="center", va="center", zorder=2)
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    ax.scatter(pos[:, 0], pos[:, 1], s=3, c="#9a9a9a", linewidths=0, zorder=3, label=f"tsnav position ({len(pos)})")
    real = sorted({cell(*map(float, k.split("|")[:2])) for t in triples for k in (t[0], t[2])})
    kept = np.array([c for c in real if c not in set(fid.missing)], dtype=np.float64).reshape(-1, 2) * g
    ax.scatter(
        kept[:, 0], kept[:, 1], s=5, c="#2e9e44", linewidths=0, zorder=4, label=f"real position tsnav has ({len(kept)})"
    )
    if fid.unvisited:
        u = np.array(fid.unvisited, dtype=np.float64) * g
        ax.scatter(
            u[:, 0],
            u[:, 1],
            s=9,
            facecolors="none",
            edgecolors="#5b8fd6",
            linewidths=0.5,
            zorder=4,
            label=f"tsnav position never reached ({len(u)})",
        )
    for a, b in fid.lost_moves:
        ax.plot([a[0] * g, b[0] * g], [a[1] * g, b[1] * g], color="#f08c00", lw=1.4, alpha=0.9, zorder=5)
    if fid.lost_moves:
        ax.plot([], [], color="#f08c00", lw=1.4, label=f"real move not kept ({len(fid.lost_moves)})")
    for c, r in fid.leaks:
        di, dj = step(r)
        ax.annotate(
            "",
            xy=((c[0] + 0.9 * di) * g, (c[1] + 0.9 * dj) * g),
            xytext=(c[0] * g, c[1] * g),
            zorder=6,
            arrowprops=dict(arrowstyle="-|>", color="#d0209c", lw=1.2, mutation_scale=7),
        )
    if fid.leaks:
        ax.plot([], [], color="#d0209c", lw=1.2, label=f"real blocked move let through ({len(fid.leaks)})")
    if fid.missing:
        m = np.array(fid.missing, dtype=np.float64) * g
        ax.scatter(
            m[:, 0],
            m[:, 1],
            s=26,
            marker="x",
            c="#d62728",
            linewidths=1.3,
            zorder=7,
            label=f"real position tsnav lacks ({len(m)})",
        )
    if drift and spec is not None:
        draw_drift(ax, drift, spec)
    pts = [pos] + [np.asarray(p, dtype=np.float64) for p in meta.get("floor", [])]
    if fid.missing:
        pts.append(np.array(fid.missing, dtype=np.float64) * g)
    allp = np.concatenate(pts)
    ax.set_xlim(allp[:, 0].min() - 0.3, allp[:, 0].max() + 0.3)
    ax.set_ylim(allp[:, 1].min() - 0.3, allp[:, 1].max() + 0.3)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=6)
    s = fid.shares()
    ax.set_title(
        f"{fid.scene}: positions {s['positions']:.1f} %, moves kept {s['moves_kept']:.1f} %, "
        f"blocked {s['blocked_blocked']:.1f} %",
        fontsize=7.5,
    )


def drift_marks(drift: dict, spec: SceneSpec) -> list[dict]:
    """What :func:`draw_drift` draws for a scene's :func:`drift_whatifs`: per object it names whose what-if gains
    something, or that has real positions inside it, ``{"id", "category", "label", "footprints", "moved"}``:
    its footprints (parts included), the same moved by its best what-if's shift (None when removed or no what-if)
    and a label (category, the what-if, real positions inside; ``*`` when it is part of the scene's
    ``without_drift``)."""
    bl = blockers(spec)
    applied = set((drift.get("without_drift") or {}).get("applied", []))
    marks = []
    for e in drift.get("objects", []):
        b = e.get("best")
        if b is None and not e.get("real_inside"):
            continue
        polys = [
            list(poly.exterior.coords)[:-1]
            for oid in [e["id"], *e.get("parts", [])]
            if oid in bl
            for poly in bl[oid][1]
        ]
        what = (
            "no what-if"
            if b is None
            else "removed"
            if b["shift"] is None
            else f"moved {b['shift'][0]:+.2f} x"
            if b["shift"][0]
            else f"moved {b['shift'][1]:+.2f} z"
        )
        label = e["category"] + ("*" if e["id"] in applied else "") + f": {what}"
        if e.get("real_inside"):
            label += f", {e['real_inside']} real inside"
        moved = None
        if b is not None and b["shift"] is not None:
            dx, dz = b["shift"]
            moved = [[(x + dx, z + dz) for x, z in fp] for fp in polys]
        marks.append({"id": e["id"], "category": e["category"], "label": label, "footprints": polys, "moved": moved})
    return marks


def draw_drift(ax, drift: dict, spec: SceneSpec) -> None:
    """The objects of :func:`drift_marks` on ``ax``: each footprint outlined in violet and labelled, and where
    its best what-if moves it, the moved footprint dashed."""
    from matplotlib.patches import Polygon as MplPolygon

    marks = drift_marks(drift, spec)
    for m in marks:
        for fp in m["footprints"]:
            ax.add_patch(MplPolygon(fp, closed=True, fill=False, edgecolor="#6a1b9a", lw=1.3, zorder=8))
        for fp in m["moved"] or []:
            ax.add_patch(MplPolygon(fp, closed=True, fill=False, edgecolor="#6a1b9a", lw=0.9, ls="--", zorder=8))
        allp = np.concatenate([np.asarray(fp) for fp in m["footprints"]])
        ax.text(
            allp[:, 0].max() + 0.05,
            allp[:, 1].max(),
            m["label"],
            fontsize=5.5,
            color="#6a1b9a",
            ha="left",
            va="bottom",
            zorder=9,
            bbox=dict(boxstyle="round,pad=0.15", facecolor="white", edgecolor="none", alpha=0.75),
        )
    if marks:
        ax.plot(
            [],
            [],
            color="#6a1b9a",
            lw=1.3,
            label=f"object a drift what-if names ({len(marks)})\ndashed: moved; *: kept together",
        )


def save_fidelity_png(
    path: str | Path,
    meta: dict,
    fid: SceneFidelity,
    positions: np.ndarray,
    triples: list[Triple],
    drift: dict | None = None,
    spec: SceneSpec | None = None,
) -> Path:
    """One scene's :func:`draw_fidelity` map as a PNG (written atomically)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8.0, 6.0), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.07, 0.07, 0.6, 0.86))
    draw_fidelity(ax, meta, fid, positions, triples, drift=drift, spec=spec)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), frameon=False)
    return atomic_save_figure(fig, path)


# ------------------------------------------------------------------------------------------------ causes
def explain_missing(meta: dict, cells: list[Cell], clearance: float) -> list[dict]:
    """Why tsnav lacks each real position of ``cells``, from a scene's ``scene.json`` (``meta``): the blocking
    footprints (furniture ids, target objects standing on the floor) nearer than ``clearance`` (or the object's own
    smaller clearance, ``navigation.clearances``) to it, ``"wall"``
    when it is nearer than that to the room's outline or outside it, or nothing (then the position is cut off
    from the kept connected set). One dict ``{"position": [x, z], "causes": [...]}`` per cell."""
    floor = unary_union([Polygon(p) for p in meta.get("floor", [])]) if meta.get("floor") else None
    own = (meta.get("navigation") or {}).get("clearances", {})
    obstacles = [(f["id"], Polygon(f["footprint"])) for f in meta.get("furniture", []) if f.get("blocks", True)]
    for o in meta.get("objects", []):
        b = o.get("bbox")
        if o.get("support") == "floor" and b:
            obstacles.append((o["objectId"], Polygon(box_footprint(b["center"], b["size"], b.get("yaw", 0.0)))))
    out = []
    for c in cells:
        p = Point(c[0] * GRID_SIZE, c[1] * GRID_SIZE)
        causes = []
        if floor is not None and (not floor.contains(p) or floor.exterior.distance(p) < clearance - 1e-9):
            causes.append("wall")
        causes += sorted(
            {oid for oid, poly in obstacles if poly.distance(p) < min(clearance, own.get(oid, clearance)) - 1e-9}
        )
        out.append({"position": [c[0] * GRID_SIZE, c[1] * GRID_SIZE], "causes": causes})
    return out


def blame(explained: list[dict]) -> dict[str, int]:
    """How many missing positions each cause (object id or ``"wall"``) accounts for, most first."""
    counts: dict[str, int] = {}
    for e in explained:
        for c in e["causes"] or ["cut off"]:
            counts[c] = counts.get(c, 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


# ------------------------------------------------------------------------------------------------ drift
#: Shifts tried for an object next to a leaked blocked move, metres, along +x, -x, +z and -z: the poses drifted by
#: this much between the lineage's AI2-THOR 2.0.2 data and the ai2thor 5 metadata (``docs/WORLD.md``, FloorPlan30's
#: island). Only objects that a shift of at most the largest can bring within the clearance of a leak are tried.
DRIFT_SHIFTS = (0.02, 0.04, 0.06, 0.08, 0.1)
#: Objects that may have stood elsewhere (pickupable or moveable per the metadata) within this distance of the
#: target of a leak no shift explains are named as suspects, metres.
SUSPECT_RADIUS = 1.0


def blockers(spec: SceneSpec) -> dict[str, tuple[str, list, float]]:
    """``{id: (category, footprint polygons, clearance)}`` of the blocking furniture and floor-standing target
    objects of ``spec``, with the clearance the navgrid keeps from each (the spec's, or the object's own smaller
    one)."""
    nav = spec.navigation or {}
    base = float(nav.get("clearance", AGENT_RADIUS))
    own = nav.get("clearances", {})
    out: dict[str, tuple[str, list, float]] = {}
    for f in spec.furniture:
        if f.blocks:
            out.setdefault(f.id, (f.category, [], min(base, own.get(f.id, base))))[1].append(Polygon(f.footprint()))
    for o in spec.objects:
        if o.support == "floor":
            out.setdefault(o.objectId, (o.objectType, [], min(base, own.get(o.objectId, base))))[1].append(
                Polygon(box_footprint(o.center, o.size, o.yaw))
            )
    return out


def relaid(spec: SceneSpec, remove=(), shifts: dict[str, tuple[float, float]] | None = None) -> SceneSpec:
    """A what-if copy of ``spec``: without the furniture and objects whose id is in ``remove``, and with those of
    ``shifts`` (id -> ``(dx, dz)``, metres) moved. Render parts are kept as they are (the navgrid ignores them)."""
    remove, shifts = set(remove), shifts or {}

    def moved(oid, c):
        dx, dz = shifts.get(oid, (0.0, 0.0))
        return (c[0] + dx, c[1], c[2] + dz)

    return replace(
        spec,
        furniture=[replace(f, center=moved(f.id, f.center)) for f in spec.furniture if f.id not in remove],
        objects=[replace(o, center=moved(o.objectId, o.center)) for o in spec.objects if o.objectId not in remove],
    )


def _figures(f: SceneFidelity, base: SceneFidelity) -> dict:
    s = f.shares()
    return {
        "positions": round(s["positions"], 2),
        "moves_kept": round(s["moves_kept"], 2),
        "blocked_blocked": round(s["blocked_blocked"], 2),
        "counts": {"positions_kept": f.positions_kept, "moves_kept": f.moves_kept, "blocked_kept": f.blocked_kept},
        "change": {
            "positions_kept": f.positions_kept - base.positions_kept,
            "moves_kept": f.moves_kept - base.moves_kept,
            "blocked_kept": f.blocked_kept - base.blocked_kept,
        },
    }


def keeps_all(f: SceneFidelity, f0: SceneFidelity) -> bool:
    """Whether ``f`` (a what-if) keeps every real position, move and blocked move that ``f0`` keeps, compared as
    sets: one that brings a real position back and loses another keeps the count but not the position."""
    return (
        set(f.missing) <= set(f0.missing) and set(f.lost_moves) <= set(f0.lost_moves) and set(f.leaks) <= set(f0.leaks)
    )


#: What the report says of its drift what-ifs, under their table (``fidelity.md``).
FITTED_NOTE = (
    "The what-ifs are fitted to these same trajectories: per object the best of {n} shifts (up to {d:g} m "
    "along +-x or +-z) or its removal, kept when it loses no real position, move or blocked move; "
    "the figures without drift (removals included) are the best these what-ifs reach on the trajectories "
    "that chose them, not a measurement."
)


def drift_whatifs(
    spec: SceneSpec,
    triples: list[Triple],
    flags: dict[str, dict] | None = None,
    base: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict:
    """Which objects' poses stand between ``spec`` and the real trajectories ``triples``, by what-ifs: the scene laid
    out again without an object, or with it moved a few centimetres (:func:`relaid`). What-ifs only: no rule moves
    an object.

    The objects looked at are the blocking ones nearer than their clearance to a real position tsnav lacks, and those
    that a shift of :data:`DRIFT_SHIFTS` brings within their clearance of the target of a real blocked move tsnav
    lets through (a leak), each with its ``parts`` (the blocking objects no larger whose footprints lie inside its
    own, such as a dresser's drawers), which every what-if moves or removes with it. Per object (``objects``):
    ``moveable``, whether the metadata (``flags``: id -> ``{"pickupable", "moveable"}``) lets it move (None: not
    known); ``real_inside``, the real positions inside its footprint (where it cannot have stood); ``missing_near``
    and ``leaks_near``; ``without``, the figures without it; ``best``, the what-if (a shift along x or z, or, when
    it does better, its removal) that gains most and loses no real position, move or blocked move kept, or None.
    ``without_drift``: the figures with those best what-ifs applied together, best first, each kept only while the
    whole loses nothing: the figure the scene would reach without that drift. ``unexplained_leaks``: the leaks it
    still lets through, with the pickupable or moveable floor objects within :data:`SUSPECT_RADIUS` of their target
    (``suspects``).

    ``base``: ``(positions, move)`` of ``spec`` when already laid out."""
    flags = flags or {}
    g = GRID_SIZE

    def fid(s: SceneSpec) -> SceneFidelity | None:
        try:
            p, m = reachable_positions(s)
        except ValueError:  # the what-if leaves no reachable position
            return None
        return measure(spec.name, p, m, triples)

    pos, move = base if base is not None else reachable_positions(spec)
    f0 = measure(spec.name, pos, move, triples)
    bl = blockers(spec)
    real = {cell(*map(float, k.split("|")[:2])) for t in triples for k in (t[0], t[2])}

    def dist(oid, c):
        return min(poly.distance(Point(c[0] * g, c[1] * g)) for poly in bl[oid][1])

    def moveable(oid):
        fl = flags.get(oid)
        return None if fl is None else bool(fl.get("pickupable") or fl.get("moveable"))

    def lossless(f):
        return f is not None and keeps_all(f, f0)

    def score(f):
        return (f.positions_kept - f0.positions_kept + f.blocked_kept - f0.blocked_kept, f.moves_kept - f0.moves_kept)

    # An object's parts (the drawers of a dresser, a sink's basin, the other shelves of a stack) go with it: the
    # blocking objects no larger (ties: lower id) whose footprints lie, at least 90 % of their area, inside its own;
    # each what-if moves or removes a whole group.
    shape = {oid: unary_union(polys) for oid, (_, polys, _) in bl.items()}
    size = {oid: (round(shape[oid].area, 6), oid) for oid in bl}
    owner = {}
    for oid in bl:
        hosts = [
            h for h in bl if size[h] > size[oid] and shape[h].intersection(shape[oid]).area >= 0.9 * shape[oid].area
        ]
        owner[oid] = max(hosts, key=size.get) if hosts else oid

    def root(oid):
        while owner[oid] != oid:
            oid = owner[oid]
        return oid

    groups = {o: [o] + sorted(p for p in bl if p != o and root(p) == o) for o in bl if owner[o] == o}

    def near(members, cells, slack):
        return {c for c in cells for m in members if dist(m, c) < bl[m][2] + slack - 1e-9}

    targets = {(c, r): (c[0] + step(r)[0], c[1] + step(r)[1]) for c, r in f0.leaks}
    missing_near = {o: len(near(ms, f0.missing, 0.0)) for o, ms in groups.items()}
    leaks_near = {o: sum(bool(near(ms, [t], DRIFT_SHIFTS[-1])) for t in targets.values()) for o, ms in groups.items()}
    looked = sorted(
        (o for o in groups if missing_near[o] or leaks_near[o]), key=lambda o: (-missing_near[o] - leaks_near[o], o)
    )
    objects, options = [], []
    for oid in looked:
        ms = groups[oid]
        gone = fid(relaid(spec, remove=set(ms)))
        best = None  # (score, order, shift, what-if, f): shifts, smallest first, then the removal
        tries = [
            ((dx, dz), {"shifts": {m: (dx, dz) for m in ms}})
            for d in DRIFT_SHIFTS
            for dx, dz in ((d, 0.0), (-d, 0.0), (0.0, d), (0.0, -d))
        ] + [(None, {"remove": set(ms)})]
        for n, (shift, kw) in enumerate(tries):
            f = gone if shift is None else fid(relaid(spec, **kw))
            if lossless(f) and score(f) > (0, 0) and (best is None or score(f) > best[0]):
                best = (score(f), n, shift, kw, f)
        e = {
            "id": oid,
            "category": bl[oid][0],
            "parts": ms[1:],
            "moveable": moveable(oid),
            "real_inside": len({c for c in real for m in ms if dist(m, c) <= 1e-9}),
            "missing_near": missing_near[oid],
            "leaks_near": leaks_near[oid],
            "without": _figures(gone, f0) if gone is not None else None,
            "best": None,
        }
        if best is not None:
            _, _, shift, kw, f = best
            e["best"] = {
                "what_if": "removed" if shift is None else "moved",
                "shift": None if shift is None else [round(v, 3) + 0.0 for v in shift],
                **_figures(f, f0),
            }
            options.append((best[0], oid, kw))
        objects.append(e)
    remove, shifts, applied, f = set(), {}, [], f0
    for sc, oid, kw in sorted(options, key=lambda t: (t[0][0], t[0][1]), reverse=True):
        r2, s2 = remove | kw.get("remove", set()), {**shifts, **kw.get("shifts", {})}
        f2 = fid(relaid(spec, remove=r2, shifts=s2))
        if lossless(f2) and score(f2) > score(f):
            remove, shifts, f = r2, s2, f2
            applied.append(oid)
    unexplained = []
    for (c, r), t in sorted(targets.items()):
        if (c, r) not in f.leaks:
            continue
        sus = sorted((round(dist(oid, t), 3), oid) for oid in bl if moveable(oid) and dist(oid, t) < SUSPECT_RADIUS)
        unexplained.append(
            {
                "from": [c[0] * g, c[1] * g],
                "heading": r,
                "to": [t[0] * g, t[1] * g],
                "suspects": [{"id": oid, "distance": d} for d, oid in sus],
            }
        )
    return {
        "objects": objects,
        "without_drift": {
            "applied": applied,
            "removed": sorted(remove),
            "shifted": {k: [round(v, 3) + 0.0 for v in d] for k, d in sorted(shifts.items()) if k in groups},
            **_figures(f, f0),
        },
        "unexplained_leaks": unexplained,
    }


def drift_total(results: list[SceneFidelity], scenes: list[dict]) -> dict:
    """The shares over all ``results`` with each scene's ``without_drift`` counts (a scene without ``drift``
    counts as it is)."""
    tot = SceneFidelity("all")
    for r, js in zip(results, scenes):
        c = ((js.get("drift") or {}).get("without_drift") or {}).get("counts", {})
        for k in ("positions", "moves", "blocked"):
            setattr(tot, k, getattr(tot, k) + getattr(r, k))
        for k in ("positions_kept", "moves_kept", "blocked_kept"):
            setattr(tot, k, getattr(tot, k) + c.get(k, getattr(r, k)))
    return {k: round(v, 2) for k, v in tot.shares().items()}


def layout_flags(name: str) -> dict[str, dict]:
    """``{objectId: {"pickupable", "moveable"}}`` of packaged real layout ``name`` (empty when there is none)."""
    from .layouts import layout_names, load_layout

    if name not in layout_names():
        return {}
    return {o.object_id: {"pickupable": o.pickupable, "moveable": o.moveable} for o in load_layout(name).objects}


def markdown_drift(scenes: list[dict]) -> str:
    """The ``drift`` what-ifs of the scenes of ``fidelity.json`` as a Markdown table (one row per object, then the
    scene without its drift), followed by the leaks no what-if explains."""
    lines = [
        "| scene | object | moveable | real positions inside | missing / leaks near | without it (positions / "
        "moves kept / blocked blocked %) | best what-if | its figures |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    loose = []
    mv = {True: "yes", False: "no", None: "?"}

    def figs(e):
        return f"{e['positions']:.1f} / {e['moves_kept']:.1f} / {e['blocked_blocked']:.1f}"

    for js in scenes:
        d = js.get("drift")
        if not d:
            continue
        name = js["scene"]
        for e in d["objects"]:
            b = e["best"]
            what = (
                "none"
                if b is None
                else "removed"
                if b["shift"] is None
                else f"moved ({b['shift'][0]:+.2f}, {b['shift'][1]:+.2f}) m"
            )
            obj = e["id"] + (f" (+{len(e['parts'])} parts)" if e["parts"] else "")
            lines.append(
                f"| {name} | {obj} | {mv[e['moveable']]} | {e['real_inside']} | {e['missing_near']} / "
                f"{e['leaks_near']} | {figs(e['without']) if e['without'] else '-'} | {what} | "
                f"{figs(b) if b else '-'} |"
            )
        w = d["without_drift"]
        if w["applied"]:
            lines.append(
                f"| {name} | **without drift** ({len(w['removed'])} removed, {len(w['shifted'])} moved) | | | "
                f"| was {figs(js)} | | **{figs(w)}** |"
            )
        for u in d["unexplained_leaks"]:
            sus = ", ".join(f"{s['id']} ({s['distance']:.2f} m)" for s in u["suspects"]) or "none"
            loose.append(
                f"- {name}: ({u['from'][0]:.2f}, {u['from'][1]:.2f}) heading {u['heading']}; pickupable or "
                f"moveable objects within {SUSPECT_RADIUS:g} m of its target: {sus}"
            )
    out = "\n".join(lines) + "\n"
    if loose:
        out += "\nReal blocked moves let through that no what-if explains:\n\n" + "\n".join(loose) + "\n"
    return out


# ------------------------------------------------------------------------------------------------ report
def fidelity_report(
    data: str | Path, trajectories: str | Path, out: str | Path | None = None, pictures: bool = True, drift: bool = True
) -> tuple[list[SceneFidelity], Path]:
    """Measure every scene of ``trajectories`` that the dataset ``data`` holds; write ``fidelity.json``,
    ``fidelity.md`` and (with ``pictures``) ``SCENE.png`` per scene into ``out`` (default ``DATA/fidelity``).
    With ``drift``, each scene's ``drift`` holds :func:`drift_whatifs` (the scene laid out again from its
    ``scene.json``; the metadata's pickupable / moveable flags of a real iTHOR scene's packaged layout), or None
    with ``drift_note`` when the scene does not lay out again to its own graph.
    Returns the per-scene results and the output folder. A trajectories file naming no scene of ``data`` is an
    error (one line); scenes of the file that ``data`` lacks are listed in the JSON as ``absent``."""
    data = Path(data)
    if not data.is_dir():
        raise FileNotFoundError(f"{data}: no such dataset folder")
    triples = load_trajectories(trajectories)
    present = [s for s in triples if is_complete(data / s)]
    absent = [s for s in triples if s not in present]
    if not present:
        raise TrajectoriesError(
            f"{trajectories}: none of its {len(triples)} scenes is a complete scene folder in {data}"
        )
    out = Path(out) if out is not None else data / "fidelity"
    out.mkdir(parents=True, exist_ok=True)
    results, scenes_json = [], []
    for name in present:
        scene = load_scene(data / name)
        positions, move = scene_moves(scene)
        fid = measure(name, positions, move, triples[name])
        results.append(fid)
        nav = scene.meta.get("navigation") or {}
        clearance = float(nav.get("clearance", AGENT_RADIUS))
        explained = explain_missing(scene.meta, fid.missing, clearance)
        js = fid.to_json()
        js["missing_positions"] = explained
        js["missing_by_cause"] = blame(explained)
        js["generator"] = scene.meta.get("generator", {"world": "procedural"} if "parts" in scene.meta else None)
        spec = None
        if drift:
            try:
                spec = SceneSpec.from_json(scene.meta)
                again = reachable_positions(spec)
            except (KeyError, TypeError, ValueError, IndexError):
                spec, again = None, (None, None)
            if spec is not None and np.array_equal(again[0], positions) and np.array_equal(again[1], move):
                flags = layout_flags(name) if (js["generator"] or {}).get("world") == "ithor-real" else {}
                js["drift"] = drift_whatifs(spec, triples[name], flags, base=(positions, move))
            else:
                js["drift"] = None
                js["drift_note"] = (
                    "scene.json does not lay out again to the scene's graph (built by other rules, or incomplete)"
                )
        scenes_json.append(js)
        if pictures:
            save_fidelity_png(
                out / f"{name}.png", scene.meta, fid, positions, triples[name], drift=js.get("drift"), spec=spec
            )
    doc = {
        "format": "tsnav-fidelity",
        "version": 1,
        "data": str(data),
        "trajectories": str(trajectories),
        "summary": summary(results),
        "scenes": scenes_json,
        "absent": absent,
    }
    if any(js.get("drift") for js in scenes_json):
        doc["summary"]["without_drift"] = drift_total(results, scenes_json)
    atomic_write_text(out / "fidelity.json", json.dumps(doc, indent=1))
    md = markdown_table(results)
    if "without_drift" in doc["summary"]:
        t = doc["summary"]["without_drift"]
        none = sum(not js.get("drift") for js in scenes_json)
        md += (
            "\n## Pose drift: what-ifs\n\n" + markdown_drift(scenes_json) + f"\nAll scenes without the drift above: "
            f"positions {t['positions']:.1f} %, moves kept {t['moves_kept']:.1f} %, blocked blocked "
            f"{t['blocked_blocked']:.1f} %"
            + (f" ({none} scene(s) without what-ifs counted as they are)" if none else "")
            + ".\n\n"
            + FITTED_NOTE.format(n=4 * len(DRIFT_SHIFTS), d=DRIFT_SHIFTS[-1])
            + "\n"
        )
    if absent:
        md += f"\nScenes of the trajectories file not in {data}: {', '.join(absent)}\n"
    atomic_write_text(out / "fidelity.md", md)
    return results, out


__all__ = [
    "SceneFidelity",
    "TrajectoriesError",
    "blame",
    "blockers",
    "draw_drift",
    "drift_marks",
    "drift_total",
    "drift_whatifs",
    "explain_missing",
    "fidelity_report",
    "keeps_all",
    "layout_flags",
    "load_trajectories",
    "markdown_drift",
    "markdown_table",
    "measure",
    "parse_trajectories",
    "relaid",
    "save_fidelity_png",
    "scene_moves",
    "step",
    "summary",
]
