"""Searched region of the exploration reward (paper section III-B, eq. ExploreReward; constants section IV-A).

From the bird's-eye view the area an agent observes clearly is an isosceles trapezoid ``T_t`` cut from the
90-degree right-angle viewing triangle (apex at the agent, 45 degrees each side of the heading) between two
bases perpendicular to the heading: at 1 m and 4 m for horizon 0, at 0.25 m and 3 m for horizon 30. A base
at distance ``d`` has half-width ``d``, so the trapezoid's area is ``far**2 - near**2`` (15 m^2 and
8.9375 m^2). The searched region is ``RG_t = (RG_{t-1} U T_t) n floor`` (the paper prints "U RoomBounds"
and means the intersection, DESIGN.md "TSRM"); the reward is ``K_e * (Area(RG_t) - Area(RG_{t-1}))``.

Two implementations:

* :class:`ExactSearchedRegion` - the reference: shapely polygons, one episode.
* :class:`AreaIndex` + :class:`BatchCoverage` - the fast path. Area is measured by point samples on a
  square lattice of pitch ``sample_size`` (1/32 m by default; it divides the 0.25 m grid, so every
  position is a lattice corner); a sample counts when it lies in the region. The samples are packed 8 x 8
  into 64-bit *blocks*. The blocks a trapezoid touches, with the bits of its samples, depend only on the
  (rotation, horizon) profile and the position's phase inside its block: one *stencil* (block offsets + bit
  masks) per such pose serves every state of every scene (16 stencils at 1/32 m, 64 at 1/16 m). Each
  episode keeps one coverage word per block, with the samples off the floor preset to 1, so the area a step
  gains is ``popcount(mask & ~coverage)`` summed over the stencil, times ``sample_size**2``. A batch of
  episodes is counted with one gather per horizon.

Samples sit at half-sample offsets from agent positions, so walls on the 0.125 m lattice (the usual room
bounds) fall between samples. Trapezoid edges that run along rows of samples (the lateral edges of headings
0/90/180/270 pass through sample centres; the bases of diagonal headings cut diagonal rows at a fixed
fraction) would bias the area by up to half a sample row per metre of edge; their samples are dithered in
proportion to the share of their row inside (:func:`stencil_weights`), which removes the bias even where a
wall clips the opposite edge. Every stencil is within 0.03% of 15 or 8.9375 m^2.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Sequence

import numpy as np
import shapely

from ..constants import GRID_SIZE, ROTATE_STEP

#: Episodes per gather in :meth:`BatchCoverage.add` (bounds the size of the temporaries).
CHUNK = 256

#: Samples per block side; a block is one 64-bit word of 8 x 8 samples (bit = 8 * row + column).
BLOCK = 8


@dataclass(frozen=True)
class AreaConfig:
    """Geometry of the observable trapezoid (paper section IV-A) and resolution of the fast raster."""

    near_level: float = 1.0
    """Distance from the agent to the near base at horizon 0 (looking straight ahead), metres."""
    far_level: float = 4.0
    """Distance from the agent to the far base at horizon 0, metres."""
    near_down: float = 0.25
    """Distance to the near base at horizon 30 (looking down), metres."""
    far_down: float = 3.0
    """Distance to the far base at horizon 30, metres."""
    sample_size: float = 1 / 32
    """Pitch of the area samples of the fast implementation, metres; must divide the 0.25 m grid. 1/32 keeps
    whole 30-step episodes within 1% of the shapely area; 1/16 makes the reward about 2x faster and is
    within 1% for 99% of such episodes (a few % on regions under 1 m^2); work grows as 1 / sample_size^2."""

    def __post_init__(self):
        for name in ("near_level", "far_level", "near_down", "far_down", "sample_size"):
            if not getattr(self, name) > 0:
                raise ValueError(f"AreaConfig.{name} must be positive, got {getattr(self, name)}")
        if not (self.near_level < self.far_level and self.near_down < self.far_down):
            raise ValueError("AreaConfig: the near base must be closer than the far base")
        k = GRID_SIZE / self.sample_size
        if abs(k - round(k)) > 1e-6 or round(k) < 1:
            raise ValueError(
                f"AreaConfig.sample_size {self.sample_size} must divide the {GRID_SIZE} m grid (e.g. 1/16, 0.05, 1/32)"
            )

    @property
    def block_size(self) -> float:
        """Side of a block of 8 x 8 samples, metres."""
        return BLOCK * self.sample_size

    def bases(self, horizon: int) -> tuple[float, float]:
        """``(near, far)`` base distances in metres for a camera horizon of 0 or 30 degrees."""
        h = int(horizon)
        if h == 0:
            return self.near_level, self.far_level
        if h == 30:
            return self.near_down, self.far_down
        raise ValueError(f"no observable trapezoid is defined for horizon {h} (only 0 and 30)")


def trapezoid_vertices(x, z, rotation, horizon, config: AreaConfig = AreaConfig()) -> np.ndarray:
    """Corners of the observable trapezoid ``T_t``, ``(..., 4, 2)`` (x, z) metres, counter-clockwise.

    ``rotation`` in degrees (0 faces +z, 90 faces +x), ``horizon`` 0 or 30. Order: near-left, near-right,
    far-right, far-left, where right is the side RotateRight turns to.
    """
    x, z, rot, hor = np.broadcast_arrays(
        np.asarray(x, float), np.asarray(z, float), np.asarray(rotation, float), np.asarray(horizon)
    )
    near = np.empty(x.shape)
    far = np.empty(x.shape)
    for h in np.unique(hor):
        n, f = config.bases(int(h))
        near[hor == h], far[hor == h] = n, f
    rad = np.deg2rad(rot)
    fx, fz = np.sin(rad), np.cos(rad)  # heading
    rx, rz = np.cos(rad), -np.sin(rad)  # to the right of the heading
    out = np.empty(x.shape + (4, 2))
    for k, (d, side) in enumerate(((near, -1), (near, 1), (far, 1), (far, -1))):
        out[..., k, 0] = x + d * fx + side * d * rx
        out[..., k, 1] = z + d * fz + side * d * rz
    return out


def trapezoid(x: float, z: float, rotation: int, horizon: int, config: AreaConfig = AreaConfig()) -> shapely.Polygon:
    """The observable trapezoid as a shapely polygon (metres)."""
    return shapely.Polygon(trapezoid_vertices(x, z, rotation, horizon, config))


def floor_union(floor: Sequence[np.ndarray]):
    """Union of a scene's floor polygons (``Scene.floor``: list of ``(N, 2)`` x, z arrays) as one geometry."""
    polys = [shapely.Polygon(np.asarray(p, float)) for p in floor if len(p) >= 3]
    if not polys:
        raise ValueError("the scene has no floor polygon (scene.json 'floor'); the searched area is undefined")
    geom = shapely.union_all([shapely.make_valid(p) for p in polys])
    # Repairing a self-touching outline (e.g. a ring that doubles back along a wall, as in the recorded floors
    # of FloorPlan8 and FloorPlan204) gives a collection of polygons and zero-area lines; keep the polygons.
    parts = [g for g in shapely.get_parts(geom) if g.geom_type in ("Polygon", "MultiPolygon")]
    geom = shapely.union_all(parts) if parts else shapely.Polygon()
    if geom.area <= 0:
        raise ValueError("the scene's floor polygons have zero area")
    return geom


def scene_floor(scene):
    """A scene's floor as one shapely geometry: its ``scene.json`` floor polygons, or, for imported data
    without them (the paper's RoomBounds unavailable), the union of the 0.25 m grid cells centred on its
    reachable positions."""
    if len(scene.floor):
        return floor_union(scene.floor)
    pos = np.unique(np.stack([np.round(scene.x / GRID_SIZE), np.round(scene.z / GRID_SIZE)], 1), axis=0) * GRID_SIZE
    h = GRID_SIZE / 2
    return shapely.union_all(shapely.box(pos[:, 0] - h, pos[:, 1] - h, pos[:, 0] + h, pos[:, 1] + h))


class ExactSearchedRegion:
    """Reference searched region of one episode with shapely: ``RG_t = (RG_{t-1} U T_t) n floor``."""

    def __init__(self, floor, config: AreaConfig = AreaConfig()):
        self.floor = floor if isinstance(floor, shapely.Geometry) else floor_union(floor)
        self.config = config
        self.reset()

    def reset(self) -> None:
        """Start an episode: ``RG_0`` is empty."""
        self.region = shapely.Polygon()

    @property
    def area(self) -> float:
        """``Area(RG_t)`` in square metres."""
        return float(self.region.area)

    def add(self, x: float, z: float, rotation: int, horizon: int) -> float:
        """Add the trapezoid seen from this pose; returns the gained area ``Area(RG_t) - Area(RG_{t-1})`` m^2."""
        before = self.region.area
        t = trapezoid(x, z, rotation, horizon, self.config)
        self.region = shapely.intersection(shapely.union(self.region, t), self.floor)
        return float(self.region.area - before)


def profile_of(rotation, horizon) -> np.ndarray:
    """Pose profile index ``(rotation / 45) * 2 + (horizon == 30)``; there are 16 profiles and stencils."""
    rotation = np.asarray(rotation).astype(np.int64) % 360
    horizon = np.asarray(horizon).astype(np.int64)
    if (rotation % ROTATE_STEP).any():
        bad = int(rotation[(rotation % ROTATE_STEP) != 0].flat[0])
        raise ValueError(f"rotation {bad} is not a multiple of {ROTATE_STEP} degrees")
    bad = (horizon != 0) & (horizon != 30)
    if bad.any():
        raise ValueError(f"no observable trapezoid is defined for horizon {int(horizon[bad].flat[0])} (only 0 and 30)")
    return (rotation // ROTATE_STEP) * 2 + (horizon == 30)


def stencil_reach(config: AreaConfig) -> int:
    """Blocks from the agent's block to the farthest block any stencil touches (rasters pad by more)."""
    far = max(config.far_level, config.far_down)
    return int(np.ceil(far * np.sqrt(2) / config.block_size)) + 2


def stencil_weights(rotation: int, horizon: int, config: AreaConfig = AreaConfig()):
    """Fraction of each sample's share of the plane inside the trapezoid of an agent at the origin.

    Returns ``(du, dv, weight)`` over the stencil window: sample ``(du, dv)`` sits at
    ``((du + 1/2) s, (dv + 1/2) s)`` metres from the agent (``s`` the sample size). Samples strictly inside
    weigh 1. A trapezoid edge that runs along a row of samples gets the fraction of that row's band on the
    inner side: the lateral edges of headings 0/90/180/270 pass through sample centres (weight 1/2, the
    test is on exact integers), and the bases of the diagonal headings cut the diagonal rows of samples,
    spaced ``s / sqrt(2)``, at a fixed fraction.
    """
    near, far = config.bases(horizon)
    s = config.sample_size
    r = stencil_reach(config) * BLOCK
    d = np.arange(-r, r)
    du, dv = np.meshgrid(d, d, indexing="xy")
    px2, pz2 = 2 * du + 1, 2 * dv + 1
    rad = np.deg2rad(rotation)
    ex, ez = int(round(np.sin(rad))), int(round(np.cos(rad)))
    norm = np.hypot(ex, ez)
    f2 = px2 * ex + pz2 * ez  # 2 * fwd * norm / s, exact
    l2 = px2 * ez - pz2 * ex  # 2 * lat * norm / s, exact
    lateral = np.where(np.abs(l2) < f2, 1.0, np.where(np.abs(l2) == f2, 0.5, 0.0))
    fwd = f2 * s / (2 * norm)  # metres
    half = s / (2 * norm)  # half the spacing of the sample rows across the bases
    base = np.clip((np.minimum(far, fwd + half) - np.maximum(near, fwd - half)) / (2 * half), 0.0, 1.0)
    w = lateral * base
    keep = w > 0
    return du[keep].astype(np.int64), dv[keep].astype(np.int64), w[keep]


#: Dither of the edge samples: ``frac(DITHER[0] * du + DITHER[1] * dv)``. Along a diagonal row of samples it
#: steps by the golden ratio 0.618..., along an anti-diagonal by 0.382..., so the included share of any run of
#: partial samples follows their weight closely.
DITHER = (0.5, 0.5 * (np.sqrt(5.0) - 1.0) - 0.5)


@lru_cache(maxsize=64)
def stencil_samples(rotation: int, horizon: int, config: AreaConfig = AreaConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Samples of the trapezoid of an agent at the origin: ``(du, dv)`` int arrays (x, z), in samples.

    Samples of weight 1 (:func:`stencil_weights`) are in; a partial sample of weight ``w`` is in when its
    dither value (:data:`DITHER`) is below ``w``, so the edges are unbiased in area: a whole trapezoid and
    a trapezoid clipped by a wall both come out within a few samples of their exact area.
    """
    du, dv, w = stencil_weights(rotation, horizon, config)
    dither = np.mod(DITHER[0] * du + DITHER[1] * dv, 1.0)
    keep = dither < w
    du, dv = du[keep], dv[keep]
    du.flags.writeable = dv.flags.writeable = False  # cached: shared by every caller
    return du, dv


def _pack_blocks(inside: np.ndarray) -> np.ndarray:
    """Pack a ``(8H, 8W)`` bool sample raster (row = z) into ``(H, W)`` uint64 blocks (bit = 8 * q + p)."""
    h, w = inside.shape[0] // BLOCK, inside.shape[1] // BLOCK
    bits = inside.reshape(h, BLOCK, w, BLOCK).transpose(0, 2, 1, 3).reshape(h, w, BLOCK * BLOCK)
    shifts = np.arange(BLOCK * BLOCK, dtype=np.uint64)
    return (bits.astype(np.uint64) << shifts).sum(axis=-1, dtype=np.uint64)


def _unpack_blocks(blocks: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_pack_blocks`: ``(H, W)`` uint64 -> ``(8H, 8W)`` bool."""
    h, w = blocks.shape
    shifts = np.arange(BLOCK * BLOCK, dtype=np.uint64)
    bits = ((blocks[..., None] >> shifts) & np.uint64(1)).astype(bool)
    return bits.reshape(h, w, BLOCK, BLOCK).transpose(0, 2, 1, 3).reshape(h * BLOCK, w * BLOCK)


if hasattr(np, "bitwise_count"):

    def popcount(x: np.ndarray) -> np.ndarray:
        """Number of set bits of each uint64."""
        return np.bitwise_count(x)
else:  # numpy < 2.0
    _POP8 = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)

    def popcount(x: np.ndarray) -> np.ndarray:
        """Number of set bits of each uint64 (byte lookup table)."""
        x = np.ascontiguousarray(x)
        return _POP8[x.view(np.uint8)].reshape(x.shape + (8,)).sum(axis=-1, dtype=np.uint8)


def stencil_blocks(rotation: int, horizon: int, config: AreaConfig = AreaConfig(), phase: tuple[int, int] = (0, 0)):
    """The stencil of a pose: ``(dcol, drow, mask)`` - offsets from the agent's block and the uint64 bit mask
    of the trapezoid's samples in each block. ``phase`` = (column, row) of the agent's position inside its
    block, in samples (0..7): the agent stands at the lower-left corner of sample ``phase`` of its block."""
    du, dv = stencil_samples(rotation, horizon, config)
    dcol, p = np.divmod(du + int(phase[0]), BLOCK)
    drow, q = np.divmod(dv + int(phase[1]), BLOCK)
    span = int(np.abs(dcol).max()) + 1
    keys, inv = np.unique((drow + span) * (2 * span + 1) + dcol + span, return_inverse=True)
    mask = np.zeros(len(keys), dtype=np.uint64)
    np.bitwise_or.at(mask, inv.reshape(-1), np.left_shift(np.uint64(1), (BLOCK * q + p).astype(np.uint64)))
    krow, kcol = np.divmod(keys, 2 * span + 1)
    return (kcol - span).astype(np.int64), (krow - span).astype(np.int64), mask


def _floor_samples(floor, cx: np.ndarray, cz: np.ndarray, parity: np.ndarray, s: float) -> np.ndarray:
    """Bool: the sample at ``(cx, cz)`` is on the floor. Samples lying on the floor's boundary (walls through
    sample centres, e.g. 0.125 m walls at a 0.05 m pitch) count in a checkerboard (``parity`` = u + v), half
    of them, so a wall through a row of samples costs no area on either side."""
    inside = shapely.contains_xy(floor, cx, cz)
    edge = shapely.intersects_xy(floor.boundary.buffer(s * 1e-6), cx, cz)
    inside[edge] = parity[edge] % 2 == 0
    return inside


class AreaIndex:
    """Static tables of the fast searched area for a bank of scenes (state ids concatenated in order).

    Every state maps to a *stencil* - its (rotation, horizon) profile and the sample phase of its position
    inside its block - and the stencils of each horizon are stored as one padded table, so that a batch is
    counted with one gather per horizon.

    Layout of an episode's coverage row (``rows x width`` blocks): the scene's content (floor near the
    positions) at rows ``[0, height)``, columns ``[0, content width)``, then ``reach + 1`` margin columns on
    the right and ``reach + 1`` margin rows on top, all-ones (off the floor). Rows of consecutive episodes
    are stored back to back after a leading margin, so a stencil block left of column 0 wraps into the
    previous row's right margin and one below row 0 lands in the previous episode's top margin: every
    stencil block outside the content hits an all-ones margin block, and writing ``old | mask`` back keeps
    it all-ones. Stencil padding entries point ``reach + 1`` rows below the agent (a margin row) with mask 0.

    Attributes:
        config: the :class:`AreaConfig`. width: blocks per raster row (all scenes); rows: raster rows per
        episode; row_len = rows * width; lead: blocks of the leading margin; height: ``(num_scenes,)``
        content rows of each scene.
        anchor: ``(total_S,)`` int64 flat index (within its episode row) of the block holding the position.
        group: ``(total_S,)`` int64 0 for horizon 0, 1 for horizon 30; stencil: ``(total_S,)`` int64 row of
            the state's stencil in ``offsets[group]`` / ``masks[group]``.
        offsets, masks: per horizon, ``(n_stencils, K)`` flat block offsets (int64) and bit masks (uint64).
        off_floor: ``(num_scenes, row_len)`` uint64, the bits of samples outside the floor set.
        origin: ``(num_scenes, 2)`` (x, z) metres of the lower-left corner of block (0, 0).
        floor_area: ``(num_scenes,)`` floor area at raster resolution, square metres.
    """

    def __init__(
        self,
        floors: Sequence,
        positions: Sequence[tuple[np.ndarray, np.ndarray]],
        rotations: np.ndarray,
        horizons: np.ndarray,
        config: AreaConfig = AreaConfig(),
    ):
        """``floors``: per scene, ``Scene.floor`` (list of polygons) or a shapely geometry; ``positions``: per
        scene the ``(x, z)`` arrays of its states; ``rotations``/``horizons``: all states concatenated."""
        if len(floors) != len(positions):
            raise ValueError("AreaIndex: one floor per scene is needed")
        self.config = config
        bs = config.block_size
        s = config.sample_size
        reach = self.reach = stencil_reach(config)
        geoms, us, vs, origins, widths, heights = [], [], [], [], [], []
        for fl, (x, z) in zip(floors, positions):
            g = fl if isinstance(fl, shapely.Geometry) else floor_union(fl)
            x = np.asarray(x, np.float64)
            z = np.asarray(z, np.float64)
            fx0, fz0, fx1, fz1 = g.bounds
            # content: the floor's bounding box, cut to the stencils' reach around the positions
            lo_x = min(float(x.min()), max(fx0, float(x.min()) - reach * bs))
            lo_z = min(float(z.min()), max(fz0, float(z.min()) - reach * bs))
            ox = float(x.min()) - np.ceil((float(x.min()) - lo_x) / bs - 1e-9) * bs
            oz = float(z.min()) - np.ceil((float(z.min()) - lo_z) / bs - 1e-9) * bs
            hi_x = min(fx1, float(x.max()) + reach * bs)
            hi_z = min(fz1, float(z.max()) + reach * bs)
            u, v = (x - ox) / s, (z - oz) / s
            if np.abs(u - np.round(u)).max() > 1e-3 or np.abs(v - np.round(v)).max() > 1e-3:
                raise ValueError(f"state positions are not on a {s} m lattice; the area raster needs grid positions")
            u, v = np.round(u).astype(np.int64), np.round(v).astype(np.int64)
            geoms.append(g)
            us.append(u)
            vs.append(v)
            origins.append((ox, oz))
            widths.append(max(int(u.max()) // BLOCK + 1, int(np.ceil((hi_x - ox) / bs - 1e-9))))
            heights.append(max(int(v.max()) // BLOCK + 1, int(np.ceil((hi_z - oz) / bs - 1e-9))))
        self.width = w = max(widths) + reach + 1
        self.height = np.array(heights, dtype=np.int64)
        self.rows = int(self.height.max()) + reach + 1
        self.row_len = self.rows * w
        self.lead = (reach + 1) * w
        self.origin = np.array(origins, dtype=np.float64).reshape(-1, 2)
        u, v = np.concatenate(us), np.concatenate(vs)
        self.anchor = (v // BLOCK) * w + u // BLOCK
        profile = profile_of(rotations, horizons)
        if len(profile) != len(self.anchor):
            raise ValueError("AreaIndex: rotations/horizons must cover every state of every scene")
        self.group = profile % 2
        key = (profile * BLOCK + v % BLOCK) * BLOCK + u % BLOCK  # (profile, row phase, column phase)
        self.stencil = np.zeros(len(key), dtype=np.int64)
        self.offsets, self.masks = [], []
        dummy = -(reach + 1) * w  # a margin block no real stencil entry reaches
        for grp in (0, 1):
            sel = self.group == grp
            keys, inv = np.unique(key[sel], return_inverse=True)
            self.stencil[sel] = inv.reshape(-1)
            rows = []
            for k in keys.tolist():
                prof, pv, pu = k // (BLOCK * BLOCK), (k // BLOCK) % BLOCK, k % BLOCK
                dc, dr, m = stencil_blocks((prof // 2) * ROTATE_STEP, 30 if prof % 2 else 0, config, (pu, pv))
                assert np.abs(dc).max() <= reach and np.abs(dr).max() <= reach
                rows.append((dr * w + dc, m))
            kmax = max((len(o) for o, _ in rows), default=0)
            off = np.full((len(rows), kmax), dummy, dtype=np.int64)
            msk = np.zeros((len(rows), kmax), dtype=np.uint64)
            for i, (o, m) in enumerate(rows):
                off[i, : len(o)] = o
                msk[i, : len(m)] = m
            self.offsets.append(off)
            self.masks.append(msk)
        self.off_floor = np.full((len(geoms), self.row_len), np.iinfo(np.uint64).max, dtype=np.uint64)
        for i, (g, (x0, z0), cw, h) in enumerate(zip(geoms, origins, widths, heights)):
            uu, vv = np.meshgrid(np.arange(cw * BLOCK), np.arange(h * BLOCK), indexing="xy")
            inside = _floor_samples(g, x0 + (uu + 0.5) * s, z0 + (vv + 0.5) * s, uu + vv, s)
            self.off_floor[i].reshape(self.rows, w)[:h, :cw] = ~_pack_blocks(inside)
        self.floor_area = (BLOCK * BLOCK * self.row_len - popcount(self.off_floor).sum(axis=1, dtype=np.int64)) * s * s

    @classmethod
    def from_scenes(cls, scenes: Sequence, config: AreaConfig = AreaConfig()) -> "AreaIndex":
        """Index for a list of :class:`~tsnav.data.reader.Scene` whose state ids are concatenated in order."""
        return cls(
            [scene_floor(sc) for sc in scenes],
            [(sc.x, sc.z) for sc in scenes],
            np.concatenate([sc.rotation for sc in scenes]),
            np.concatenate([sc.horizon for sc in scenes]),
            config,
        )

    def extent(self, scene: int) -> tuple[float, float, float, float]:
        """``(x_min, x_max, z_min, z_max)`` metres covered by ``scene``'s raster (for ``imshow``)."""
        x0, z0 = self.origin[scene]
        bs = self.config.block_size
        return x0, x0 + self.width * bs, z0, z0 + int(self.height[scene]) * bs


class BatchCoverage:
    """Per-episode coverage rasters of a batch of episodes: the fast searched region ``RG_t``.

    ``covered[b]`` holds one uint64 per block of episode ``b``'s raster (layout in :class:`AreaIndex`); a bit
    is set when its sample is off the floor or already searched, so the new samples under a stencil are
    exactly ``(T_t n floor) - RG_{t-1}`` at raster resolution.
    """

    def __init__(self, index: AreaIndex, batch_size: int):
        self.index = index
        self.batch_size = int(batch_size)
        self._flat = np.full(index.lead + self.batch_size * index.row_len, np.iinfo(np.uint64).max, dtype=np.uint64)
        self.covered = self._flat[index.lead :].reshape(self.batch_size, index.row_len)
        self.scene = np.zeros(self.batch_size, dtype=np.int64)
        self.samples = np.zeros(self.batch_size, dtype=np.int64)

    def reset(self, mask: np.ndarray, scene_idx: np.ndarray) -> None:
        """Empty the searched region of the episodes where ``mask`` is True (``scene_idx``: their scenes)."""
        mask = np.asarray(mask, dtype=bool)
        scene_idx = np.broadcast_to(np.asarray(scene_idx, dtype=np.int64), mask.shape)
        self.covered[mask] = self.index.off_floor[scene_idx[mask]]
        self.scene[mask] = scene_idx[mask]
        self.samples[mask] = 0

    def add(self, episodes: np.ndarray, states: np.ndarray) -> np.ndarray:
        """Add the trapezoid of each ``states[i]`` (global state id) to episode ``episodes[i]``'s region.

        Returns the gained area ``Area(RG_t) - Area(RG_{t-1})`` of each, square metres (float64).
        ``episodes`` must be distinct.
        """
        episodes = np.asarray(episodes, dtype=np.int64)
        states = np.asarray(states, dtype=np.int64)
        gained = np.zeros(len(episodes), dtype=np.int64)
        if len(episodes):
            idx = self.index
            flat = self._flat
            base = idx.lead + episodes * idx.row_len + idx.anchor[states]
            group = idx.group[states]
            for g in (0, 1):  # one padded gather per horizon and chunk of episodes
                sel_all = np.flatnonzero(group == g)
                for c in range(0, len(sel_all), CHUNK):  # chunks keep the (n, K) temporaries in cache
                    sel = sel_all[c : c + CHUNK]
                    row = idx.stencil[states[sel]]
                    cells = base[sel, None] + idx.offsets[g][row]
                    old = flat[cells]
                    upd = old | idx.masks[g][row]
                    np.bitwise_xor(upd, old, out=old)  # the samples this view adds
                    gained[sel] = popcount(old).sum(axis=1, dtype=np.int64)
                    flat[cells] = upd
            self.samples[episodes] += gained
        return gained * self.index.config.sample_size**2

    def reset_one(self, episode: int, scene: int) -> None:
        """:meth:`reset` of the one episode ``episode`` in scene ``scene`` (scalars; the single Gymnasium env's
        path, held equal to :meth:`reset` by ``tests/sim/test_gym_fast.py``)."""
        self.covered[episode] = self.index.off_floor[scene]
        self.scene[episode] = scene
        self.samples[episode] = 0

    def add_one(self, episode: int, state: int) -> float:
        """:meth:`add` of one episode and one global state id, in scalars: the same gained area (m^2) as
        ``add([episode], [state])[0]`` without the batch's index arrays (the single Gymnasium env's path)."""
        idx = self.index
        group, row = int(idx.group[state]), int(idx.stencil[state])
        cells = idx.offsets[group][row] + (idx.lead + episode * idx.row_len + int(idx.anchor[state]))
        old = self._flat[cells]
        upd = old | idx.masks[group][row]
        np.bitwise_xor(upd, old, out=old)  # the samples this view adds
        gained = int(popcount(old).sum(dtype=np.int64))
        self._flat[cells] = upd
        self.samples[episode] += gained
        return gained * idx.config.sample_size**2

    def area(self) -> np.ndarray:
        """``Area(RG_t)`` of every episode, square metres."""
        return self.samples * self.index.config.sample_size**2

    def region_mask(self, b: int) -> np.ndarray:
        """``(rows, cols)`` bool sample raster of episode ``b``'s searched region (row = z), see ``extent``."""
        idx = self.index
        s = int(self.scene[b])
        h, w = int(idx.height[s]), idx.width
        searched = self.covered[b].reshape(idx.rows, w)[:h] & ~idx.off_floor[s].reshape(idx.rows, w)[:h]
        return _unpack_blocks(searched)
