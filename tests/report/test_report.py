"""Report and gallery: recorded trajectories agree with the evaluation records, the HTML page is self-contained
(relative links to PNGs that exist, no scripts or external assets) and shows every kind of folder."""

import json
from html.parser import HTMLParser

import numpy as np
import pytest
from PIL import Image

from tsnav.cli import main
from tsnav.constants import CATEGORY_INDEX, DONE
from tsnav.report.gallery import key_frames, select_episodes
from tsnav.eval.runner import read_trajectories, record_trajectories, write_trajectories
from tsnav.metrics import EpisodeRecord, read_records
from tsnav.eval.policies import make_policy
from tsnav.report.html import build_report, plot_learning_curves, scan
from tsnav.eval.runner import EvalConfig, evaluate
from tsnav.sim.batch import SceneBank
from tsnav.sim.episodes import make_episodes, write_episodes


@pytest.fixture(scope="module")
def bank(tiny_scenes):
    return SceneBank([s for s in tiny_scenes if s.meta.get("split") == "test"])


@pytest.fixture(scope="module")
def episodes(bank):
    return make_episodes(bank, per_room_type=12, seed=0)


@pytest.mark.parametrize("name", ["explorer", "random"])
def test_recorded_trajectories_match_records(bank, episodes, name):
    config = EvalConfig(batch_size=5)  # several chunks
    recs, trajs = record_trajectories(bank, episodes, make_policy(name, bank, seed=3), config)
    assert recs == evaluate(bank, episodes, make_policy(name, bank, seed=3), config)
    stage = bank.stage_mask
    for r, t in zip(recs, trajs):
        assert (t.scene, t.target, t.episode, t.keys[0]) == (r.scene, r.target, r.episode, r.start)
        assert len(t.actions) == r.steps and len(t.keys) == r.steps + 1
        assert sum(a != DONE for a in t.actions) == r.path_length
        si = bank.scene_index(t.scene)
        ids = bank.offsets[si] + bank.scenes[si].indices(t.keys)
        # consecutive frames follow the graph
        assert all(bank.next_state[ids[k], t.actions[k]] == ids[k + 1] for k in range(len(t.actions)))
        assert t.switch_frame == (r.pathfinding_start_step if r.entered_pathfinding else -1)
        if r.entered_pathfinding:
            assert stage[ids[t.switch_frame], CATEGORY_INDEX[t.target]]
        if r.success:
            assert t.actions[-1] == DONE and bank.success[ids[-1], CATEGORY_INDEX[t.target]]


def test_trajectory_roundtrip_and_key_frames(tmp_path, bank, episodes):
    _, trajs = record_trajectories(bank, episodes[:4], make_policy("explorer", bank))
    write_trajectories(tmp_path / "t.jsonl", trajs)
    assert read_trajectories(tmp_path / "t.jsonl") == trajs
    for t in trajs:
        marks = key_frames(t)
        frames = [f for _, f in marks]
        assert frames[0] == 0 and frames == sorted(set(frames)) and frames[-1] == len(t.keys) - 1 or len(t.keys) == 1
        if t.switch_frame > 0:
            assert t.switch_frame in frames


def test_select_episodes_mixes_outcomes():
    recs = [
        EpisodeRecord(
            success=i % 3 == 0, path_length=10, optimal_length=3 + i % 4, scene=f"S{i % 2}", target="Bowl", episode=i
        )
        for i in range(30)
    ]
    pick = select_episodes(recs, 6)
    assert len(pick) == 6 and len(set(pick)) == 6
    assert sum(recs[i].success for i in pick) == 3
    assert select_episodes(recs[:1], 6) == [0]
    assert select_episodes([], 6) == []


class _Links(HTMLParser):
    def __init__(self):
        super().__init__()
        self.srcs, self.tags = [], []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        d = dict(attrs)
        for k in ("src", "href"):
            if d.get(k):
                self.srcs.append(d[k])


def _fake_train_run(d, n=12):
    d.mkdir(parents=True)
    (d / "config.json").write_text(
        json.dumps({"format": "tsnav-train-run", "train": {"reward": "tsrm", "features": "x", "algo": "batched"}})
    )
    rng = np.random.default_rng(0)
    with open(d / "log.jsonl", "w") as f:
        for u in range(1, n + 1):
            f.write(
                json.dumps(
                    {
                        "update": u,
                        "env_steps": 480 * u,
                        "episodes": 10 * u,
                        "seconds": u,
                        "return": -0.3 + u / 10,
                        "reward/explore": 0.1 * u,
                        "reward/slack": -0.3,
                        "SR": u / n,
                        "SPL": u / (2 * n),
                        "SSR": 0.9,
                        "SSSPL": 0.5,
                        "NSNPL": 0.4,
                        "policy_loss": rng.normal(),
                        "value_loss": 1 / u,
                        "entropy": 1.7,
                    }
                )
                + "\n"
            )
        f.write('{"update": 13, "env_st')  # a torn last line is ignored


def test_learning_curves_png(tmp_path):
    _fake_train_run(tmp_path / "run")
    from tsnav.rl.logger import read_log

    log = read_log(tmp_path / "run")
    assert len(log) == 12
    p = plot_learning_curves(log, tmp_path / "c.png", "t")
    img = np.asarray(Image.open(p).convert("RGB"))
    assert img.shape[1] > 900 and len(np.unique(img.reshape(-1, 3), axis=0)) > 20
    assert plot_learning_curves([], tmp_path / "none.png") is None


def test_report_end_to_end(tmp_path, tiny_world, episodes):
    ep_file = tmp_path / "episodes.json"
    write_episodes(ep_file, episodes, split="test", success_distance=1.0)
    root = tmp_path / "work"
    for p in ("explorer", "random"):
        assert (
            main(
                [
                    "eval",
                    "--data",
                    str(tiny_world),
                    "--episodes",
                    str(ep_file),
                    "--policy",
                    p,
                    "--seed",
                    "1",
                    "--out",
                    str(root / "evals" / p),
                ]
            )
            == 0
        )
    _fake_train_run(root / "runs" / "agent")
    pre = root / "pretrain"
    pre.mkdir()
    (pre / "config.json").write_text(json.dumps({"pretrain": {"method": "demae", "model": "vit_tiny"}, "model": {}}))
    Image.fromarray(np.full((20, 50, 3), 128, np.uint8)).save(pre / "recon.png")
    found = scan(root)
    assert len(found.evals) == 2 and len(found.train_runs) == 1 and len(found.pretrain_runs) == 1

    index = build_report(root, gallery=3)
    assert index == root / "report" / "index.html"
    text = index.read_text()
    links = _Links()
    links.feed(text)
    assert "script" not in links.tags and "link" not in links.tags
    assert "http" not in text.lower().replace("http-equiv", "")
    imgs = [s for s in links.srcs if not s.startswith("#")]
    assert len(imgs) >= 2 + 1 + 2 * 3 * 2 - 2  # curves, recon, maps and frame strips of two galleries
    for s in imgs:
        assert not s.startswith("/") and ".." not in s
        assert (index.parent / s).is_file(), s
    for word in ("Results", "Training", "Pretraining", "Episode gallery", "SSSPL", "L&gt;=5"):
        assert word in text
    # the random policy's gallery was re-rolled and agrees with its records
    rr = read_records(root / "evals" / "random" / "records.jsonl")
    tr = read_trajectories(root / "evals" / "random" / "trajectories.jsonl")
    assert [len(t.actions) for t in tr] == [r.steps for r in rr]
    # a second report replaces the first
    assert build_report(root, gallery=0) == index and "Episode gallery" not in index.read_text()


def test_report_command_errors(tmp_path, capsys):
    assert main(["report", str(tmp_path / "missing")]) == 2
    assert "no such folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["report", str(tmp_path / "empty")]) == 2
    assert "nothing to report" in capsys.readouterr().err


def test_report_rerolls_a_trained_agent(tmp_path, tiny_world, episodes):
    """`tsnav eval --run` keeps no trajectories: the report re-rolls the agent (sampled actions, same seed) and
    gets the very same episodes."""
    from rl_helpers import StandInTrainer
    from tsnav.agent import agent_config
    from tsnav.pipeline.steps import ensure_oracle_detections
    from tsnav.pretrain.pixels import cache_pixel_features
    from tsnav.rl.config import TrainConfig

    cache_pixel_features(tiny_world, "report_px", grid=4)
    ensure_oracle_detections(tiny_world, "oracle")  # the agent reads a named detection table
    run = tmp_path / "work" / "run"
    StandInTrainer()(
        TrainConfig(data=str(tiny_world), features="report_px", detections="oracle", device="cpu"),
        agent_config("cpu"),
        run,
    )
    ep_file = tmp_path / "episodes.json"
    write_episodes(ep_file, episodes, split="test", success_distance=1.0)
    ev = tmp_path / "work" / "eval_agent"
    assert (
        main(
            [
                "eval",
                "--data",
                str(tiny_world),
                "--episodes",
                str(ep_file),
                "--run",
                str(run),
                "--seed",
                "4",
                "--out",
                str(ev),
            ]
        )
        == 0
    )
    index = build_report(tmp_path / "work", gallery=2)
    assert (ev / "trajectories.jsonl").exists()  # re-rolled, and equal to the records (checked while writing)
    text = index.read_text()
    assert "no gallery" not in text and text.count("_map.png") == 2


def test_pretrain_progress_is_read_progress_without_torch(tmp_path):
    """The report reads a pretraining run's progress through checkpoint_layout.read_progress (the one reader,
    also pretrain.train's), torch-free; a broken or missing file gives an empty entry, not an error."""
    import subprocess
    import sys

    from tsnav.checkpoint_layout import read_progress
    from tsnav.report.html import _pretrain_progress
    from tsnav.pretrain import train

    assert train.read_progress is read_progress
    run = tmp_path / "run"
    run.mkdir()
    assert _pretrain_progress(run) == {} and read_progress(run) is None
    (run / "progress.json").write_text('{"step": 3, "loss": 0.5}')
    assert _pretrain_progress(run) == read_progress(run) == {"step": 3, "loss": 0.5}
    for step, text in ((4, '{"step": 4, "total_steps": 9}'), (5, '{"step": 5, "tot')):
        ck = run / "checkpoints" / f"ckpt_{step:09d}"
        ck.mkdir(parents=True)
        (ck / "state.json").write_text(text)
    assert _pretrain_progress(run) == read_progress(run) == {"step": 4, "total_steps": 9}  # newest broken: skipped
    (run / "checkpoints" / "ckpt_000000004" / "state.json").write_text("[]")
    (run / "progress.json").write_text("{")
    assert _pretrain_progress(run) == {}
    code = "import sys, tsnav.report.html, tsnav.checkpoint_layout; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
