"""TSRM reward: collision rule, stage switch, variants, agreement with the per-episode paper reference."""

import numpy as np
import pytest

from sim_helpers import StagedReward
from tsnav.constants import (
    CATEGORY_INDEX,
    DONE,
    LOOK_DOWN,
    LOOK_UP,
    MOVE_AHEAD,
    NUM_CATEGORIES,
    ROTATE_LEFT,
    ROTATE_RIGHT,
)
from tsnav.data.toy import toy_scene
from tsnav.sim.batch import BatchEnv, RewardFn, SceneBank
from tsnav.tsrm.distance import bank_pose_distance
from tsnav.tsrm.reward import (
    PATHFINDING,
    SEARCHING,
    TERMS,
    VARIANT_TERMS,
    VARIANTS,
    RewardConfig,
    TSRMReward,
    TSRMRewardReference,
)

BOWL = CATEGORY_INDEX["Bowl"]
CHAIR = CATEGORY_INDEX["Chair"]


def room():
    return toy_scene(4.0, 3.0, objects={"Bowl|1": (4.0, 3.0), "Chair|1": (0.5, 2.5)}, blocked=[(2.0, 1.0), (2.0, 1.25)])


def run(reward, scene, start, target, actions):
    """Step one episode (row 0 of a batch of 1) through ``actions``; returns per-step rewards and terms."""
    reward = reward if isinstance(reward, StagedReward) else StagedReward(reward)  # the stage an env would hand in
    reward.reset(np.ones(1, bool), np.zeros(1, int), np.array([target]), np.array([start]))
    s = start
    out = []
    for a in actions:
        n = int(scene.next_state[s, a])
        r, terms = reward.step(
            np.array([s]),
            np.array([a]),
            np.array([n]),
            np.array([n == s and a == MOVE_AHEAD]),
            np.array([a == DONE]),
            np.array([False]),
        )
        out.append((float(r[0]), {k: float(v[0]) for k, v in terms.items()}))
        s = n
    return out


def test_protocol_and_config_errors():
    bank = SceneBank([room()], cache=False)
    assert isinstance(TSRMReward(bank), RewardFn)
    with pytest.raises(ValueError, match="unknown reward variant 'full'"):
        RewardConfig(variant="full")
    with pytest.raises(ValueError, match="c_target"):
        SceneBank([room()], cache=False, c_target=1.5)  # C_target's one home below the user's configs
    with pytest.raises(ValueError, match="confidence must have shape"):
        StagedReward(TSRMReward(bank), confidence=np.zeros((3, NUM_CATEGORIES)))
    assert RewardConfig(area={"sample_size": 1 / 64}).area.sample_size == 1 / 64  # from saved JSON


def test_collision_rule():
    sc = room()
    bank = SceneBank([sc], cache=False)
    rew = TSRMReward(bank, RewardConfig(variant="baseline"))
    start = sc.index("0.00|0.00|180|0")  # facing the wall
    steps = run(
        rew, sc, start, BOWL, [MOVE_AHEAD, MOVE_AHEAD, LOOK_DOWN, MOVE_AHEAD, ROTATE_RIGHT, MOVE_AHEAD, MOVE_AHEAD]
    )
    col = [t["collision"] for _, t in steps]
    # first bump free; again at the same pose -0.1; looking down keeps the pose (horizon is not part of it);
    # at a new rotation (225) the first bump is free again
    assert col == pytest.approx([0.0, -0.1, 0.0, -0.1, 0.0, 0.0, -0.1])
    assert all(t["slack"] == pytest.approx(-0.01) for _, t in steps)
    # a new episode forgets the collisions
    again = run(rew, sc, start, BOWL, [MOVE_AHEAD])
    assert again[0][1]["collision"] == 0.0


def test_failed_looks_are_not_collisions():
    """LookUp at horizon 0 and LookDown at 30 fail (lastActionSuccess False, no graph edge) but bump into
    nothing: the env flags them ``failed``, not ``collided``, so the collision penalty never applies to them,
    however often they repeat at one pose; a repeated MoveAhead into the wall is penalised."""
    sc = room()
    bank = SceneBank([sc], cache=False)
    rew = TSRMReward(bank, RewardConfig(variant="tsrm"))
    env = BatchEnv(bank, 1, max_steps=100, autoreset=False, reward_fn=rew)
    start = sc.index("0.00|0.00|180|0")  # level, facing the wall
    env.reset(episodes=(np.zeros(1, int), np.array([BOWL]), np.array([start])))
    seq = [
        (LOOK_UP, True, False),
        (LOOK_UP, True, False),
        (LOOK_DOWN, False, False),
        (LOOK_DOWN, True, False),
        (LOOK_DOWN, True, False),
        (MOVE_AHEAD, True, True),
        (MOVE_AHEAD, True, True),
    ]
    col = []
    for a, failed, collided in seq:
        _, _, _, _, info = env.step(np.array([a]))
        assert bool(info["failed"][0]) == failed and bool(info["collided"][0]) == collided
        col.append(float(info["reward_terms"]["collision"][0]))
    assert col == pytest.approx([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -0.1])


def test_stage_switch_is_irreversible_and_switching_step_explores():
    sc = room()
    bank = SceneBank([sc], cache=False)
    conf = np.zeros((sc.num_states, NUM_CATEGORIES), np.float32)
    seen = sc.index("1.00|1.00|0|0")
    conf[seen, BOWL] = 0.9
    conf[sc.index("1.00|1.00|315|0"), BOWL] = 0.7  # not above C_target = 0.7
    rew = StagedReward(TSRMReward(bank, RewardConfig()), confidence=conf)
    start = sc.index("1.00|1.00|270|0")
    steps = run(rew, sc, start, BOWL, [ROTATE_RIGHT, ROTATE_RIGHT, MOVE_AHEAD, ROTATE_LEFT, MOVE_AHEAD])
    # steps 1, 2 are taken in the searching stage (step 2 reaches the switching frame); the rest pathfinding
    assert [t["explore"] > 0 for _, t in steps[:2]] == [True, True]
    assert all(t["distance"] == 0 for _, t in steps[:2])
    assert all(t["explore"] == 0 for _, t in steps[2:])
    assert any(t["distance"] != 0 for _, t in steps[2:])
    assert rew.stage[0] == PATHFINDING and rew.switch_step[0] == 2  # stays after the target left the view
    # the start frame counts: an episode starting at the switching frame is in pathfinding from the start
    first = run(rew, sc, seen, BOWL, [ROTATE_RIGHT])
    assert rew.switch_step[0] == 0 and first[0][1]["explore"] == 0 and first[0][1]["distance"] != 0
    # another target never switches here
    run(rew, sc, start, CHAIR, [MOVE_AHEAD, MOVE_AHEAD])
    assert rew.stage[0] == SEARCHING and rew.switch_step[0] == -1


def test_distance_reward_telescopes():
    sc = room()
    bank = SceneBank([sc], cache=False)
    conf = np.ones((sc.num_states, NUM_CATEGORIES), np.float32)  # pathfinding from the start frame
    cfg = RewardConfig()
    rew = StagedReward(TSRMReward(bank, cfg), confidence=conf)
    d = bank_pose_distance(bank)[:, BOWL]
    rng = np.random.default_rng(0)
    acts = rng.choice(5, 40)
    start = sc.index("0.50|0.50|270|0")
    steps = run(rew, sc, start, BOWL, acts)
    end = start
    for a in acts:
        end = sc.next_state[end, a]
    total = sum(t["distance"] for _, t in steps)
    assert total == pytest.approx(cfg.k_distance * (int(d[start]) - int(d[end])), abs=1e-5)


def test_distance_increase_scale_charges_the_long_way_round():
    """With the paper's symmetric term a turn the long way (six lefts) earns what the short way (two rights) does;
    with ``distance_increase_scale`` each step that moves away costs ``(scale - 1) * K_d`` more, and a shortest
    path keeps its full reward."""
    sc = room()
    bank = SceneBank([sc], cache=False)
    conf = np.ones((sc.num_states, NUM_CATEGORIES), np.float32)  # pathfinding from the start frame
    d = bank_pose_distance(bank)[:, BOWL]
    start = sc.index("3.00|0.00|270|0")  # facing -x; the bowl at (4, 3) is best faced at 0 (+z)
    short, long_ = [ROTATE_RIGHT] * 2, [ROTATE_LEFT] * 6  # 270 -> 315 -> 0, or 270 -> 225 -> ... -> 0

    def end(acts):
        s = start
        for a in acts:
            s = sc.next_state[s, a]
        return s

    assert end(short) == end(long_) and d[end(short)] == d[start] - 2
    assert d[sc.next_state[start, ROTATE_LEFT]] == d[start] + 1  # the first left moves away, the rest come back
    k = RewardConfig().k_distance
    with pytest.raises(ValueError, match="distance_increase_scale"):
        RewardConfig(distance_increase_scale=-1.0)
    for scale in (1.0, 2.0):
        cfg = RewardConfig(distance_increase_scale=scale)
        got = {}
        for name, acts in (("short", short), ("long", long_)):
            steps = run(StagedReward(TSRMReward(bank, cfg), confidence=conf), sc, start, BOWL, acts)
            got[name] = sum(t["distance"] for _, t in steps)
            ref = TSRMRewardReference(sc, cfg, confidence=conf)
            ref.reset(BOWL, start)
            s, total = start, 0.0
            for a in acts:
                n = int(sc.next_state[s, a])
                total += ref.step(s, a, n, False, False, False)[1]["distance"]
                s = n
            assert total == pytest.approx(got[name], abs=1e-6)
        assert got["short"] == pytest.approx(2 * k, abs=1e-6)
        assert got["long"] == pytest.approx(2 * k - (scale - 1.0) * k, abs=1e-6)  # one step of increase


def test_success_and_done():
    sc = room()
    bank = SceneBank([sc], cache=False)
    rew = StagedReward(TSRMReward(bank))
    rew.reset(np.ones(2, bool), np.zeros(2, int), np.array([BOWL, BOWL]), np.array([0, 1]))
    r, terms = rew.step(
        np.array([0, 1]),
        np.array([DONE, DONE]),
        np.array([0, 1]),
        np.zeros(2, bool),
        np.ones(2, bool),
        np.array([True, False]),
    )
    assert terms["success"].tolist() == [5.0, 0.0]
    assert r == pytest.approx(np.array([5.0 - 0.01, -0.01]) + terms["distance"] + terms["explore"])
    assert terms["explore"].tolist() == [0.0, 0.0]  # Done adds no view


def test_each_variant_switches_off_exactly_its_terms():
    sc = room()
    bank = SceneBank([sc], cache=False)
    # down to the wall, bump twice, turn until the bowl is in view, walk towards it, then Done
    acts = (
        [MOVE_AHEAD] * 6
        + [ROTATE_LEFT, ROTATE_LEFT]
        + [MOVE_AHEAD] * 3
        + [ROTATE_LEFT]
        + [MOVE_AHEAD] * 3
        + [ROTATE_RIGHT, MOVE_AHEAD, LOOK_DOWN, DONE]
    )
    start = sc.index("1.00|1.00|180|0")
    full = run(TSRMReward(bank, RewardConfig(variant="tsrm-regret")), sc, start, BOWL, acts)  # every term
    sums = {k: sum(abs(t[k]) for _, t in full) for k in TERMS}
    assert all(v > 0 for k, v in sums.items() if k != "success")  # the walk exercises every shaping term
    for variant in VARIANTS:
        steps = run(TSRMReward(bank, RewardConfig(variant=variant)), sc, start, BOWL, acts)
        for (r, t), (_, tf) in zip(steps, full):
            for k in TERMS:
                assert t[k] == (tf[k] if k in VARIANT_TERMS[variant] else 0.0)
            assert r == pytest.approx(sum(t.values()), abs=1e-6)


@pytest.mark.parametrize("variant,scale", [("tsrm", 1.0), ("baseline", 1.0), ("tsrm", 2.5)])
def test_fast_matches_reference_on_random_walks(variant, scale):
    a = room()
    b = toy_scene(3.0, 2.0, objects={"Bowl|1": (0.0, 2.0), "Chair|1": (3.0, 0.0)}, name="B")
    scenes = [a, b]
    bank = SceneBank(scenes, cache=False)
    rng = np.random.default_rng(7)
    conf = rng.uniform(0, 0.75, (bank.num_states, NUM_CATEGORIES)).astype(np.float32)  # ~7% of frames switch
    cfg = RewardConfig(variant=variant, distance_increase_scale=scale)
    fast = StagedReward(TSRMReward(bank, cfg), confidence=conf)
    n = 12
    scene_idx = np.arange(n) % 2
    target = rng.choice([BOWL, CHAIR], n)
    local = np.array([rng.integers(0, scenes[s].num_states) for s in scene_idx])
    off = bank.offsets[scene_idx]
    fast.reset(np.ones(n, bool), scene_idx, target, local + off)
    refs = []
    for i in range(n):
        sc = scenes[scene_idx[i]]
        o = int(off[i])
        refs.append(TSRMRewardReference(sc, cfg, confidence=conf[o : o + sc.num_states]))
        refs[-1].reset(target[i], local[i])
    explore_fast = np.zeros(n)
    explore_ref = np.zeros(n)
    increases = 0  # pathfinding steps that moved away from the target (where distance_increase_scale acts)
    for _ in range(30):
        act = rng.choice(6, n, p=[0.5, 0.15, 0.15, 0.08, 0.08, 0.04])
        new = bank.next_state[local + off, act].astype(np.int64)
        collided = (new == local + off) & (act == MOVE_AHEAD)
        done = act == DONE
        success = done & bank.success[new, target]
        r, terms = fast.step(local + off, act, new, collided, done, success)
        for i in range(n):
            rr, tr = refs[i].step(
                int(local[i]), int(act[i]), int(new[i] - off[i]), bool(collided[i]), bool(done[i]), bool(success[i])
            )
            for k in TERMS:
                tol = 0.1 * 0.03 if k == "explore" else 1e-6  # explore: K_e x 0.03 m^2 per step
                assert terms[k][i] == pytest.approx(tr[k], abs=tol), k
            assert r[i] == pytest.approx(rr, abs=0.1 * 0.03 + 1e-5)
            explore_ref[i] += tr["explore"]
            increases += tr["distance"] < 0
        explore_fast += terms["explore"]
        assert fast.stage.tolist() == [int(x.pathfinding) for x in refs]
        assert fast.switch_step.tolist() == [x.switch_step for x in refs]
        local = new - off
    # whole episodes: exploration within 1% (plus two samples' area)
    assert np.all(np.abs(explore_fast - explore_ref) <= 0.01 * explore_ref + 0.1 * 2 / 32**2)
    if variant == "tsrm":
        assert explore_ref.sum() > 1.0
        assert increases > 0  # the walks exercise the scaled branch


def test_exact_area_option_equals_reference():
    sc = room()
    bank = SceneBank([sc], cache=False)
    acts = np.random.default_rng(5).choice(5, 20)
    start = sc.index("2.50|0.50|0|0")
    exact = run(TSRMReward(bank, RewardConfig(exact_area=True)), sc, start, CHAIR, acts)
    ref = TSRMRewardReference(sc, RewardConfig())
    ref.reset(CHAIR, start)
    s = start
    for (r, t), a in zip(exact, acts):
        n = int(sc.next_state[s, a])
        rr, tr = ref.step(s, int(a), n, n == s, False, False)
        assert r == pytest.approx(rr, abs=1e-6)
        s = n


def test_inside_batch_env_with_autoreset():
    a = room()
    bank = SceneBank([a], cache=False)
    rew = TSRMReward(bank)

    class Sampler:
        def sample(self, n, rng):
            return np.zeros(n, np.int64), np.full(n, BOWL, np.int64), rng.integers(0, bank.num_states, n)

    env = BatchEnv(bank, 8, Sampler(), reward_fn=rew, max_steps=10, seed=0)
    env.reset()
    rng = np.random.default_rng(0)
    for _ in range(25):
        obs, r, term, trunc, info = env.step(rng.choice(6, 8, p=[0.4, 0.2, 0.2, 0.05, 0.05, 0.1]))
        assert r.dtype == np.float32 and set(info["reward_terms"]) == set(TERMS)
        assert np.allclose(r, sum(info["reward_terms"].values()), atol=1e-5)
        # rows that just restarted have step 0 and a fresh stage of their new start frame
        fresh = term | trunc
        assert (env.steps[fresh] == 0).all()
        assert (env.stage.stage[fresh] == bank.stage_mask[obs["state"][fresh], BOWL]).all()
    assert (rew.searched_area >= 0).all()
