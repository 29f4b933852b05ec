"""Episodes you can watch (issue 45 item 4): a clip has one frame per frame of the episode (steps + 1) at the
size of its two panels and text band; the path is drawn in the searching colour up to the stage switch and in the
pathfinding colour after it, the switch is marked where it happened; MP4 and GIF decode to the same frame count;
`tsnav eval --video N` writes N clips and their index; the report embeds the clips it writes."""

import json
import sys

import numpy as np
import pytest

from tsnav.cli import main
from tsnav.constants import CATEGORY_INDEX
from tsnav.eval.policies import make_policy
from tsnav.eval.runner import record_trajectories
from tsnav.eval.video import (
    BAND,
    PANEL,
    PATH_RGB,
    SEARCH_RGB,
    SWITCH_RGB,
    RoomMap,
    clip_frames,
    default_format,
    episode_clip,
    read_clip,
    read_video_index,
    segment_colors,
    write_clip,
)
from tsnav.sim.batch import SceneBank
from tsnav.sim.episodes import make_episodes, write_episodes
from tsnav.world.show import frame_images


@pytest.fixture(scope="module")
def rolled(tiny_scenes):
    """The explorer's episodes in the tiny world's test room (ground-truth stage switch) and the random policy's."""
    bank = SceneBank([s for s in tiny_scenes if s.meta.get("split") == "test"])
    episodes = make_episodes(bank, per_room_type=12, seed=0)
    records, trajectories = record_trajectories(bank, episodes, make_policy("explorer", bank))
    _, wandering = record_trajectories(bank, episodes, make_policy("random", bank, seed=1))
    return bank, episodes, records, trajectories + wandering


def _walk(bank, trajectories):
    """A recorded episode that moves often, and a stage-switch frame in its middle: a frame after the first move and
    before the last one whose state was not visited before (a confidence table above C_target at that state only
    then switches the episode exactly there)."""

    def positions(t):
        scene = bank.scenes[bank.scene_index(t.scene)]
        idx = scene.indices(t.keys)
        return scene, idx, np.stack([scene.x[idx], scene.z[idx]], 1)

    t = max(trajectories, key=lambda t: len(np.unique(positions(t)[2], axis=0)))
    scene, idx, pos = positions(t)
    moves = [k for k in range(1, len(idx)) if (pos[k] != pos[k - 1]).any()]
    sw = next(k for k in range(moves[0], moves[-1]) if idx[k] not in idx[:k])
    return t, scene, idx, sw


def _count(panel: np.ndarray, rgb) -> int:
    return int((panel == np.asarray(rgb, np.uint8)).all(-1).sum())


def test_clip_frames_one_per_frame_coloured_by_stage(rolled):
    bank, _, records, trajectories = rolled
    t, scene, states, sw = _walk(bank, trajectories)
    conf = np.zeros((scene.num_states, 22), np.float32)
    g = CATEGORY_INDEX[t.target]
    conf[states[sw], g] = 0.9  # the switch happens at frame sw, and only there
    views = frame_images(scene, t.keys)
    frames = clip_frames(scene, states, t.actions, t.target, conf, views, score_name="in frame")
    assert frames.shape == (len(t.actions) + 1, BAND + PANEL, 2 * PANEL, 3) and frames.dtype == np.uint8
    assert frames.shape[1] % 16 == 0 and frames.shape[2] % 16 == 0  # H.264 macroblocks, no rescaling
    # under the text band, the left panel is the agent's own frame, upscaled
    k = PANEL // views.shape[1]
    assert np.array_equal(frames[0, BAND + k // 2 :: k, k // 2 : PANEL : k], views[0])
    maps = frames[:, BAND:, PANEL:]
    # before the switch: searching colour only, no star; at the switch the star appears where the agent is
    assert all(_count(m, PATH_RGB) == 0 and _count(m, SWITCH_RGB) == 0 for m in maps[:sw])
    assert _count(maps[sw], SEARCH_RGB) > 0 and _count(maps[sw], PATH_RGB) == 0 and _count(maps[sw], SWITCH_RGB) > 0
    room = RoomMap(scene, t.target, np.stack([scene.x[states], scene.z[states]], 1))
    rows, cols = np.nonzero((maps[sw] == np.asarray(SWITCH_RGB, np.uint8)).all(-1))
    where = room.pixels(scene.x[states[sw]], scene.z[states[sw]])[0]
    assert abs(cols.mean() - where[0]) < 2.5 and abs(rows.mean() - where[1]) < 2.5
    # after it the path goes on in the pathfinding colour, and what was searched keeps its colour
    assert _count(maps[-1], PATH_RGB) > 0 and _count(maps[-1], SEARCH_RGB) > 0 and _count(maps[-1], SWITCH_RGB) > 0
    # the segment into frame t is searching up to the switch frame (as draw_episode draws the path)
    assert segment_colors(5, 2) == [SEARCH_RGB, SEARCH_RGB, PATH_RGB, PATH_RGB]
    assert segment_colors(3, -1) == [SEARCH_RGB, SEARCH_RGB]
    assert segment_colors(3, 0) == [PATH_RGB, PATH_RGB]
    # the switching frame has a gold border around the first-person view; no other frame has
    border = frames[:, BAND + 1, PANEL // 2]
    assert [tuple(b) == SWITCH_RGB for b in border] == [f == sw for f in range(len(frames))]
    with pytest.raises(ValueError, match="needs"):
        clip_frames(scene, states[:-1], t.actions, t.target, conf, views)


@pytest.mark.parametrize("fmt", ["mp4", "gif"])
def test_written_clip_decodes_to_steps_plus_one_frames(tmp_path, rolled, fmt):
    bank, _, records, trajectories = rolled
    r, t = next((r, t) for r, t in zip(records, trajectories) if t.switch_frame > 0)
    path = episode_clip(bank, t, tmp_path / f"clip.{fmt}")
    frames = read_clip(path)
    assert frames.shape == (r.steps + 1, PANEL + BAND, 2 * PANEL, 3)
    assert not list(tmp_path.glob(".*"))  # written atomically: no temporary file left
    # the decoded switch frame still shows the gold star near where the raw frame has it (lossy for MP4)
    gold = np.abs(frames[t.switch_frame, BAND:, PANEL:].astype(int) - SWITCH_RGB).sum(-1) < 60
    assert gold.sum() > 20


def test_write_clip_refuses_bad_input(tmp_path):
    with pytest.raises(ValueError, match="one of mp4, gif"):
        write_clip(np.zeros((2, 8, 8, 3), np.uint8), tmp_path / "x.avi")
    with pytest.raises(ValueError, match=r"\(T, H, W, 3\)"):
        write_clip(np.zeros((8, 8, 3), np.uint8), tmp_path / "x.gif")
    with pytest.raises(ValueError, match="even frame size"):
        write_clip(np.zeros((2, 9, 8, 3), np.uint8), tmp_path / "x.mp4")
    assert not list(tmp_path.iterdir())


def test_gif_without_imageio_ffmpeg(monkeypatch):
    assert default_format() == "mp4"
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # import fails as if it were not installed
    assert default_format() == "gif"


def test_eval_video_writes_n_clips_and_report_embeds_clips(tmp_path, tiny_world, rolled, capsys):
    _, episodes, _, _ = rolled
    ep_file = tmp_path / "episodes.json"
    write_episodes(ep_file, episodes, split="test", success_distance=1.0)
    out = tmp_path / "work" / "eval"
    assert (
        main(
            [
                "eval",
                "--data",
                str(tiny_world),
                "--episodes",
                str(ep_file),
                "--policy",
                "explorer",
                "--out",
                str(out),
                "--video",
                "3",
            ]
        )
        == 0
    )
    assert "wrote 3 clips into" in capsys.readouterr().out
    clips = read_video_index(out)
    assert len(clips) == 3 and len({c.episode for c in clips}) == 3
    recs = {json.loads(line)["episode"]: json.loads(line) for line in (out / "records.jsonl").read_text().splitlines()}
    for c in clips:
        assert (out / "videos" / c.file).suffix == ".mp4"
        assert len(read_clip(out / "videos" / c.file)) == c.frames == recs[c.episode]["steps"] + 1
    # asking again for fewer replaces the clips
    assert (
        main(
            [
                "eval",
                "--data",
                str(tiny_world),
                "--episodes",
                str(ep_file),
                "--policy",
                "explorer",
                "--out",
                str(out),
                "--video",
                "1",
            ]
        )
        == 0
    )
    assert len(list((out / "videos").glob("*.mp4"))) == 1 == len(read_video_index(out))
    assert (
        main(["eval", "--data", str(tiny_world), "--episodes", str(ep_file), "--out", str(out), "--video", "-1"]) == 2
    )
    assert "--video must be >= 0" in capsys.readouterr().err

    from tsnav.report.html import build_report

    index = build_report(tmp_path / "work", gallery=3, video=2)
    text = index.read_text()
    srcs = [s.split("'")[0] for s in text.split("<video src='")[1:]]
    assert len(srcs) == 2 and all((index.parent / s).is_file() for s in srcs)
    assert "videos" not in {p.name for p in (index.parent).iterdir()}  # the eval's own clips are not scanned
    assert build_report(tmp_path / "work", gallery=3, video=0).read_text().count("<video") == 0
    assert not list(index.parent.rglob("*.mp4"))  # the report's old clips went with its old galleries


def test_report_command_video_flag(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["report", str(tmp_path / "empty"), "--video", "-1"]) == 2
    assert "--video must be >= 0" in capsys.readouterr().err
