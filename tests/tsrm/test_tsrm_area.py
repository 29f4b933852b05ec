"""Searched region of the exploration reward: trapezoid geometry, the shapely reference, the packed raster."""

import numpy as np
import pytest
import shapely

from tsnav.data.toy import toy_scene
from tsnav.tsrm.area import (
    AreaConfig,
    AreaIndex,
    BatchCoverage,
    ExactSearchedRegion,
    floor_union,
    profile_of,
    stencil_samples,
    stencil_weights,
    trapezoid,
    trapezoid_vertices,
)

L_FLOOR = np.array([[-0.125, -0.125], [6.125, -0.125], [6.125, 2.625], [3.125, 2.625], [3.125, 5.125], [-0.125, 5.125]])


def l_room():
    """A 6 x 5 m room with its 3 x 2.5 m upper-right quarter cut off (an L), positions every 0.25 m."""
    blocked = [(x * 0.25, z * 0.25) for x in range(13, 25) for z in range(11, 21)]
    sc = toy_scene(6.0, 5.0, blocked=blocked, name="L")
    sc.floor = [L_FLOOR.copy()]
    return sc


def random_walks(scene, n, steps, seed):
    """``(steps + 1, n)`` state ids of random walks (MoveAhead-heavy, with rotations and looks)."""
    rng = np.random.default_rng(seed)
    s = rng.integers(0, scene.num_states, n)
    out = [s]
    for _ in range(steps):
        s = scene.next_state[s, rng.choice(5, n, p=[0.5, 0.15, 0.15, 0.1, 0.1])]
        out.append(s)
    return np.array(out)


def test_trapezoid_areas_by_hand():
    # (4^2 - 1^2) = 15 m^2 looking ahead, (3^2 - 0.25^2) = 8.9375 m^2 looking down, at every heading
    for r in range(0, 360, 45):
        assert trapezoid(1.0, 2.0, r, 0).area == pytest.approx(15.0)
        assert trapezoid(1.0, 2.0, r, 30).area == pytest.approx(8.9375)


def test_trapezoid_corners_and_heading():
    # heading 0 faces +z: near base at z = 1 with half-width 1, far base at z = 4 with half-width 4
    v = trapezoid_vertices(0.0, 0.0, 0, 0)
    assert {tuple(np.round(p, 9)) for p in v} == {(-1, 1), (1, 1), (4, 4), (-4, 4)}
    # heading 90 faces +x, looking down: bases at x = 0.25 and x = 3
    v = trapezoid_vertices(0.0, 0.0, 90, 30)
    assert {tuple(np.round(p, 9)) for p in v} == {(0.25, 0.25), (0.25, -0.25), (3, 3), (3, -3)}
    # heading 45: the near-base corners lie on the +x and +z axes at distance sqrt(2) * 1
    v = trapezoid_vertices(0.0, 0.0, 45, 0)
    assert {tuple(np.round(p, 9)) for p in v[:2]} == {(0, round(np.sqrt(2), 9)), (round(np.sqrt(2), 9), 0)}


def test_trapezoid_clipped_by_walls():
    # wall along the heading through the agent: half the trapezoid remains
    half = shapely.box(0, -10, 10, 10)
    assert trapezoid(0, 0, 0, 0).intersection(half).area == pytest.approx(7.5)
    # wall across the heading 2 m ahead: the part between the near base (1 m) and the wall, 2^2 - 1^2
    front = shapely.box(-10, -10, 10, 2)
    assert trapezoid(0, 0, 0, 0).intersection(front).area == pytest.approx(3.0)
    reg = ExactSearchedRegion([np.array([[-10, -10], [10, -10], [10, 2], [-10, 2]])])
    assert reg.add(0, 0, 0, 0) == pytest.approx(3.0)


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="horizon 60"):
        trapezoid(0, 0, 0, 60)
    with pytest.raises(ValueError, match="sample_size"):
        AreaConfig(sample_size=0.03)
    with pytest.raises(ValueError, match="near base"):
        AreaConfig(near_level=5.0)
    with pytest.raises(ValueError, match="no floor"):
        floor_union([])
    with pytest.raises(ValueError, match="rotation 30"):
        profile_of([30], [0])


def test_exact_region_is_monotone_and_bounded_by_floor():
    sc = l_room()
    floor_area = floor_union(sc.floor).area
    walks = random_walks(sc, 4, 40, seed=0)
    for b in range(walks.shape[1]):
        reg = ExactSearchedRegion(sc.floor)
        prev = 0.0
        for s in walks[:, b]:
            gain = reg.add(sc.x[s], sc.z[s], sc.rotation[s], sc.horizon[s])
            assert gain >= -1e-9
            assert reg.area == pytest.approx(prev + gain)
            assert reg.area <= floor_area + 1e-9
            prev = reg.area
        # the same view again adds nothing
        assert reg.add(sc.x[s], sc.z[s], sc.rotation[s], sc.horizon[s]) == pytest.approx(0.0, abs=1e-9)


def test_stencil_areas():
    cfg = AreaConfig()
    s2 = cfg.sample_size**2
    for r in range(0, 360, 45):
        for h, exact in ((0, 15.0), (30, 8.9375)):
            # the weights integrate the trapezoid (up to its four corners); the dithered samples within 0.1%
            assert stencil_weights(r, h, cfg)[2].sum() * s2 == pytest.approx(exact, rel=1e-5)
            n = len(stencil_samples(r, h, cfg)[0])
            assert n * s2 == pytest.approx(exact, rel=1e-3)
            if r % 90 == 0:  # only the dithered half-samples on the two lateral edges can differ
                assert abs(n * s2 - exact) <= 4 * s2


def test_single_views_match_shapely_at_every_state():
    sc = toy_scene(4.0, 3.0)
    idx = AreaIndex.from_scenes([sc])
    assert idx.floor_area[0] == pytest.approx(floor_union(sc.floor).area)
    n = sc.num_states
    cov = BatchCoverage(idx, n)
    cov.reset(np.ones(n, bool), np.zeros(n, int))
    fast = cov.add(np.arange(n), np.arange(n))
    fl = floor_union(sc.floor)
    exact = np.array(
        [trapezoid(sc.x[s], sc.z[s], sc.rotation[s], sc.horizon[s]).intersection(fl).area for s in range(n)]
    )
    # one view, clipped by walls in every way the room allows: within 0.03 m^2 (a sample row of a 1 m edge)
    assert np.abs(fast - exact).max() < 0.03
    assert np.abs(fast - exact).mean() < 0.005


@pytest.mark.parametrize("sample_size", [1 / 32, 0.05])
def test_fast_matches_exact_over_random_walks(sample_size):
    sc = l_room()
    idx = AreaIndex.from_scenes([sc], AreaConfig(sample_size=sample_size))
    walks = random_walks(sc, 24, 30, seed=1)
    b = walks.shape[1]
    cov = BatchCoverage(idx, b)
    cov.reset(np.ones(b, bool), np.zeros(b, int))
    refs = [ExactSearchedRegion(sc.floor, idx.config) for _ in range(b)]
    prev = np.zeros(b)
    for states in walks:
        gain = cov.add(np.arange(b), states)
        exact = np.array([r.add(sc.x[s], sc.z[s], sc.rotation[s], sc.horizon[s]) for r, s in zip(refs, states)])
        assert (gain >= 0).all()
        assert np.abs(gain - exact).max() < 0.03 * sample_size * 32
        assert np.all(cov.area() >= prev) and np.all(cov.area() <= idx.floor_area[0] + 1e-9)
        prev = cov.area().copy()
    exact_total = np.array([r.area for r in refs])
    # whole episodes agree within 1% (plus two samples' area for regions of a few hundredths of a m^2)
    assert np.all(np.abs(cov.area() - exact_total) <= 0.01 * exact_total + 2 * idx.config.sample_size**2)
    # the raster of the region holds exactly the counted samples
    for e in range(3):
        assert cov.region_mask(e).sum() * idx.config.sample_size**2 == pytest.approx(cov.area()[e])


def test_batch_rows_are_independent_and_reset():
    sc = l_room()
    other = toy_scene(2.0, 1.5, name="Small")
    idx = AreaIndex.from_scenes([sc, other])
    off = sc.num_states
    cov = BatchCoverage(idx, 3)
    cov.reset(np.ones(3, bool), np.array([0, 1, 0]))
    s0, s1 = sc.index("1.00|1.00|0|0"), other.index("0.00|0.00|45|0")
    g = cov.add(np.array([0, 1, 2]), np.array([s0, off + s1, s0]))
    assert g[0] == g[2] > 0
    assert g[1] == pytest.approx(trapezoid(0, 0, 45, 0).intersection(floor_union(other.floor)).area, abs=0.03)
    assert cov.add(np.array([0]), np.array([s0]))[0] == 0.0  # revisiting adds nothing
    cov.reset(np.array([True, False, False]), np.array([0, 1, 0]))
    assert cov.area()[0] == 0 and cov.area()[2] == g[2]
    assert cov.add(np.array([0]), np.array([s0]))[0] == g[0]


def test_floor_falls_back_to_reachable_cells():
    sc = toy_scene(2.0, 1.5, blocked=[(1.0, 0.75)])
    sc.floor = []  # imported data without room bounds
    from tsnav.tsrm.area import scene_floor

    floor = scene_floor(sc)
    # 9 x 7 positions minus one, each a 0.25 m square
    assert floor.area == pytest.approx((9 * 7 - 1) * 0.0625)
    idx = AreaIndex.from_scenes([sc])
    assert idx.floor_area[0] == pytest.approx(floor.area)


def test_floor_outline_doubling_back_keeps_its_polygon():
    # A recorded floor ring that runs out along a wall and back (FloorPlan8 and FloorPlan204 of ithor-real):
    # shapely repairs it into a polygon plus a zero-area line; the floor is the polygon alone, and the fast
    # area index (which needs the floor's boundary) builds on it.
    ring = np.array([(0, 0), (1, 0), (1, 1), (0, 1), (0, 0.5), (-1, 0.5), (0, 0.5)], float)
    fl = floor_union([ring])
    assert fl.geom_type == "Polygon" and fl.area == pytest.approx(1.0) and fl.boundary is not None
    assert fl.equals(floor_union([ring[:4]]))
