"""Reachable positions and the state graph, from geometry.

A grid position (0.25 m lattice) is reachable when a disc of the agent's radius around it lies on the
floor and touches no wall or blocking furniture/object footprint. MoveAhead between two neighbouring
positions (8 headings; diagonal headings move one step in x and z) is allowed when the whole swept
segment stays in free space. Only one connected set of positions is kept, so every reachable position can
reach every other one: the largest, unless no target object is in sight from it (:func:`keep_component`), as
when a walled-off shower stall holds a few more grid positions than the rest of the bathroom.
"""

from __future__ import annotations

import numpy as np
import shapely
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from shapely.geometry import LineString, Polygon
from shapely.ops import unary_union

from ..constants import GRID_SIZE, HORIZONS, ROTATIONS, TARGET_CATEGORIES, state_key
from .spec import SceneSpec, box_footprint

AGENT_RADIUS = 0.2
#: A target is "in sight" of a connected set when one of its positions lies within this distance (metres) of
#: the object's centre with a clear 2-D line between them (:func:`keep_component`).
SIGHT_DISTANCE = 1.5
#: How much of that line may run outside free space: the object's own footprint and the furniture it stands on.
SIGHT_SLACK = 0.35
#: Connected sets smaller than this are never kept when a larger one exists.
MIN_COMPONENT = 4
#: Headings (degrees) -> grid step (dx, dz) of MoveAhead.
STEPS = {r: (int(round(np.sin(np.deg2rad(r)))), int(round(np.cos(np.deg2rad(r))))) for r in ROTATIONS}


def free_space(spec: SceneSpec, radius: float = AGENT_RADIUS):
    """Shapely geometry of the positions the agent's centre may occupy: the floor shrunk by ``radius``, less every
    wall and blocking footprint grown by ``radius``, or by its own smaller clearance when the spec's
    ``navigation["clearances"]`` gives one (objectId -> metres: a low object the capsule's rounded bottom passes
    closer to)."""
    floor = unary_union([Polygon(p) for p in spec.floor])
    own = (spec.navigation or {}).get("clearances", {})
    groups: dict[float, list] = {}
    wall_inst = {i for i, n in enumerate(spec.instances) if n == "Wall"}
    for p in spec.parts:
        if int(p.inst) in wall_inst:
            groups.setdefault(radius, []).append(Polygon(box_footprint(p.center, p.size, p.yaw)))
    for f in spec.furniture:
        if f.blocks:
            groups.setdefault(min(radius, own.get(f.id, radius)), []).append(Polygon(f.footprint()))
    for o in spec.objects:
        if o.support == "floor":
            groups.setdefault(min(radius, own.get(o.objectId, radius)), []).append(
                Polygon(box_footprint(o.center, o.size, o.yaw))
            )
    grown = [unary_union(polys).buffer(r, quad_segs=4) for r, polys in sorted(groups.items()) if polys]
    blocked = unary_union(grown) if grown else Polygon()
    return floor.buffer(-radius + 1e-6, quad_segs=4).difference(blocked)


def reachable_positions(spec: SceneSpec, radius: float | None = None):
    """``(positions (P, 2) float, move (P, 8) int)``: reachable grid positions (the connected set of :func:`keep_component`,
    sorted by x then z) and, per rotation index, the neighbour reached by MoveAhead (-1 when blocked). ``radius``:
    the clearance kept from walls and obstacles (default: the spec's ``clearance``, else :data:`AGENT_RADIUS`)."""
    nav = spec.navigation or {}
    if radius is None:
        radius = float(nav.get("clearance", AGENT_RADIUS))
    free = free_space(spec, radius)
    sweep = nav.get("sweep_clearance")
    free_path = free if sweep is None or float(sweep) == radius else free_space(spec, float(sweep))
    minx, minz, maxx, maxz = free.bounds if not free.is_empty else (0, 0, 0, 0)
    if free_path is not free:
        shapely.prepare(free_path)
    xs = np.arange(np.ceil(minx / GRID_SIZE), np.floor(maxx / GRID_SIZE) + 1) * GRID_SIZE
    zs = np.arange(np.ceil(minz / GRID_SIZE), np.floor(maxz / GRID_SIZE) + 1) * GRID_SIZE
    gx, gz = np.meshgrid(xs, zs, indexing="ij")
    gx, gz = gx.ravel(), gz.ravel()
    shapely.prepare(free)
    ok = shapely.contains_xy(free, gx, gz)
    pos = np.stack([gx[ok], gz[ok]], axis=1)
    if len(pos) == 0:
        raise ValueError(f"scene {spec.name}: no reachable position")
    ij = np.round(pos / GRID_SIZE).astype(np.int64)
    lookup = {(int(a), int(b)): n for n, (a, b) in enumerate(ij)}
    move = np.full((len(pos), len(ROTATIONS)), -1, dtype=np.int64)
    samples = np.linspace(0.0, 1.0, 6)[1:-1]
    for k, r in enumerate(ROTATIONS):
        dx, dz = STEPS[r]
        tgt = np.array([lookup.get((int(a) + dx, int(b) + dz), -1) for a, b in ij])
        has = tgt >= 0
        # The swept segment must stay free (checked at interior sample points).
        seg_ok = np.ones(len(pos), dtype=bool)
        for t in samples:
            sx = pos[:, 0] + t * dx * GRID_SIZE
            sz = pos[:, 1] + t * dz * GRID_SIZE
            seg_ok &= shapely.contains_xy(free_path, sx, sz)
        move[:, k] = np.where(has & seg_ok, tgt, -1)
    # Connected sets of the MoveAhead graph (moves are symmetric: reverse heading); one is kept.
    src, kk = np.nonzero(move >= 0)
    adj = coo_matrix((np.ones(len(src)), (src, move[src, kk])), shape=(len(pos), len(pos)))
    ncomp, label = connected_components(adj, directed=True, connection="strong")
    keep = label == keep_component(spec, pos, label)
    remap = np.full(len(pos), -1, dtype=np.int64)
    remap[keep] = np.arange(keep.sum())
    pos, move = pos[keep], move[keep]
    move = np.where(move >= 0, remap[np.maximum(move, 0)], -1)
    return pos, move


def targets_in_sight(spec: SceneSpec, positions: np.ndarray, free_thin=None) -> set[str]:
    """Target categories of ``spec`` with an object within :data:`SIGHT_DISTANCE` of one of ``positions``
    ((P, 2) x, z) along a 2-D line that leaves free space (agent radius 1 cm) for at most :data:`SIGHT_SLACK`."""
    free_thin = free_space(spec, radius=0.01) if free_thin is None else free_thin
    seen = set()
    for o in spec.objects:
        if o.objectType not in TARGET_CATEGORIES or o.objectType in seen:
            continue
        ox, oz = float(o.center[0]), float(o.center[2])
        d = np.hypot(positions[:, 0] - ox, positions[:, 1] - oz)
        for i in np.flatnonzero(d < SIGHT_DISTANCE):
            line = LineString([(positions[i, 0], positions[i, 1]), (ox, oz)])
            if line.difference(free_thin).length < SIGHT_SLACK:
                seen.add(o.objectType)
                break
    return seen


def keep_component(spec: SceneSpec, positions: np.ndarray, label: np.ndarray) -> int:
    """The label of the connected set to keep: the largest, unless no target is in sight from it
    (:func:`targets_in_sight`) while one is from another set of :data:`MIN_COMPONENT` positions or more; then
    the set with the most targets in sight (ties: the larger, then the lower label)."""
    sizes = np.bincount(label)
    largest = int(sizes.argmax())
    others = [int(c) for c in np.flatnonzero(sizes >= MIN_COMPONENT) if c != largest]
    if not others:
        return largest
    free_thin = free_space(spec, radius=0.01)
    if targets_in_sight(spec, positions[label == largest], free_thin):
        return largest
    score = {
        c: (len(targets_in_sight(spec, positions[label == c], free_thin)), int(sizes[c]), -c)
        for c in [largest, *others]
    }
    return max(score, key=score.get)


def state_poses(positions: np.ndarray) -> np.ndarray:
    """``(V, 4)`` float64 rows ``(x, z, rotation, horizon)`` of every state, in node order: position, then
    rotation (:data:`ROTATIONS`), then horizon (:data:`HORIZONS`); state ``(p, k, h)`` is row ``(p * R + k) * H + h``."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    R, H = len(ROTATIONS), len(HORIZONS)
    per = R * H
    rh = np.array([(r, h) for r in ROTATIONS for h in HORIZONS], dtype=np.float64)  # (R*H, 2)
    return np.concatenate([np.repeat(positions, per, axis=0), np.tile(rh, (len(positions), 1))], axis=1)


def state_keys(positions: np.ndarray) -> np.ndarray:
    """State keys (:func:`~tsnav.constants.state_key`) of :func:`state_poses`, same order, as a numpy string
    array; each position's ``x|z`` is formatted once."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    xz = [state_key(x, z, 0, 0).rsplit("|", 2)[0] for x, z in positions]
    tails = ["|" + state_key(0, 0, r, h).split("|", 2)[2] for r in ROTATIONS for h in HORIZONS]
    return np.array([a + t for a in xz for t in tails]) if xz else np.array([], dtype=str)


def graph_edges(move: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Directed edges of the state graph as state indices (rows of :func:`state_poses`): ``(source, target)``.

    Per state, in this order: RotateRight (+45), RotateLeft (-45), the other horizon (LookDown/LookUp), then
    MoveAhead when ``move[p, k] >= 0``; states in node order. Array form of :func:`build_graph`.
    """
    move = np.asarray(move, dtype=np.int64)
    P, R, H = len(move), len(ROTATIONS), len(HORIZONS)
    p = np.arange(P)[:, None, None]
    k = np.arange(R)[None, :, None]
    h = np.arange(H)[None, None, :]

    def index(pp, kk, hh):
        return (pp * R + kk) * H + hh

    src = np.broadcast_to(index(p, k, h), (P, R, H))
    right = np.broadcast_to(index(p, (k + 1) % R, h), (P, R, H))
    left = np.broadcast_to(index(p, (k - 1) % R, h), (P, R, H))
    other = np.broadcast_to(index(p, k, (H - 1) - h), (P, R, H))
    m = move[:, :, None]
    ahead = np.broadcast_to(np.where(m >= 0, index(np.maximum(m, 0), k, h), -1), (P, R, H))
    tgt = np.stack([right, left, other, ahead], axis=-1).reshape(-1)
    srcs = np.repeat(src.reshape(-1), 4)
    keep = tgt >= 0
    return srcs[keep], tgt[keep]


def build_graph(positions: np.ndarray, move: np.ndarray) -> tuple[list[str], list[tuple[str, str]]]:
    """State keys and directed edges (RotateRight/Left, LookDown/Up, MoveAhead) of the state graph.

    Slow, obviously-correct reference of :func:`state_keys` + :func:`graph_edges` (which the build uses);
    ``tests/world/test_world.py`` holds them together.
    """
    nodes, edges = [], []
    for p, (x, z) in enumerate(positions):
        for k, r in enumerate(ROTATIONS):
            for h in HORIZONS:
                key = state_key(x, z, r, h)
                nodes.append(key)
                edges.append((key, state_key(x, z, (r + 45) % 360, h)))
                edges.append((key, state_key(x, z, (r - 45) % 360, h)))
                other = HORIZONS[1] if h == HORIZONS[0] else HORIZONS[0]
                edges.append((key, state_key(x, z, r, other)))
                if move[p, k] >= 0:
                    nx, nz = positions[move[p, k]]
                    edges.append((key, state_key(nx, nz, r, h)))
    return nodes, edges
