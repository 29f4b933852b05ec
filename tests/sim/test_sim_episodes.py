"""Episodes: the training sampler's validity, fixed lists (JSON), and the ``tsnav episodes`` command."""

import json

import numpy as np
import pytest

from sim_helpers import toy_scenes, write_toy_dataset
from tsnav.cli import main
from tsnav.constants import CATEGORY_INDEX, NUM_CATEGORIES
from tsnav.sim.batch import SceneBank
from tsnav.sim.episodes import (
    EpisodeConfig,
    TrainingSampler,
    episodes_to_arrays,
    make_episodes,
    read_episodes,
    valid_starts,
    write_episodes,
)
from tsnav.sim.paths import UNREACHABLE


@pytest.fixture(scope="module")
def bank():
    return SceneBank(toy_scenes(), cache=False)


@pytest.mark.parametrize("horizon", [None, 0, 30])
def test_valid_starts_table_matches_brute_force(bank, horizon):
    t = valid_starts(bank, EpisodeConfig(start_horizon=horizon))
    got = set(
        zip(
            t.pair_scene[np.repeat(np.arange(len(t.counts)), t.counts)].tolist(),
            t.pair_target[np.repeat(np.arange(len(t.counts)), t.counts)].tolist(),
            t.starts.tolist(),
        )
    )
    expect = set()
    for s in range(bank.num_states):
        for c in range(NUM_CATEGORIES):
            if (
                (horizon is None or bank.horizon[s] == horizon)
                and bank.present[bank.scene_of[s], c]
                and not bank.success[s, c]
                and bank.dist[s, c] < UNREACHABLE
            ):
                expect.add((int(bank.scene_of[s]), c, s))
    # Vase is not a target category; all present categories belong to the room lists here.
    assert got == expect
    if horizon is None:  # the default: both horizons, as the lineage's test splits
        assert set(bank.horizon[t.starts].tolist()) == {0, 30}


def test_training_sampler_is_valid_and_covers(bank):
    sampler = TrainingSampler(bank)
    scene, target, start = sampler.sample(3000, np.random.default_rng(0))
    assert (bank.scene_of[start] == scene).all()
    assert 0.3 < (bank.horizon[start] == 30).mean() < 0.7  # both horizons, about half each
    assert not bank.success[start, target].any()
    assert (bank.dist[start, target] < UNREACHABLE).all()
    assert bank.present[scene, target].all()
    counts = np.bincount(scene, minlength=3)
    assert (np.abs(counts / 3000 - 1 / 3) < 0.05).all()  # scenes uniform
    a = target[scene == 0]
    assert abs(np.mean(a == CATEGORY_INDEX["Bowl"]) - 0.5) < 0.06  # targets uniform within a scene


def test_room_target_restriction():
    scenes = toy_scenes()
    scenes[1].meta["room_type"] = "bedroom"  # Sink is not a bedroom target; GarbageCan is
    b = SceneBank(scenes, cache=False)
    t = valid_starts(b)
    assert set(t.pair_target[t.pair_scene == 1].tolist()) == {CATEGORY_INDEX["GarbageCan"]}
    t2 = valid_starts(b, EpisodeConfig(room_targets=False))
    assert set(t2.pair_target[t2.pair_scene == 1].tolist()) == {CATEGORY_INDEX["GarbageCan"], CATEGORY_INDEX["Sink"]}


def test_fixed_episodes_round_trip(bank, tmp_path):
    eps = make_episodes(bank, per_room_type=40, seed=1)
    assert sum(e.room_type == "kitchen" for e in eps) == 40 and sum(e.room_type == "bathroom" for e in eps) == 40
    assert len({(e.scene, e.target, e.start) for e in eps}) == len(eps)
    assert make_episodes(bank, per_room_type=40, seed=1) == eps
    scene_idx, target, start = episodes_to_arrays(bank, eps)
    assert np.array_equal(bank.dist[start, target], [e.optimal_length for e in eps])
    assert (bank.dist[start, target] >= 1).all()
    assert abs((bank.horizon[start] == 30).mean() - 0.5) < 0.15  # each horizon 1/2 within a pair
    level = make_episodes(bank, per_room_type=40, seed=1, config=EpisodeConfig(start_horizon=0))
    assert {e.start.split("|")[3] for e in level} == {"0"}
    p = tmp_path / "test.json"
    write_episodes(p, eps, split="test", seed=1)
    eps2, meta = read_episodes(p)
    assert eps2 == eps and meta["split"] == "test" and meta["version"] == 1
    eps2[0].optimal_length += 1
    with pytest.raises(ValueError, match="episode 0 .*regenerate"):
        episodes_to_arrays(bank, eps2)
    # A small world yields fewer episodes than asked for.
    tiny = SceneBank([toy_scenes()[2]], cache=False)
    n_valid = len(valid_starts(tiny).starts)
    assert len(make_episodes(tiny, per_room_type=10**6)) == n_valid


def test_episodes_command(tmp_path, capsys):
    root = write_toy_dataset(tmp_path / "data")
    out = tmp_path / "eps" / "test.json"
    args = ["episodes", "--data", str(root), "--split", "test", "--per-room-type", "25", "--out", str(out)]
    assert main(args) == 0
    doc = json.loads(out.read_text())
    assert doc["format"] == "tsnav-episodes" and len(doc["episodes"]) == 50
    assert "wrote 50 episodes" in capsys.readouterr().out
    assert main(args) == 0 and "up to date" in capsys.readouterr().out
    before = out.read_text()
    assert main(args[:-2] + ["--out", str(out), "--seed", "9"]) == 2
    assert "--force" in capsys.readouterr().err and out.read_text() == before  # not destroyed
    assert main(["episodes", "--data", str(tmp_path / "nope"), "--out", str(out)]) == 2
    assert main(["episodes", "--data", str(root), "--split", "train", "--out", str(tmp_path / "x.json")]) == 2
    assert "no complete scenes" in capsys.readouterr().err


def test_room_target_mask_and_the_two_users_agree(tiny_world):
    """One definition of "which classes may be targets here": the episode sampler's per-scene mask and the
    detector quality report's (`detect.quality.scene_targets`) are the same."""
    from tsnav.constants import ROOM_TARGETS, room_target_mask
    from tsnav.detect.quality import scene_targets
    from tsnav.sim.episodes import EpisodeConfig, allowed_targets

    for rt, names in ROOM_TARGETS.items():
        m = room_target_mask(rt)
        assert m.dtype == bool and m.shape == (NUM_CATEGORIES,) and m.sum() == len(names)
        assert all(m[CATEGORY_INDEX[c]] for c in names)
    assert room_target_mask("garage").all()
    bank = SceneBank.from_root(tiny_world, "train")
    allowed = allowed_targets(bank, EpisodeConfig())
    for i, scene in enumerate(bank.scenes):
        assert np.array_equal(scene_targets(scene), allowed[i])
