"""Episodes you can watch: one clip per evaluation episode, made from the trajectories an evaluation recorded
(:func:`tsnav.eval.runner.record_trajectories`).

Every frame of a clip is one frame of the episode (frames 0..T: the start frame, then one per action, so a clip of
an episode of ``T`` steps has ``T + 1`` frames):

* a text band on top: scene, target, step ``t`` of ``T``; the action taken at this frame and the stage it is in;
  the target's score (the detector's, or ground truth "in frame" without a detector) against C_target; on the last
  frame, how the episode ended (it is on top because a player's controls cover a clip's bottom);
* left, the agent's first-person frame (``images.hdf5``, or rendered), with a gold border on the switching frame;
* right, the top-down map: floor, furniture, the target's instances (green X), the start (square), the path so far
  coloured by stage (blue: searching, red: pathfinding; paper III-B), the stage switch (gold star) from the frame
  it happened on, the agent and its heading.

The stage of a frame is the evaluation's rule (:func:`tsnav.sim.stage.switch_frame` on the bank's
``stage_confidence`` at the evaluation's C_target), so the clip and the episode's record agree on where the switch
happened; the path's segment into frame ``t`` is drawn in the searching colour up to the switch frame and in the
pathfinding colour after it, as :func:`tsnav.tsrm.plot.draw_episode` draws the whole path.

Clips are MP4 (H.264, ``yuv420p``: what browsers play) through the ffmpeg binary that the ``imageio-ffmpeg``
package ships, or animated GIF through Pillow (:func:`write_clip`; the format follows the file's suffix;
:func:`default_format` is MP4 when ``imageio-ffmpeg`` is installed). Files are written atomically.
``tsnav eval --video N`` writes N clips into ``OUT/videos/`` with ``videos/index.json``; ``tsnav report --video N``
embeds N clips per gallery (:mod:`tsnav.report.gallery`).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path
from typing import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure
from matplotlib.patches import Polygon as MplPolygon
from PIL import Image, ImageDraw, ImageFont

from ..atomic import atomic_path, atomic_write_json
from ..constants import ACTIONS, C_TARGET, CATEGORY_INDEX, TARGET_CATEGORIES
from ..metrics import EpisodeRecord
from ..sim.stage import switch_frame
from ..tsrm.area import scene_floor
from ..tsrm.plot import PATH_COLOR, SEARCH_COLOR
from ..world.show import frame_images
from .outcomes import episode_ending, select_episodes

#: Folder of the clips in an evaluation folder (``tsnav eval --video N``).
VIDEO_DIR = "videos"
#: Side of the two square panels (first-person frame, map), pixels.
PANEL = 256
#: Height of the text band above the panels, pixels (panels + band: a multiple of 16, as H.264 wants).
BAND = 64
#: Frames per second of a clip (a 100-step episode lasts 25 s).
FPS = 4
#: Clip formats by file suffix.
FORMATS = ("mp4", "gif")

SEARCH_RGB = tuple(int(255 * c) for c in to_rgb(SEARCH_COLOR))
PATH_RGB = tuple(int(255 * c) for c in to_rgb(PATH_COLOR))
SWITCH_RGB = (255, 200, 0)
TARGET_RGB = (44, 160, 44)


def default_format() -> str:
    """``mp4`` when ``imageio-ffmpeg`` (which ships an ffmpeg binary) is installed, else ``gif``."""
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        return "gif"
    return "mp4"


@lru_cache(maxsize=4)
def _font(size: int, bold: bool = False) -> ImageFont.FreeTypeFont:
    """DejaVu Sans, the font matplotlib ships (so no system font is needed)."""
    from matplotlib import font_manager

    path = font_manager.findfont(font_manager.FontProperties(family="DejaVu Sans", weight="bold" if bold else "normal"))
    return ImageFont.truetype(path, size)


class RoomMap:
    """The static part of the map panel of one room (floor, furniture, the target's instances), drawn once with
    matplotlib, and the transform from room metres (x, z) to panel pixels (column, row; +z is up)."""

    def __init__(self, scene, target: str, points: np.ndarray, size: int = PANEL):
        floor = scene_floor(scene)
        x0, z0, x1, z1 = floor.bounds
        xs = np.concatenate([[x0, x1], points[:, 0]])
        zs = np.concatenate([[z0, z1], points[:, 1]])
        half = max(xs.max() - xs.min(), zs.max() - zs.min()) / 2 + 0.3
        cx, cz = (xs.max() + xs.min()) / 2, (zs.max() + zs.min()) / 2
        self.lo, self.scale, self.size = np.array([cx - half, cz + half]), size / (2 * half), size
        fig = Figure(figsize=(size / 100, size / 100), dpi=100)
        canvas = FigureCanvasAgg(fig)
        ax = fig.add_axes((0, 0, 1, 1))
        ax.set_axis_off()
        ax.set_xlim(cx - half, cx + half)
        ax.set_ylim(cz - half, cz + half)
        for poly in getattr(floor, "geoms", [floor]):
            if hasattr(poly, "exterior") and not poly.is_empty:
                ax.add_patch(
                    MplPolygon(
                        np.asarray(poly.exterior.coords),
                        closed=True,
                        facecolor="#f3efe6",
                        edgecolor="#444",
                        lw=1.2,
                        zorder=0,
                    )
                )
        for f in scene.meta.get("furniture", []):
            if "footprint" in f and f.get("blocks", True):
                ax.add_patch(
                    MplPolygon(
                        np.asarray(f["footprint"]),
                        closed=True,
                        facecolor="#b9aa94",
                        edgecolor="#6b5d49",
                        lw=0.6,
                        zorder=1,
                    )
                )
        objs = [
            o
            for o in scene.meta.get("objects", [])
            if o.get("objectType", str(o.get("objectId", "")).split("|")[0]) == target and "position" in o
        ]
        if objs:
            ax.scatter(
                [o["position"]["x"] for o in objs],
                [o["position"]["z"] for o in objs],
                marker="X",
                s=70,
                color=np.array(TARGET_RGB) / 255,
                edgecolors="k",
                linewidths=0.6,
                zorder=3,
            )
        canvas.draw()
        self.image = np.asarray(canvas.buffer_rgba())[..., :3].copy()  # [size, size, 3]

    def pixels(self, x, z) -> np.ndarray:
        """``(N, 2)`` panel pixels (column, row) of room points."""
        x, z = np.atleast_1d(np.asarray(x, np.float64)), np.atleast_1d(np.asarray(z, np.float64))
        return np.stack([(x - self.lo[0]) * self.scale, (self.lo[1] - z) * self.scale], 1)


def segment_colors(num_frames: int, switch: int) -> list[tuple[int, int, int]]:
    """Colour of the path's segment into frame ``t`` (index ``t - 1`` of the list, ``t`` = 1..T): searching up to
    and including the switch frame, pathfinding after it (``switch`` -1: searching throughout)."""
    return [SEARCH_RGB if switch < 0 or t <= switch else PATH_RGB for t in range(1, num_frames)]


def clip_frames(
    scene,
    states: Sequence[int],
    actions: Sequence[int],
    target: str | int,
    confidence: np.ndarray,
    views: np.ndarray,
    c_target: float = C_TARGET,
    score_name: str = "detector score",
    ending: str | None = None,
) -> np.ndarray:
    """``(T + 1, BAND + PANEL, 2 * PANEL, 3)`` uint8 frames of one episode of ``scene``: the text band on top, the
    first-person frame (left) and the map (right) under it.

    ``states``: scene-local state ids of the frames, start first (``T + 1``); ``actions``: the ``T`` actions
    (``constants.ACTIONS`` order); ``confidence``: ``(S, 22)`` target confidence per scene-local state, the
    stage-switch input; ``views``: ``(T + 1, H, W, 3)`` first-person frames; ``score_name`` names what the
    confidence is; ``ending``: how the episode ended, written on the last frame."""
    states = np.asarray(states, dtype=np.int64)
    g = CATEGORY_INDEX[target] if isinstance(target, str) else int(target)
    name = TARGET_CATEGORIES[g]
    n = len(states)
    if n == 0 or len(actions) != n - 1 or len(views) != n:
        raise ValueError(
            f"an episode of {len(actions)} actions needs {len(actions) + 1} states and views, got {n} and {len(views)}"
        )
    score = np.asarray(confidence)[states, g].astype(np.float64)
    switch = switch_frame(score, c_target)
    px, pz = scene.x[states].astype(np.float64), scene.z[states].astype(np.float64)
    room = RoomMap(scene, name, np.stack([px, pz], 1))
    pts = room.pixels(px, pz)
    colors = segment_colors(n, switch)
    big, small = _font(15, bold=True), _font(13)
    out = np.empty((n, PANEL + BAND, 2 * PANEL, 3), np.uint8)
    for t in range(n):
        img = Image.new("RGB", (2 * PANEL, PANEL + BAND), (255, 255, 255))
        view = Image.fromarray(np.ascontiguousarray(views[t])).resize((PANEL, PANEL), Image.NEAREST)
        img.paste(view, (0, BAND))
        img.paste(Image.fromarray(room.image), (PANEL, BAND))
        d = ImageDraw.Draw(img)
        c0, r0 = PANEL + pts[0][0], BAND + pts[0][1]
        d.rectangle([c0 - 4, r0 - 4, c0 + 4, r0 + 4], outline=(0, 0, 0), width=2)  # the start
        for k in range(1, t + 1):  # the path so far, segment by segment in its stage's colour
            (ca, ra), (cb, rb) = pts[k - 1], pts[k]
            d.line([(PANEL + ca, BAND + ra), (PANEL + cb, BAND + rb)], fill=colors[k - 1], width=3)
        c, r = PANEL + pts[t][0], BAND + pts[t][1]
        rad = np.deg2rad(scene.rotation[states[t]])
        d.line([(c, r), (c + 14 * np.sin(rad), r - 14 * np.cos(rad))], fill=(0, 0, 0), width=3)  # heading
        d.ellipse([c - 5, r - 5, c + 5, r + 5], fill=(255, 255, 255), outline=(0, 0, 0), width=2)
        if 0 <= switch <= t:  # the stage switch, from the frame it happened on
            _star(d, PANEL + pts[switch][0], BAND + pts[switch][1], 9, SWITCH_RGB)
        searching = switch < 0 or t < switch
        if t == switch:
            d.rectangle([0, BAND, PANEL - 1, BAND + PANEL - 1], outline=SWITCH_RGB, width=5)
        # the text band above the panels (a player's controls cover a clip's bottom): where, what the agent
        # did, what the detector said and which stage that makes
        act = ACTIONS[int(actions[t])] if t < n - 1 else f"end: {ending}" if ending else "end"
        stage = "searching" if searching else ("pathfinding (switched here)" if t == switch else "pathfinding")
        d.text((8, 4), f"{scene.name}  target {name}  step {t}/{n - 1}", font=big, fill=(20, 20, 20))
        d.text((8, 24), f"action: {act}", font=small, fill=(20, 20, 20))
        d.rectangle([PANEL + 8, 26, PANEL + 20, 38], fill=SEARCH_RGB if searching else PATH_RGB)
        d.text((PANEL + 26, 24), f"stage: {stage}", font=small, fill=(20, 20, 20))
        d.text(
            (8, 43),
            f"{score_name} of {name}: {score[t]:.2f} {'>' if score[t] > c_target else '<='} C_target {c_target:g}",
            font=small,
            fill=(20, 20, 20),
        )
        out[t] = np.asarray(img)
    return out


def _star(d: ImageDraw.ImageDraw, c: float, r: float, radius: float, fill) -> None:
    ang = np.deg2rad(np.arange(10) * 36 - 90)
    rad = np.where(np.arange(10) % 2 == 0, radius, radius * 0.45)
    d.polygon([(c + a * np.cos(b), r + a * np.sin(b)) for a, b in zip(rad, ang)], fill=fill, outline=(0, 0, 0))


def write_clip(frames: np.ndarray, path: str | Path, fps: float = FPS) -> Path:
    """Write ``(T, H, W, 3)`` uint8 frames as a clip, atomically; the format follows the suffix: ``.mp4`` (H.264
    through imageio-ffmpeg's ffmpeg; ``H`` and ``W`` even) or ``.gif`` (Pillow). Returns the path."""
    path = Path(path)
    frames = np.asarray(frames, dtype=np.uint8)
    if frames.ndim != 4 or frames.shape[-1] != 3 or len(frames) == 0:
        raise ValueError(f"clip frames must be (T, H, W, 3) with T >= 1, got {frames.shape}")
    fmt = path.suffix.lstrip(".").lower()
    if fmt not in FORMATS:
        raise ValueError(f"{path}: clip format must be one of {', '.join(FORMATS)}")
    with atomic_path(path) as tmp:
        if fmt == "gif":
            imgs = [Image.fromarray(f) for f in frames]
            imgs[0].save(
                tmp,
                format="GIF",
                save_all=True,
                append_images=imgs[1:],
                duration=int(round(1000 / fps)),
                loop=0,
                optimize=False,
                disposal=1,
            )
        else:
            import imageio_ffmpeg

            h, w = frames.shape[1:3]
            if h % 2 or w % 2:
                raise ValueError(f"H.264 needs an even frame size, got {w}x{h}")
            writer = imageio_ffmpeg.write_frames(
                str(tmp),
                (w, h),
                fps=fps,
                codec="libx264",
                macro_block_size=2,
                pix_fmt_in="rgb24",
                pix_fmt_out="yuv420p",
                quality=None,
                output_params=["-crf", "20", "-movflags", "+faststart", "-f", "mp4"],
            )
            writer.send(None)
            for f in frames:
                writer.send(np.ascontiguousarray(f).tobytes())
            writer.close()
    return path


def read_clip(path: str | Path) -> np.ndarray:
    """``(T, H, W, 3)`` uint8 frames of a clip written by :func:`write_clip` (decoded; MP4 frames are lossy)."""
    path = Path(path)
    if path.suffix.lower() == ".gif":
        with Image.open(path) as im:
            out = []
            for k in range(im.n_frames):
                im.seek(k)
                out.append(np.asarray(im.convert("RGB")))
            return np.stack(out)
    import imageio_ffmpeg

    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    w, h = meta["size"]
    return np.stack([np.frombuffer(b, np.uint8).reshape(h, w, 3) for b in gen])


@dataclass
class Clip:
    """One clip of an evaluation: its file (relative to the folder it is listed in), episode and outcome."""

    file: str
    episode: int
    frames: int
    switch_frame: int
    success: bool
    caption: str


def episode_clip(bank, trajectory, path: str | Path, c_target: float = C_TARGET, fps: float = FPS) -> Path:
    """Write the clip of one recorded episode (``trajectory`` of :func:`~tsnav.eval.runner.record_trajectories`)
    to ``path``; the stage follows ``bank.stage_confidence`` at ``c_target``, as in the evaluation."""
    si = bank.scene_index(trajectory.scene)
    scene = bank.scenes[si]
    lo, hi = int(bank.offsets[si]), int(bank.offsets[si + 1])
    states = scene.indices(trajectory.keys)
    score_name = "detector score" if bank.confidence is not None else "in frame (ground truth)"
    frames = clip_frames(
        scene,
        states,
        trajectory.actions,
        trajectory.target,
        bank.stage_confidence[lo:hi],
        frame_images(scene, trajectory.keys),
        c_target=c_target,
        score_name=score_name,
        ending=episode_ending(trajectory),
    )
    return write_clip(frames, path, fps)


def write_videos(
    bank,
    records: Sequence[EpisodeRecord],
    trajectories: Sequence,
    out_dir: str | Path,
    n: int,
    c_target: float = C_TARGET,
    fmt: str | None = None,
    relative_to: str | Path | None = None,
) -> list[Clip]:
    """Clips of about ``n`` episodes (:func:`~tsnav.eval.outcomes.select_episodes`: successes and failures) into
    ``out_dir`` as ``ep<episode>.<fmt>`` (default :func:`default_format`). ``records`` and ``trajectories`` are
    parallel lists. File names in the returned items are relative to ``relative_to`` (default ``out_dir``)."""
    fmt = fmt or default_format()
    if fmt not in FORMATS:
        raise ValueError(f"clip format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    out_dir = Path(out_dir)
    base = Path(relative_to) if relative_to is not None else out_dir
    clips = []
    for i in select_episodes(records, n):
        r, tr = records[i], trajectories[i]
        path = episode_clip(bank, tr, out_dir / f"ep{r.episode:05d}.{fmt}", c_target)
        sw = "never" if tr.switch_frame < 0 else f"at step {tr.switch_frame}"
        caption = (
            f"Episode {r.episode}: {tr.scene} ({r.room_type}), target {tr.target}: {episode_ending(tr)} after "
            f"{r.steps} steps, {r.path_length} moves (optimal {r.optimal_length}); pathfinding stage entered {sw}."
        )
        clips.append(
            Clip(
                str(path.relative_to(base)),
                int(r.episode),
                len(tr.keys),
                int(tr.switch_frame),
                bool(r.success),
                caption,
            )
        )
    return clips


def write_evaluation_videos(
    out_dir: str | Path, bank, records, trajectories, n: int, c_target: float = C_TARGET, fmt: str | None = None
) -> list[Clip]:
    """``tsnav eval --video N``: the clips of :func:`write_videos` in ``out_dir/videos/`` (clips of an earlier call
    removed first) and their list ``videos/index.json``."""
    folder = Path(out_dir) / VIDEO_DIR
    if folder.is_dir():
        for old in folder.iterdir():
            if old.suffix.lstrip(".") in FORMATS:
                old.unlink()
    clips = write_videos(bank, records, trajectories, folder, n, c_target, fmt)
    atomic_write_json(folder / "index.json", {"fps": FPS, "clips": [asdict(c) for c in clips]})
    return clips


def read_video_index(out_dir: str | Path) -> list[Clip]:
    """The clips ``tsnav eval --video`` listed in ``out_dir/videos/index.json`` ([] when there is none)."""
    p = Path(out_dir) / VIDEO_DIR / "index.json"
    if not p.exists():
        return []
    return [Clip(**c) for c in json.loads(p.read_text())["clips"]]
