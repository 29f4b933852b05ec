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
  square lattice of pitch ``sample_size`` (1/32 m by default); a sample counts when it lies in the region.
  The samples are packed 8 x 8 into 64-bit *blocks* whose side (8 samples = 0.25 m) divides the position
  grid, so every agent stands on a block corner and the blocks a trapezoid touches, with the bits of the
  samples inside it, depend only on (rotation, horizon): one *stencil* (block offsets + bit masks) per pose
  profile serves every state of every scene. Each episode keeps one coverage word per block, with the
  samples off the floor preset to 1, so the area a step gains is ``popcount(mask & ~coverage)`` summed
  over the stencil, times ``sample_size**2``. A batch of episodes is counted with one gather per profile.

Samples sit at half-sample offsets from agent positions, so walls on the 0.125 m lattice (the usual room
bounds) fall between samples. Trapezoid edges that run along rows of samples (the lateral edges of headings
0/90/180/270 pass through sample centres; the bases of diagonal headings cut diagonal rows at a fixed
fraction) would bias the area by up to half a sample row per metre of edge; their samples are dithered in
proportion to the share of their row inside (:func:`stencil_weights`), which removes the bias even where a
wall clips the opposite edge. Every stencil is within 0.03% of 15 or 8.9375 m^2.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import shapely

from ..constants import GRID_SIZE, ROTATE_STEP

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
    """Pitch of the area samples of the fast implementation, metres. A block of 8 x 8 samples must divide
    the 0.25 m grid: 1/32 (blocks of 0.25 m) or 1/64, 1/96, ... (finer, slower)."""

    def __post_init__(self):
        for name in ("near_level", "far_level", "near_down", "far_down", "sample_size"):
            if not getattr(self, name) > 0:
                raise ValueError(f"AreaConfig.{name} must be positive, got {getattr(self, name)}")
        if not (self.near_level < self.far_level and self.near_down < self.far_down):
            raise ValueError("AreaConfig: the near base must be closer than the far base")
        k = GRID_SIZE / (BLOCK * self.sample_size)
        if abs(k - round(k)) > 1e-6 or round(k) < 1:
            raise ValueError(f"AreaConfig.sample_size {self.sample_size}: 8 samples must divide the {GRID_SIZE} m "
                             f"grid (use 1/32, 1/64, ...)")

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
    x, z, rot, hor = np.broadcast_arrays(np.asarray(x, float), np.asarray(z, float),
                                         np.asarray(rotation, float), np.asarray(horizon))
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
    """Blocks from the agent to the farthest block any stencil touches (rasters pad positions by this)."""
    far = max(config.far_level, config.far_down)
    return int(np.ceil(far * np.sqrt(2) / config.block_size)) + 1


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


def stencil_samples(rotation: int, horizon: int, config: AreaConfig = AreaConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Samples of the trapezoid of an agent at the origin: ``(du, dv)`` int arrays (x, z), in samples.

    Samples of weight 1 (:func:`stencil_weights`) are in; a partial sample of weight ``w`` is in when its
    dither value (:data:`DITHER`) is below ``w``, so the edges are unbiased in area: a whole trapezoid and
    a trapezoid clipped by a wall both come out within a few samples of their exact area.
    """
    du, dv, w = stencil_weights(rotation, horizon, config)
    dither = np.mod(DITHER[0] * du + DITHER[1] * dv, 1.0)
    keep = dither < w
    return du[keep], dv[keep]


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


def stencil_blocks(rotation: int, horizon: int, config: AreaConfig = AreaConfig()):
    """The stencil of a pose profile: ``(dcol, drow, mask)`` - block offsets from the block whose lower-left
    corner is the agent, and the uint64 bit mask of the trapezoid's samples in each block."""
    du, dv = stencil_samples(rotation, horizon, config)
    dcol, p = np.divmod(du, BLOCK)
    drow, q = np.divmod(dv, BLOCK)
    keys, inv = np.unique(np.stack([drow, dcol], axis=1), axis=0, return_inverse=True)
    mask = np.zeros(len(keys), dtype=np.uint64)
    np.bitwise_or.at(mask, inv.reshape(-1), np.left_shift(np.uint64(1), (BLOCK * q + p).astype(np.uint64)))
    return keys[:, 1].astype(np.int64), keys[:, 0].astype(np.int64), mask


class AreaIndex:
    """Static tables of the fast searched area for a bank of scenes (state ids concatenated in order).

    Attributes:
        config: the :class:`AreaConfig`. width: common raster width of all scenes, blocks.
        row_len: blocks per coverage row (``max height * width``); height: ``(num_scenes,)`` rows, blocks.
        anchor: ``(total_S,)`` int64 flat index of the block whose lower-left corner is the state's position.
        profile: ``(total_S,)`` int64 pose profile (:func:`profile_of`).
        offsets, masks: per profile, flat block offsets (int64) and sample bit masks (uint64) of the stencil.
        off_floor: ``(num_scenes, row_len)`` uint64, the bits of samples outside the floor set.
        origin: ``(num_scenes, 2)`` (x, z) metres of the lower-left corner of block (0, 0).
        floor_area: ``(num_scenes,)`` floor area at raster resolution, square metres.
    """

    def __init__(self, floors: Sequence, positions: Sequence[tuple[np.ndarray, np.ndarray]],
                 rotations: np.ndarray, horizons: np.ndarray, config: AreaConfig = AreaConfig()):
        """``floors``: per scene, ``Scene.floor`` (list of polygons) or a shapely geometry; ``positions``: per
        scene the ``(x, z)`` arrays of its states; ``rotations``/``horizons``: all states concatenated."""
        if len(floors) != len(positions):
            raise ValueError("AreaIndex: one floor per scene is needed")
        self.config = config
        bs = config.block_size
        s = config.sample_size
        pad = stencil_reach(config) + 1
        geoms, cols, rows, origins, widths, heights = [], [], [], [], [], []
        for fl, (x, z) in zip(floors, positions):
            g = fl if isinstance(fl, shapely.Geometry) else floor_union(fl)
            x = np.asarray(x, np.float64)
            z = np.asarray(z, np.float64)
            x0, z0 = float(x.min()), float(z.min())
            ci, ri = (x - x0) / bs, (z - z0) / bs
            if np.abs(ci - np.round(ci)).max() > 1e-3 or np.abs(ri - np.round(ri)).max() > 1e-3:
                raise ValueError(f"state positions are not on a {bs} m lattice; the area raster needs grid positions")
            ci = np.round(ci).astype(np.int64) + pad
            ri = np.round(ri).astype(np.int64) + pad
            geoms.append(g)
            cols.append(ci)
            rows.append(ri)
            origins.append((x0 - pad * bs, z0 - pad * bs))
            widths.append(int(ci.max()) + pad + 1)
            heights.append(int(ri.max()) + pad + 1)
        self.width = w = max(widths)
        self.height = np.array(heights, dtype=np.int64)
        self.row_len = int(self.height.max()) * w
        self.origin = np.array(origins, dtype=np.float64).reshape(-1, 2)
        self.anchor = np.concatenate([r * w + c for r, c in zip(rows, cols)]).astype(np.int64)
        self.profile = profile_of(rotations, horizons)
        if len(self.profile) != len(self.anchor):
            raise ValueError("AreaIndex: rotations/horizons must cover every state of every scene")
        self.offsets, self.masks = [], []
        for p in range(16):
            dc, dr, m = stencil_blocks((p // 2) * ROTATE_STEP, 30 if p % 2 else 0, config)
            self.offsets.append(dr * w + dc)
            self.masks.append(m)
        self.off_floor = []
        for g, (x0, z0), h in zip(geoms, origins, heights):
            u = np.arange(w * BLOCK)
            v = np.arange(h * BLOCK)
            uu, vv = np.meshgrid(u, v, indexing="xy")
            inside = shapely.contains_xy(g, x0 + (uu + 0.5) * s, z0 + (vv + 0.5) * s)
            row = np.full(self.row_len, np.iinfo(np.uint64).max, dtype=np.uint64)
            row[: h * w] = ~_pack_blocks(inside).reshape(-1)
            self.off_floor.append(row)
        self.floor_area = np.array([(BLOCK * BLOCK * self.row_len - popcount(r).sum(dtype=np.int64)) * s * s
                                    for r in self.off_floor])
        self.off_floor = np.stack(self.off_floor)

    @classmethod
    def from_scenes(cls, scenes: Sequence, config: AreaConfig = AreaConfig()) -> "AreaIndex":
        """Index for a list of :class:`~tsnav.data.reader.Scene` whose state ids are concatenated in order."""
        return cls([scene_floor(sc) for sc in scenes], [(sc.x, sc.z) for sc in scenes],
                   np.concatenate([sc.rotation for sc in scenes]), np.concatenate([sc.horizon for sc in scenes]),
                   config)

    def extent(self, scene: int) -> tuple[float, float, float, float]:
        """``(x_min, x_max, z_min, z_max)`` metres covered by ``scene``'s raster (for ``imshow``)."""
        x0, z0 = self.origin[scene]
        bs = self.config.block_size
        return x0, x0 + self.width * bs, z0, z0 + int(self.height[scene]) * bs


class BatchCoverage:
    """Per-episode coverage rasters of a batch of episodes: the fast searched region ``RG_t``.

    ``covered[b]`` holds one uint64 per block of episode ``b``'s scene; a bit is set when its sample is off
    the floor or already searched, so the new samples under a stencil are exactly ``(T_t n floor) - RG_{t-1}``
    at raster resolution.
    """

    def __init__(self, index: AreaIndex, batch_size: int):
        self.index = index
        self.batch_size = int(batch_size)
        self.covered = np.full((self.batch_size, index.row_len), np.iinfo(np.uint64).max, dtype=np.uint64)
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
            flat = self.covered.reshape(-1)
            base = episodes * idx.row_len + idx.anchor[states]
            prof = idx.profile[states]
            order = np.argsort(prof, kind="stable")
            bounds = np.searchsorted(prof[order], np.arange(17))
            for p in range(16):  # one gather per pose profile, all episodes of that profile at once
                sel = order[bounds[p]:bounds[p + 1]]
                if len(sel) == 0:
                    continue
                cells = base[sel, None] + idx.offsets[p][None, :]
                old = flat[cells]
                upd = old | idx.masks[p]
                np.bitwise_xor(upd, old, out=old)  # the samples this view adds
                gained[sel] = popcount(old).sum(axis=1, dtype=np.int64)
                flat[cells] = upd
            self.samples[episodes] += gained
        return gained * self.index.config.sample_size ** 2

    def area(self) -> np.ndarray:
        """``Area(RG_t)`` of every episode, square metres."""
        return self.samples * self.index.config.sample_size ** 2

    def region_mask(self, b: int) -> np.ndarray:
        """``(rows, cols)`` bool sample raster of episode ``b``'s searched region (row = z), see ``extent``."""
        s = int(self.scene[b])
        h, w = int(self.index.height[s]), self.index.width
        searched = self.covered[b, : h * w] & ~self.index.off_floor[s][: h * w]
        return _unpack_blocks(searched.reshape(h, w))
