"""Reward terms as objects (tsrm/terms.py): each registered term's batched, scalar and reference code agree on
random episodes, alone; variants are lists of term names; the registry refuses what it cannot run."""

import numpy as np
import pytest

from sim_helpers import StagedReward
from tsnav.constants import CATEGORY_INDEX, DONE, MOVE_AHEAD, NUM_CATEGORIES, ROTATE_RIGHT
from tsnav.data.toy import toy_scene
from tsnav.sim.batch import SceneBank
from tsnav.tsrm import terms as term_registry
from tsnav.tsrm.reward import TERMS, VARIANT_TERMS, VARIANTS, RewardConfig, TSRMReward, TSRMRewardReference

BOWL, CHAIR = CATEGORY_INDEX["Bowl"], CATEGORY_INDEX["Chair"]


def two_rooms():
    a = toy_scene(4.0, 3.0, objects={"Bowl|1": (4.0, 3.0), "Chair|1": (0.5, 2.5)}, blocked=[(2.0, 1.0), (2.0, 1.25)])
    b = toy_scene(3.0, 2.0, objects={"Bowl|1": (0.0, 2.0), "Chair|1": (3.0, 0.0)}, name="B")
    return [a, b]


def test_variants_are_lists_of_registered_terms():
    assert TERMS == ("explore", "distance", "collision", "slack", "success", "regret")
    assert set(VARIANTS) >= {"baseline", "explore", "distance", "tsrm", "sparse", "tsrm-regret"}
    assert all(set(v) <= set(TERMS) for v in VARIANT_TERMS.values())
    assert VARIANT_TERMS["tsrm"] == ("explore", "distance", "collision", "slack", "success")  # the paper's
    assert VARIANT_TERMS["tsrm-regret"] == tuple(TERMS) and VARIANT_TERMS["sparse"] == ("slack", "success")
    assert not any("regret" in terms for v, terms in VARIANT_TERMS.items() if v != "tsrm-regret")  # off by default
    with pytest.raises(ValueError, match="unknown reward term"):
        term_registry.register_variant("mine", ("slack", "nope"))
    with pytest.raises(ValueError, match="not a RewardTerm"):
        term_registry.register_term(dict)
    with pytest.raises(ValueError, match="already registered"):
        term_registry.register_variant("tsrm", ("slack",))


@pytest.mark.parametrize("name", list(TERMS))
@pytest.mark.parametrize("exact_area", [False, True])
def test_each_term_batched_scalar_and_reference_agree(name, exact_area, monkeypatch):
    """One term alone (a variant of just that term), over 12 random episodes of two rooms with random stages:
    the batched ``step`` equals the paper reference (explore: the raster within K_e x 0.03 m^2 per step, the
    exact shapely area to 1e-9) and the scalar ``step_one`` equals ``step`` bit for bit."""
    if exact_area and name != "explore":
        pytest.skip("exact_area only changes the exploration term")
    monkeypatch.setitem(VARIANT_TERMS, f"only-{name}", (name,))
    scenes = two_rooms()
    bank = SceneBank(scenes, cache=False)
    cfg = RewardConfig(variant=f"only-{name}", distance_increase_scale=1.5, exact_area=exact_area)
    rng = np.random.default_rng(11)
    conf = rng.uniform(0, 0.75, (bank.num_states, NUM_CATEGORIES)).astype(np.float32)
    n = 12
    fast = StagedReward(TSRMReward(bank, cfg), confidence=conf)
    assert [t.name for t in fast.reward.terms] == [name]
    scene_idx = np.arange(n) % 2
    target = rng.choice([BOWL, CHAIR], n)
    local = np.array([rng.integers(0, scenes[s].num_states) for s in scene_idx])
    off = bank.offsets[scene_idx]
    fast.reset(np.ones(n, bool), scene_idx, target, local + off)
    refs, ones = [], []
    for i in range(n):
        sc, o = scenes[scene_idx[i]], int(off[i])
        refs.append(TSRMRewardReference(sc, cfg, confidence=conf[o : o + sc.num_states]))
        refs[-1].reset(target[i], local[i])
        one = TSRMReward(bank, cfg)
        one.reset_one(int(scene_idx[i]), int(target[i]), int(local[i] + o), searching=not refs[-1].pathfinding)
        ones.append(one)
    tol = (1e-9 if exact_area else 0.1 * 0.03) if name == "explore" else 1e-12
    nonzero = 0
    for _ in range(30):
        act = rng.choice(6, n, p=[0.5, 0.15, 0.15, 0.08, 0.08, 0.04])
        new = bank.next_state[local + off, act].astype(np.int64)
        collided = (new == local + off) & (act == MOVE_AHEAD)
        done = act == DONE
        success = done | (rng.random(n) < 0.1)  # an input to the terms; not every one of them reachable by a walk
        searching = fast.switch.searching.copy()
        r, terms = fast.step(local + off, act, new, collided, done, success)
        for i in range(n):
            rr, tr = refs[i].step(
                int(local[i]), int(act[i]), int(new[i] - off[i]), bool(collided[i]), bool(done[i]), bool(success[i])
            )
            assert terms[name][i] == pytest.approx(tr[name], abs=tol)
            assert all(terms[k][i] == 0.0 and tr[k] == 0.0 for k in TERMS if k != name)
            r1, t1 = ones[i].step_one(
                int(local[i] + off[i]),
                int(act[i]),
                int(new[i]),
                bool(collided[i]),
                bool(done[i]),
                bool(success[i]),
                searching=bool(searching[i]),
            )
            assert r1 == float(r[i]) and t1 == {k: float(v[i]) for k, v in terms.items()}
            nonzero += tr[name] != 0.0
        assert fast.stage.tolist() == [int(x.pathfinding) for x in refs]
        local = new - off
    assert nonzero > 3  # the walks exercise the term


def test_regret_charges_each_action_beyond_a_shortest_path():
    """The regret term (issue 47, a deviation from the paper, variant tsrm-regret): along a shortest path (the
    oracle's actions on SceneBank.dist, SPL's L*) it is 0; a full turn in place, on which the paper's distance term
    sums to exactly 0, costs 8 K_r; over any walk in the pathfinding stage it sums to -K_r (L - (D_start - D_end)),
    every step is a whole number of K_r at most 0, Done is free, and the searching stage is never charged."""
    from tsnav.sim.paths import UNREACHABLE, optimal_action_targets

    bank = SceneBank(two_rooms(), cache=False)
    cfg = RewardConfig(variant="tsrm-regret", k_regret=0.05)
    k = cfg.k_regret
    far = [s for s in range(bank.num_states) if bank.scene_of[s] == 0 and 6 <= bank.dist[s, BOWL] < UNREACHABLE]
    n = len(far)
    assert n > 10
    start = np.array(far, dtype=np.int64)
    target = np.full(n, BOWL)
    scene = bank.scene_of[start].astype(np.int64)
    path = np.zeros(n, dtype=bool)  # the pathfinding stage, as the env hands it in

    def fresh():
        r = TSRMReward(bank, cfg)
        r.reset(np.ones(n, bool), scene, target, start, searching=path)
        return r

    def walk(reward, actions_of, steps):
        state, sums = start.copy(), {"regret": np.zeros(n), "distance": np.zeros(n)}
        for _ in range(steps):
            act = actions_of(state)
            new = bank.next_state[state, act].astype(np.int64)
            _, terms = reward.step(
                state, act, new, (new == state) & (act == MOVE_AHEAD), act == DONE, act == DONE, path
            )
            for key in sums:
                sums[key] += terms[key]
            units = terms["regret"] / k  # minus the regret in actions: a whole number, never above 0
            assert (units <= 0).all() and np.allclose(units, np.round(units), atol=1e-5)
            state = new
        return state, sums

    # a shortest path: no regret, K_d per pose-graph action of progress
    _, sums = walk(fresh(), lambda s: optimal_action_targets(bank.next_state, bank.dist, s, target), 4)
    assert (sums["regret"] == 0).all() and (sums["distance"] >= 0).all()
    # a full turn in place: the potential difference sums to 0, the regret to 8 actions
    end, sums = walk(fresh(), lambda s: np.full(len(s), ROTATE_RIGHT), 8)
    assert (end == start).all() and (sums["distance"] == 0).all()
    np.testing.assert_allclose(sums["regret"], -8 * k, rtol=1e-6)  # terms are reported in float32
    # any walk of movement actions: K_r times the actions beyond the shortest path
    rng = np.random.default_rng(3)
    end, sums = walk(fresh(), lambda s: rng.integers(0, 5, len(s)), 20)
    d0, d1 = bank.dist[start, BOWL].astype(np.int64), bank.dist[end, BOWL].astype(np.int64)
    np.testing.assert_allclose(sums["regret"], -k * (20 - (d0 - d1)), rtol=1e-6)  # terms are reported in float32
    # Done is free; the searching stage is never charged
    r = fresh()
    done = np.full(n, DONE)
    _, terms = r.step(start, done, start, np.zeros(n, bool), np.ones(n, bool), np.zeros(n, bool), path)
    assert (terms["regret"] == 0).all()
    r = TSRMReward(bank, cfg)
    r.reset(np.ones(n, bool), scene, target, start, searching=~path)
    away = np.full(n, ROTATE_RIGHT)
    _, terms = r.step(start, away, bank.next_state[start, away].astype(np.int64), *[np.zeros(n, bool)] * 3, ~path)
    assert (terms["regret"] == 0).all()
    with pytest.raises(ValueError, match="k_regret"):
        RewardConfig(variant="tsrm-regret", k_regret=-1.0)


def test_failed_done_charges_a_done_that_fails_only():
    """``failed_done`` (issue 47, a deviation from the paper, 0 by default): a Done that fails is charged it in every
    variant, a Done that succeeds earns the success reward, any other action neither; batched, scalar and reference
    agree."""
    scenes = two_rooms()
    bank = SceneBank(scenes, cache=False)
    n = 6
    act = np.array([DONE, DONE, MOVE_AHEAD, ROTATE_RIGHT, DONE, MOVE_AHEAD])
    success = np.array([True, False, False, False, False, False])
    start = bank.offsets[np.zeros(n, int)] + np.arange(n)
    new = bank.next_state[start, act].astype(np.int64)
    for variant in ("tsrm", "sparse", "tsrm-regret"):
        for penalty, want in ((0.0, [5.0, 0, 0, 0, 0, 0]), (-1.5, [5.0, -1.5, 0, 0, -1.5, 0])):
            cfg = RewardConfig(variant=variant, failed_done=penalty)
            fast = TSRMReward(bank, cfg)
            searching = np.ones(n, bool)
            fast.reset(np.ones(n, bool), np.zeros(n, int), np.full(n, BOWL), start, searching=searching)
            _, terms = fast.step(start, act, new, np.zeros(n, bool), act == DONE, success, searching=searching)
            assert terms["success"].tolist() == want
            ref = TSRMRewardReference(scenes[0], cfg, confidence=np.zeros((scenes[0].num_states, NUM_CATEGORIES)))
            for i in range(n):
                ref.reset(BOWL, int(start[i]))
                _, tr = ref.step(int(start[i]), int(act[i]), int(new[i]), False, bool(act[i] == DONE), bool(success[i]))
                assert tr["success"] == want[i]
                one = TSRMReward(bank, cfg)
                one.reset_one(0, BOWL, int(start[i]), searching=True)
                _, t1 = one.step_one(
                    int(start[i]),
                    int(act[i]),
                    int(new[i]),
                    False,
                    bool(act[i] == DONE),
                    bool(success[i]),
                    searching=True,
                )
                assert t1["success"] == want[i]
    assert RewardConfig().failed_done == 0.0  # the paper's reward by default
    with pytest.raises(ValueError, match="failed_done"):
        RewardConfig(failed_done=0.5)
