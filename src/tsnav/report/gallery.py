"""The report's episode gallery, drawn from the trajectories an evaluation recorded
(:func:`tsnav.eval.runner.record_trajectories`).

A gallery item (:func:`write_gallery`) is two PNGs: the top-down map of :func:`tsnav.tsrm.plot.draw_episode`
(path coloured by stage, searched region, stage switch, target instances) and a strip of the agent's
first-person frames at key steps (start, mid-search, stage switch, mid-pathfinding, end), read from the
scene's ``images.hdf5`` or rendered when the scene has no stored images; the first ``videos`` items also get
a clip of the whole episode (:mod:`tsnav.eval.video`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..atomic import atomic_save_figure
from ..constants import ACTIONS, C_TARGET, DONE
from ..tsrm.plot import draw_episode
from ..world.show import frame_images
from ..metrics import EpisodeRecord
from ..eval.outcomes import select_episodes
from ..eval.runner import Trajectory
from ..eval.video import default_format, episode_clip


def key_frames(traj: Trajectory) -> list[tuple[str, int]]:
    """(label, frame index) pairs: start, mid-search, stage switch, mid-pathfinding, end (no duplicates)."""
    last = len(traj.keys) - 1
    marks: list[tuple[str, int]] = [("start", 0)]
    sw = traj.switch_frame
    if sw > 0:
        if sw >= 4:
            marks.append(("searching", sw // 2))
        marks.append(("stage switch", sw))
        if last - sw >= 4:
            marks.append(("pathfinding", (sw + last) // 2))
    elif sw == 0:
        marks[0] = ("start = switch", 0)
        if last >= 4:
            marks.append(("pathfinding", last // 2))
    elif last >= 4:
        marks.append(("searching", last // 2))
    if last > 0:
        marks.append(("end" + (" (Done)" if traj.actions and traj.actions[-1] == DONE else ""), last))
    out, seen = [], set()
    for lab, f in marks:
        if f not in seen:
            out.append((lab, f))
            seen.add(f)
    return out


def draw_frame_strip(frames: np.ndarray, labels: Sequence[str], path: str | Path, title: str = "") -> Path:
    """A PNG of ``frames`` side by side with one caption each."""
    k = len(frames)
    fig = Figure(figsize=(1.9 * k, 2.35), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, k, squeeze=False)[0]
    for ax, img, lab in zip(axes, frames, labels):
        ax.imshow(img, interpolation="nearest")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(lab, fontsize=8)
    if title:
        fig.suptitle(title, fontsize=8)
    return atomic_save_figure(fig, path, dpi=100)


@dataclass
class GalleryItem:
    """One episode of the gallery: its pictures (paths relative to the gallery folder's parent) and a caption."""

    map_png: str
    frames_png: str
    caption: str
    success: bool
    record: dict = field(default_factory=dict)
    clip: str = ""
    """The episode's clip (MP4 or GIF, :mod:`tsnav.eval.video`), or "" when none was written."""


def write_gallery(
    bank,
    records: Sequence[EpisodeRecord],
    trajectories: Sequence[Trajectory],
    out_dir: str | Path,
    n: int = 6,
    c_target: float = C_TARGET,
    prefix: str = "ep",
    relative_to: str | Path | None = None,
    videos: int = 0,
) -> list[GalleryItem]:
    """Pictures of about ``n`` selected episodes (:func:`select_episodes`) into ``out_dir``.

    ``records`` and ``trajectories`` are parallel lists (as from :func:`record_trajectories`); the map's stage
    colouring uses ``bank.stage_confidence`` and ``c_target`` like the evaluation. Picture paths in the items
    are relative to ``relative_to`` (default: the parent of ``out_dir``). The first ``videos`` items also get a
    clip of the whole episode (:func:`tsnav.eval.video.episode_clip`, :func:`~tsnav.eval.video.default_format`).
    """
    out_dir = Path(out_dir)
    base = Path(relative_to) if relative_to is not None else out_dir.parent
    conf = bank.stage_confidence
    items = []
    fmt = default_format()
    for i in select_episodes(records, n):
        r, tr = records[i], trajectories[i]
        si = bank.scene_index(tr.scene)
        scene = bank.scenes[si]
        lo, hi = int(bank.offsets[si]), int(bank.offsets[si + 1])
        local = scene.indices(tr.keys)
        stem = f"{prefix}{r.episode:05d}"
        outcome = (
            "success"
            if r.success
            else ("failure: wrong Done" if tr.actions and tr.actions[-1] == DONE else "failure: out of steps")
        )
        title = (
            f"{tr.scene} ({r.room_type}), target {tr.target}: {outcome}; {r.path_length} moves, "
            f"optimal {r.optimal_length}"
        )
        map_png = draw_episode(
            scene, local, tr.target, out_dir / f"{stem}_map.png", confidence=conf[lo:hi], c_target=c_target, title=title
        )
        marks = key_frames(tr)
        labels = [f"{lab}, t={f}" + (f"\n{ACTIONS[tr.actions[f]]}" if f < len(tr.actions) else "") for lab, f in marks]
        try:
            frames = frame_images(scene, [tr.keys[f] for _, f in marks])
            frames_png = draw_frame_strip(frames, labels, out_dir / f"{stem}_frames.png")
            frames_rel = str(Path(frames_png).relative_to(base))
        except (ValueError, OSError, RuntimeError, ImportError):
            frames_rel = ""
        sw = "never" if tr.switch_frame < 0 else f"at step {tr.switch_frame}"
        caption = (
            f"Episode {r.episode}: {title}. Pathfinding stage entered {sw}; "
            f"SPL term {(r.optimal_length / max(r.path_length, r.optimal_length, 1)) if r.success else 0:.2f}."
        )
        clip = ""
        if len(items) < videos:
            try:
                clip = str(episode_clip(bank, tr, out_dir / f"{stem}.{fmt}", c_target).relative_to(base))
            except (ValueError, OSError, RuntimeError, ImportError):
                clip = ""
        items.append(
            GalleryItem(str(Path(map_png).relative_to(base)), frames_rel, caption, bool(r.success), asdict(r), clip)
        )
    return items
