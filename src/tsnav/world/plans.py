"""Reading RoboTHOR's top-down plan images: walls, the apartment outline and furniture footprints (issue 46).

A plan is a 300 x 300 RGB orthographic render from above (``data/robothor/plans/``, ``CALIBRATION.txt``): walls
show as thin light lines one or two pixels wide, furniture as coloured blobs on a dark brown floor, about 4.2 cm
a pixel. All functions here work on numpy arrays (a hand-drawn array in a test is a plan like any other); the
rules are general, none names a scene. The rules of each version are in :data:`RULES`.

Walls (:func:`infer_walls`). The five furniture variants of an apartment share its walls, so each pixel votes:

1. *Ridges.* In each variant a pixel is a horizontal-line pixel when its luminance exceeds that of the pixels
   :data:`RIDGE_OFFSET` rows above and below by more than :data:`RIDGE_MIN` (a vertical-line pixel: columns left
   and right); furniture and its shadows make such pixels too, but rarely in the same place in every variant.
2. *Vote.* A pixel is a wall-line pixel of an orientation when at least :data:`VOTE_MIN` of the variants say so.
3. *Segments.* Along each row (column) the voted pixels form runs; gaps of at most :data:`MAX_GAP` pixels are
   bridged, runs shorter than :data:`MIN_RUN` dropped; runs on neighbouring rows that overlap are one wall, at
   their mean row. Every wall is axis-aligned (RoboTHOR's are).
4. *Outline.* The apartment is a rectangle. Its sides start at the extent of the segments of at least twice
   :data:`MIN_RUN` (their endpoints included: interior walls end on the outer walls even where an outer wall's
   own line is faint, as the bottom walls are in every plan). Each side then moves to the nearest line of its
   orientation, within :data:`OUTLINE_IN` pixels inwards and :data:`OUTLINE_OUT` outwards, that shows a faint line
   or a step (the edge of the lit floor) in most variants over the largest share of the span (ties within
   :data:`PROFILE_TIE`: the nearest). Segments within :data:`OUTER_BAND` pixels of a side are outer walls; the
   others inside the rectangle are interior walls.
5. *Wall ends.* An interior wall ending within :data:`SNAP` pixels of a side or of a crossing wall is extended to
   it, and so is one ending within :data:`EXTEND` pixels when the gap shows a line in some variant on at least
   half its pixels (a wall hidden under furniture in most variants).

Furniture (:func:`furniture_blobs`, for scenes without object records): inside the outline, a pixel is not
floor when its colour is far from the floor's (the median colour of the pixels inside the outline): chroma
farther than :data:`CHROMA_MIN` or luminance more than :data:`LUMA_MIN` away from the local floor (the median
of a :data:`LOCAL_WINDOW`-pixel window); wall-line pixels are left out, the mask is opened (3 x 3) and blobs of
at least :data:`MIN_BLOB` pixels are kept, each as its pixel bounding box. A blob of which at least
:data:`STATIC_SHARE` of the pixels look the same in all five plans of the apartment (:func:`static_mask`) is a
fixture (the glass ceiling lamps, seen from above) and is left out: no recorded furniture of the train scenes stands
in the same place in all five variants of its apartment. A blob of :data:`LAMP_PX` pixels, green >= red >= blue
and brighter than :data:`LAMP_LUMA` is a glass ceiling lamp (:func:`is_lamp`): of the 796 blobs of the 60 train
plans, 74 cover no recorded object; the rule finds 59 of them and 3 of the 722 others.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

#: Plan calibration (``plans/CALIBRATION.txt``): camera centre x, z, orthographic half-size (m), image side (px).
CAMERA_X, CAMERA_Z, HALF_SIZE, PLAN_PX = 5.05, -5.663423, 6.261584, 300
SPAN = 2 * HALF_SIZE
PIXEL = SPAN / PLAN_PX  #: metres per pixel (0.0417)
X0, Z0 = CAMERA_X - HALF_SIZE, CAMERA_Z - HALF_SIZE

#: Version of the plan rules; :data:`RULES` holds each version's constants.
PLAN_VERSION = 1
RIDGE_OFFSET = 2  #: pixels between a line pixel and the floor pixels it is compared with
RIDGE_MIN = 10.0  #: luminance (0-255) a line pixel exceeds both neighbours by
VOTE_MIN = 3  #: variants (of 5) that must see a line pixel
MAX_GAP = 3  #: pixels of a line bridged along it (a chair's shadow across a wall)
MIN_RUN = 8  #: shortest wall segment, pixels (0.33 m)
OUTER_BAND = 3  #: pixels from the outline's side within which a segment is an outer wall
SNAP = 4  #: pixels: an interior wall ending this near a side (or another wall) is extended to it
CHROMA_MIN = 0.035  #: chroma (r, g of r+g+b) distance from the floor's that makes a pixel furniture
LUMA_MIN = 38.0  #: luminance above the local floor that makes a pixel furniture
DARK_FACTOR = 1.0  #: a pixel darker than the local floor is furniture beyond LUMA_MIN times this (shadows are dark)
LOCAL_WINDOW = 31  #: side of the window of the local floor luminance, pixels
MIN_BLOB = 12  #: smallest furniture blob, pixels (0.02 m^2)
LAMP_PX = (60, 140)  #: pixel count of a glass ceiling lamp blob (a 0.5 m disc is 113 px)
LAMP_LUMA = 110.0  #: mean brightness above which a lamp-sized greenish-white blob is a lamp
STATIC_TOL = 12.0  #: colour spread (0-255) across an apartment's plans under which a pixel is static
STATIC_SHARE = 0.6  #: share of static pixels that makes a blob a fixture of the apartment, not furniture
OUTLINE_RIDGE = 4.0  #: ridge of a faint line for the outline profile (rule 4)
OUTLINE_STEP = 10.0  #: luminance step for the outline profile (rule 4)
OUTLINE_MARGIN = 8  #: pixels left out at the ends of a profile's span
OUTLINE_IN, OUTLINE_OUT = 8, 25  #: pixels a side may move inwards / outwards from the segments' extent
PROFILE_MIN = 0.5  #: share of a side's span that must show a line for the side to move
PROFILE_TIE = 0.05  #: profile values this close to the best count as tied (the nearest to the extent wins)
EXTEND = 30  #: farthest an interior wall end is extended to a side or crossing wall, pixels (rule 5)
RULES = {
    1: {
        "ridge_offset": RIDGE_OFFSET,
        "ridge_min": RIDGE_MIN,
        "vote_min": VOTE_MIN,
        "max_gap": MAX_GAP,
        "min_run": MIN_RUN,
        "outer_band": OUTER_BAND,
        "snap": SNAP,
        "chroma_min": CHROMA_MIN,
        "luma_min": LUMA_MIN,
        "dark_factor": DARK_FACTOR,
        "local_window": LOCAL_WINDOW,
        "min_blob": MIN_BLOB,
        "lamp_px": LAMP_PX,
        "lamp_luma": LAMP_LUMA,
        "static_tol": STATIC_TOL,
        "static_share": STATIC_SHARE,
        "outline_ridge": OUTLINE_RIDGE,
        "outline_step": OUTLINE_STEP,
        "outline_margin": OUTLINE_MARGIN,
        "outline_in": OUTLINE_IN,
        "outline_out": OUTLINE_OUT,
        "profile_min": PROFILE_MIN,
        "profile_tie": PROFILE_TIE,
        "extend": EXTEND,
    }
}


def pixel_to_world(row: float, col: float) -> tuple[float, float]:
    """World ``(x, z)`` of a pixel centre (``CALIBRATION.txt``: row 0 is the top, larger z)."""
    return X0 + col * PIXEL, Z0 + (1 - row / PLAN_PX) * SPAN


def world_to_pixel(x, z):
    """``(row, col)`` (floats) of world ``x, z``; the inverse of :func:`pixel_to_world`."""
    return PLAN_PX * (1 - (np.asarray(z) - Z0) / SPAN), (np.asarray(x) - X0) / PIXEL


def luminance(rgb: np.ndarray) -> np.ndarray:
    """``(H, W)`` float luminance (0-255) of an ``(H, W, 3)`` RGB plan (ITU-R 601 weights)."""
    rgb = np.asarray(rgb, dtype=np.float64)
    return rgb[..., 0] * 0.299 + rgb[..., 1] * 0.587 + rgb[..., 2] * 0.114


def ridges(gray: np.ndarray, offset: int = RIDGE_OFFSET, min_rise: float = RIDGE_MIN) -> tuple[np.ndarray, np.ndarray]:
    """``(horizontal, vertical)`` boolean masks of line pixels of one plan (module docstring, rule 1); the
    border ``offset`` pixels are never line pixels."""
    g = np.asarray(gray, dtype=np.float64)
    H, W = g.shape
    h = np.zeros((H, W), bool)
    v = np.zeros((H, W), bool)
    o = offset
    h[o : H - o] = g[o : H - o] - np.maximum(g[: H - 2 * o], g[2 * o :]) > min_rise
    v[:, o : W - o] = g[:, o : W - o] - np.maximum(g[:, : W - 2 * o], g[:, 2 * o :]) > min_rise
    return h, v


def vote(masks: list[np.ndarray], vote_min: int = VOTE_MIN) -> np.ndarray:
    """Pixels at least ``vote_min`` of ``masks`` hold (module docstring, rule 2); all of them when fewer masks."""
    return np.sum(np.stack(masks), axis=0) >= min(vote_min, len(masks))


@dataclass(frozen=True)
class Segment:
    """An axis-aligned wall line in pixels: ``axis`` 0 is horizontal (along a row: ``line`` is the row, ``a0..a1``
    the columns), 1 vertical (``line`` the column, ``a0..a1`` the rows); ``a0 <= a1`` inclusive."""

    axis: int
    line: float
    a0: int
    a1: int

    @property
    def length(self) -> int:
        return self.a1 - self.a0 + 1


def runs_1d(mask: np.ndarray, max_gap: int = MAX_GAP, min_run: int = MIN_RUN) -> list[tuple[int, int]]:
    """Inclusive ``(start, end)`` runs of True in a 1-D mask, gaps of at most ``max_gap`` bridged, runs shorter
    than ``min_run`` dropped."""
    idx = np.flatnonzero(mask)
    if len(idx) == 0:
        return []
    cut = np.flatnonzero(np.diff(idx) > max_gap + 1)
    starts = np.r_[idx[0], idx[cut + 1]]
    ends = np.r_[idx[cut], idx[-1]]
    return [(int(s), int(e)) for s, e in zip(starts, ends) if e - s + 1 >= min_run]


def segments(mask: np.ndarray, axis: int, max_gap: int = MAX_GAP, min_run: int = MIN_RUN) -> list[Segment]:
    """Wall segments of one orientation (module docstring, rule 3): ``axis`` 0 reads rows of ``mask``, 1 columns.
    Runs on neighbouring lines that overlap along the line merge into one segment at their mean line."""
    m = np.asarray(mask, bool)
    if axis == 1:
        m = m.T
    raw = [(r, s, e) for r in range(m.shape[0]) for s, e in runs_1d(m[r], max_gap, min_run)]
    groups: list[list[tuple[int, int, int]]] = []
    for r, s, e in raw:  # rows ascending: a run joins a group whose last row is the row above and overlaps
        for g in groups:
            if r - max(x[0] for x in g) == 1 and any(s <= x[2] and x[1] <= e for x in g):
                g.append((r, s, e))
                break
        else:
            groups.append([(r, s, e)])
    out = []
    for g in groups:
        w = np.array([x[2] - x[1] + 1 for x in g], float)
        line = float(np.average([x[0] for x in g], weights=w))
        out.append(Segment(axis, round(line, 2), min(x[1] for x in g), max(x[2] for x in g)))
    return sorted(out, key=lambda s: (s.axis, s.line, s.a0))


@dataclass
class WallPlan:
    """Walls of one apartment in pixels: ``outline`` ``(top row, left col, bottom row, right col)`` (the outer
    walls' centre lines), ``interior`` wall segments, and how many plans voted."""

    outline: tuple[float, float, float, float]
    interior: list[Segment] = field(default_factory=list)
    outer: list[Segment] = field(default_factory=list)
    plans: int = 0

    def to_json(self) -> dict:
        return {
            "outline_px": list(self.outline),
            "plans": self.plans,
            "interior_px": [[s.axis, s.line, s.a0, s.a1] for s in self.interior],
            "outer_px": [[s.axis, s.line, s.a0, s.a1] for s in self.outer],
        }


def relaxed_lines(gray: np.ndarray, offset: int = RIDGE_OFFSET) -> tuple[np.ndarray, np.ndarray]:
    """``(horizontal, vertical)`` masks of faint lines and steps (rule 4's outline profile): a ridge above
    :data:`OUTLINE_RIDGE` or a step between the two neighbours above :data:`OUTLINE_STEP` (an outer wall often shows
    only as the edge of the lit floor)."""
    g = np.asarray(gray, dtype=np.float64)
    H, W = g.shape
    o = offset
    h = np.zeros((H, W), bool)
    v = np.zeros((H, W), bool)
    up, mid, dn = g[: H - 2 * o], g[o : H - o], g[2 * o :]
    h[o : H - o] = (mid - np.maximum(up, dn) > OUTLINE_RIDGE) | (np.abs(up - dn) > OUTLINE_STEP)
    lf, mid, rt = g[:, : W - 2 * o], g[:, o : W - o], g[:, 2 * o :]
    v[:, o : W - o] = (mid - np.maximum(lf, rt) > OUTLINE_RIDGE) | (np.abs(lf - rt) > OUTLINE_STEP)
    return h, v


def snap_side(profile: np.ndarray, extent: float, outward: int) -> float:
    """Rule 4's side: the line nearest ``extent`` (the segments' extent on that side) among those within
    :data:`OUTLINE_IN` pixels inwards and :data:`OUTLINE_OUT` outwards (``outward`` +1: larger index) whose
    profile is within :data:`PROFILE_TIE` of the window's best; ``extent`` when no line reaches :data:`PROFILE_MIN`."""
    n = len(profile)
    lo, hi = (extent - OUTLINE_IN, extent + OUTLINE_OUT) if outward > 0 else (extent - OUTLINE_OUT, extent + OUTLINE_IN)
    idx = np.arange(max(int(np.ceil(lo)), 0), min(int(np.floor(hi)), n - 1) + 1)
    if len(idx) == 0 or profile[idx].max() < PROFILE_MIN:
        return float(extent)
    best = idx[profile[idx] >= profile[idx].max() - PROFILE_TIE]
    return float(best[np.argmin(np.abs(best - extent))])


def infer_walls(plans: list[np.ndarray]) -> WallPlan:
    """The walls of one apartment from its plans (RGB ``(H, W, 3)`` or luminance ``(H, W)`` arrays of the same
    shape; the module docstring's rules 1-5). ``ValueError`` when no wall segment is found."""
    if not plans:
        raise ValueError("no plans to infer walls from")
    grays = [luminance(p) if np.ndim(p) == 3 else np.asarray(p, np.float64) for p in plans]
    hv = [ridges(g) for g in grays]
    hmask = vote([h for h, _ in hv])
    vmask = vote([v for _, v in hv])
    segs = segments(hmask, 0) + segments(vmask, 1)
    if not segs:
        raise ValueError("no wall line found in the plans")
    longs = [s for s in segs if s.length >= 2 * MIN_RUN] or segs
    rows = [s.line for s in longs if s.axis == 0] + [a for s in longs if s.axis == 1 for a in (s.a0, s.a1)]
    cols = [s.line for s in longs if s.axis == 1] + [a for s in longs if s.axis == 0 for a in (s.a0, s.a1)]
    top, bottom, left, right = min(rows), max(rows), min(cols), max(cols)
    rel = [relaxed_lines(g) for g in grays]
    rh, rv = vote([h for h, _ in rel]), vote([v for _, v in rel])
    m = OUTLINE_MARGIN
    c0, c1 = int(left) + m, int(right) - m
    r0, r1 = int(top) + m, int(bottom) - m
    hprof = rh[:, c0 : c1 + 1].mean(axis=1) if c1 > c0 else np.zeros(len(rh))
    vprof = rv[r0 : r1 + 1, :].mean(axis=0) if r1 > r0 else np.zeros(rv.shape[1])
    top, bottom = snap_side(hprof, top, -1), snap_side(hprof, bottom, +1)
    left, right = snap_side(vprof, left, -1), snap_side(vprof, right, +1)
    outer, interior = [], []
    for s in segs:
        sides = (top, bottom) if s.axis == 0 else (left, right)
        if min(abs(s.line - sides[0]), abs(s.line - sides[1])) <= OUTER_BAND:
            outer.append(s)
        elif sides[0] < s.line < sides[1]:
            interior.append(s)
    # Rule 5: ends snapped to the sides and to the lines of crossing walls, or extended to them over a gap that
    # shows the line in some variant for at least half its length (a wall hidden under furniture in most variants).
    anyh, anyv = vote([h for h, _ in hv], 1), vote([v for _, v in hv], 1)
    out = []
    for s in interior:
        lo, hi = (left, right) if s.axis == 0 else (top, bottom)
        cross = [lo, hi] + [t.line for t in interior if t.axis != s.axis and t.a0 - SNAP <= s.line <= t.a1 + SNAP]
        seen = anyh[int(round(s.line))] if s.axis == 0 else anyv[:, int(round(s.line))]
        a0 = _extend(s.a0, cross, SNAP, seen, -1)
        a1 = _extend(s.a1, cross, SNAP, seen, +1)
        a0, a1 = max(lo, a0), min(hi, a1)
        if a1 - a0 + 1 >= MIN_RUN:
            out.append(Segment(s.axis, s.line, int(round(a0)), int(round(a1))))
    return WallPlan((float(top), float(left), float(bottom), float(right)), out, outer, len(plans))


def _extend(v: float, targets: list[float], snap: float, seen: np.ndarray, direction: int) -> float:
    """An end ``v`` moved to the nearest target line in ``direction`` within :data:`EXTEND` pixels when it is within
    ``snap`` or the gap shows a line pixel in some variant (``seen``) on at least half its pixels."""
    ahead = [t for t in targets if (t - v) * direction >= -snap]
    if not ahead:
        return v
    t = min(ahead, key=lambda t: abs(t - v))
    if abs(t - v) <= snap:
        return t
    if abs(t - v) > EXTEND:
        return v
    a, b = sorted((int(round(v)), int(round(t))))
    gap = seen[a : b + 1]
    return t if len(gap) and gap.mean() >= 0.5 else v


def wall_mask(shape: tuple[int, int], walls: WallPlan, pad: int = 1) -> np.ndarray:
    """Pixels within ``pad`` of a wall line (outline sides and interior segments)."""
    m = np.zeros(shape, bool)
    t, l, b, r = (int(round(v)) for v in walls.outline)
    for row in (t, b):
        m[max(row - pad, 0) : row + pad + 1, l : r + 1] = True
    for col in (l, r):
        m[t : b + 1, max(col - pad, 0) : col + pad + 1] = True
    for s in walls.interior:
        c = int(round(s.line))
        if s.axis == 0:
            m[max(c - pad, 0) : c + pad + 1, s.a0 : s.a1 + 1] = True
        else:
            m[s.a0 : s.a1 + 1, max(c - pad, 0) : c + pad + 1] = True
    return m


def furniture_mask(rgb: np.ndarray, walls: WallPlan) -> np.ndarray:
    """Pixels inside the outline that are not floor (module docstring, "Furniture"), before blob filtering."""
    rgb = np.asarray(rgb, dtype=np.float64)
    t, l, b, r = (int(round(v)) for v in walls.outline)
    inside = np.zeros(rgb.shape[:2], bool)
    inside[t + 2 : b - 1, l + 2 : r - 1] = True
    inside &= ~wall_mask(rgb.shape[:2], walls, pad=1)
    s = rgb.sum(axis=2) + 1e-6
    chroma = np.stack([rgb[..., 0] / s, rgb[..., 1] / s], axis=-1)
    floor_c = np.median(chroma[inside], axis=0)
    far_c = np.linalg.norm(chroma - floor_c, axis=-1) > CHROMA_MIN
    g = luminance(rgb)
    local = ndimage.median_filter(np.where(inside, g, np.median(g[inside])), size=LOCAL_WINDOW, mode="nearest")
    far_l = (g - local > LUMA_MIN) | (local - g > LUMA_MIN * DARK_FACTOR)
    return (far_c | far_l) & inside


def static_mask(plans: list[np.ndarray], tol: float = STATIC_TOL) -> np.ndarray:
    """Pixels that look the same (every channel within ``tol``) in all of ``plans`` (the variants of one
        apartment): its fixtures, such as the ceiling lamps seen from above; no furniture of the train scenes' records
        stands in the same place in all five variants of its apartment. A blob of :data:`LAMP_PX` pixels, green >= red >= blue
    and brighter than :data:`LAMP_LUMA` is a glass ceiling lamp (:func:`is_lamp`): of the 796 blobs of the 60 train
    plans, 74 cover no recorded object; the rule finds 59 of them and 3 of the 722 others."""
    a = np.stack([np.asarray(p, dtype=np.float64) for p in plans])
    spread = a.max(axis=0) - a.min(axis=0)
    return (spread.max(axis=-1) if spread.ndim == 3 else spread) <= tol


def is_lamp(pixels: int, mean_rgb) -> bool:
    """Whether a blob of ``pixels`` pixels and mean colour ``mean_rgb`` is one of RoboTHOR's glass ceiling lamps
    seen from above (module docstring, "Furniture"): :data:`LAMP_PX` pixels, green >= red >= blue, bright."""
    r, g, b = (float(v) for v in mean_rgb)
    return LAMP_PX[0] <= pixels <= LAMP_PX[1] and g >= r >= b and (r + g + b) / 3 > LAMP_LUMA


def furniture_blobs(rgb: np.ndarray, walls: WallPlan) -> list[tuple[int, int, int, int, int]]:
    """Furniture blobs of one plan as ``(row0, col0, row1, col1, pixels)`` (inclusive pixel bounding boxes), the
    largest first."""
    m = ndimage.binary_opening(furniture_mask(rgb, walls), structure=np.ones((3, 3), bool))
    lab, n = ndimage.label(m)
    out = []
    for k, sl in enumerate(ndimage.find_objects(lab), start=1):
        if sl is None:
            continue
        px = int((lab[sl] == k).sum())
        if px >= MIN_BLOB:
            out.append((sl[0].start, sl[1].start, sl[0].stop - 1, sl[1].stop - 1, px))
    return sorted(out, key=lambda b: -b[4])


__all__ = [
    "PIXEL",
    "PLAN_VERSION",
    "Segment",
    "WallPlan",
    "furniture_blobs",
    "furniture_mask",
    "infer_walls",
    "pixel_to_world",
    "ridges",
    "runs_1d",
    "segments",
    "vote",
    "wall_mask",
    "world_to_pixel",
]
