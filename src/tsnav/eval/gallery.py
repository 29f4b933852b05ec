"""Per-step trajectories of evaluation episodes and the report's episode gallery.

The evaluation runner (:mod:`tsnav.eval.runner`) keeps only per-episode counts. For pictures we need the
states an agent went through, so :func:`record_trajectories` runs :func:`~tsnav.eval.runner.evaluate`
unchanged with the policy wrapped in a :class:`TrajectoryRecorder` that notes the observed state and the
returned action of every row at every step. The records are therefore exactly those of a plain evaluation
(same batches, same policy calls, same random draws), and each :class:`Trajectory` is consistent with its
record (``len(actions) == steps``; movement actions ``== path_length``).

A gallery item (:func:`write_gallery`) is two PNGs: the top-down map of :func:`tsnav.tsrm.plot.draw_episode`
(path coloured by stage, searched region, stage switch, target instances) and a strip of the agent's
first-person frames at key steps (start, mid-search, stage switch, mid-pathfinding, end), read from the
scene's ``images.hdf5`` or rendered when the scene has no stored images.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from ..atomic import atomic_save_figure, atomic_write_text
from ..constants import ACTION_ORDER, ACTIONS, CATEGORY_INDEX, DONE, OLD_ACTION_ORDER, action_permutation
from .metrics import EpisodeRecord
from .runner import EvalConfig, evaluate


@dataclass
class Trajectory:
    """The frames and actions of one evaluation episode (frames 0..T: the start frame, then one per action)."""

    episode: int
    """Index of the episode in its episode list (``EpisodeRecord.episode``)."""
    scene: str
    target: str
    keys: list[str]
    """State keys of the frames, start first (``len(actions) + 1`` entries)."""
    actions: list[int]
    """Action ids in the order of ``constants.ACTIONS``, Done included."""
    switch_frame: int = -1
    """First frame whose target confidence exceeded C_target (the pathfinding stage starts there), or -1."""
    success: bool = False
    action_order: str = ACTION_ORDER
    """The order ``actions`` are written in (``constants.ACTION_ORDER``); files without it are from the old order."""

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)


class TrajectoryRecorder:
    """A :class:`~tsnav.eval.policies.Policy` wrapper noting ``obs["state"]``, ``obs["active"]`` and the actions.

    Each ``reset`` whose mask is all True starts a new chunk (the runner resets once per chunk of episodes).
    """

    def __init__(self, policy):
        self.policy = policy
        self.chunks: list[dict[str, list[np.ndarray]]] = []

    def reset(self, mask: np.ndarray) -> None:
        mask = np.asarray(mask, dtype=bool)
        if mask.all():
            self.chunks.append({"state": [], "active": [], "action": []})
        self.policy.reset(mask)

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        a = np.asarray(self.policy.act(obs))
        c = self.chunks[-1]
        c["state"].append(np.asarray(obs["state"], dtype=np.int64).copy())
        c["active"].append(np.asarray(obs.get("active", np.ones(len(a), bool)), dtype=bool).copy())
        c["action"].append(a.astype(np.int64).copy())
        return a


def record_trajectories(bank, episodes, policy, config: EvalConfig | None = None
                        ) -> tuple[list[EpisodeRecord], list[Trajectory]]:
    """Evaluate ``policy`` on ``episodes`` (exactly like :func:`~tsnav.eval.runner.evaluate`) and return the
    records together with one :class:`Trajectory` per episode, in the same order."""
    config = config or EvalConfig()
    rec = TrajectoryRecorder(policy)
    records = evaluate(bank, episodes, rec, config)
    stage = bank.stage_confidence > config.c_target
    trajectories: list[Trajectory] = []
    lo = 0
    for chunk in rec.chunks:
        states = np.stack(chunk["state"]) if chunk["state"] else np.zeros((0, 0), np.int64)  # [T, B]
        active = np.stack(chunk["active"]) if chunk["active"] else np.zeros((0, 0), bool)
        actions = np.stack(chunk["action"]) if chunk["action"] else np.zeros((0, 0), np.int64)
        n = states.shape[1] if states.ndim == 2 and states.shape[0] else 0
        for j in range(n):
            r = records[lo + j]
            t = np.flatnonzero(active[:, j])
            s, a = states[t, j], actions[t, j]
            if len(s):
                final = int(bank.next_state[s[-1], a[-1]])
                frames = np.concatenate([s, [final]])
            else:
                frames = np.array([bank.global_state(bank.scene_index(r.scene), r.start)], dtype=np.int64)
            g = CATEGORY_INDEX[r.target]
            above = stage[frames, g]
            trajectories.append(Trajectory(
                episode=r.episode, scene=r.scene, target=r.target, keys=[str(k) for k in bank.keys[frames]],
                actions=[int(x) for x in a], switch_frame=int(np.argmax(above)) if above.any() else -1,
                success=bool(r.success)))
        lo += n
    if len(trajectories) != len(records):
        raise RuntimeError(f"recorded {len(trajectories)} trajectories for {len(records)} episodes")
    return records, trajectories


def write_trajectories(path: str | Path, trajectories: Sequence[Trajectory]) -> None:
    """JSON Lines, one trajectory per line, written atomically."""
    atomic_write_text(Path(path), "".join(t.to_json() + "\n" for t in trajectories))


def read_trajectories(path: str | Path) -> list[Trajectory]:
    """Trajectories of a JSON Lines file, action ids converted to ``constants.ACTIONS`` (lines without an
    ``action_order`` were written in ``constants.OLD_ACTION_ORDER``); ``ValueError`` naming the line otherwise."""
    out = []
    with open(path) as f:
        for i, line in enumerate(f, 1):
            if line.strip():
                try:
                    d = json.loads(line)
                    order = d.pop("action_order", OLD_ACTION_ORDER)
                    perm = action_permutation(order)
                    d["actions"] = [int(perm[a]) for a in d["actions"]]
                    out.append(Trajectory(**d))
                except (json.JSONDecodeError, TypeError, KeyError, IndexError, ValueError) as e:
                    raise ValueError(f"{path}:{i}: not a trajectory ({e})") from None
    return out


def select_episodes(records: Sequence[EpisodeRecord], n: int = 6, seed: int = 0) -> list[int]:
    """Indices (into ``records``) of about ``n`` episodes to show: half successes, half failures (whichever
    kind is short is filled with the other), preferring episodes with ``L* >= 5`` that switched stage, spread
    over scenes and targets. Deterministic."""
    rng = np.random.default_rng(seed)
    if n <= 0 or not records:
        return []

    def score(i: int) -> tuple:
        r = records[i]
        return (-(r.optimal_length >= 5), -bool(r.entered_pathfinding), rng.random())

    succ = sorted([i for i, r in enumerate(records) if r.success], key=score)
    fail = sorted([i for i, r in enumerate(records) if not r.success], key=score)

    def spread(pool: list[int], k: int) -> list[int]:
        chosen, seen = [], set()
        for i in pool:  # first pass: one per (scene, target)
            key = (records[i].scene, records[i].target)
            if key not in seen and len(chosen) < k:
                chosen.append(i)
                seen.add(key)
        for i in pool:
            if len(chosen) >= k:
                break
            if i not in chosen:
                chosen.append(i)
        return chosen

    k_s = min(len(succ), max(n - len(fail), (n + 1) // 2))
    k_f = min(len(fail), n - k_s)
    return spread(succ, k_s) + spread(fail, k_f)


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


def frame_images(scene, keys: Sequence[str]) -> np.ndarray:
    """``(K, H, W, 3)`` uint8 first-person frames of ``keys``: from ``images.hdf5`` when the scene has it,
    else rendered from ``scene.json`` (needs EGL); ``ValueError`` when neither is possible."""
    p = scene.images_path()
    if p is not None:
        import h5py

        with h5py.File(p, "r") as f:
            return np.stack([f[k][()] for k in keys]).astype(np.uint8)
    if "parts" not in scene.meta:
        raise ValueError(f"{scene.path}: no images.hdf5 and no render parts: no first-person frames")
    from ..world.show import render_views

    idx = scene.indices(list(keys))
    poses = np.stack([scene.x[idx], scene.z[idx], scene.rotation[idx], scene.horizon[idx]], 1).astype(np.float32)
    rgb, _, _ = render_views(scene, poses, size=scene.image_size or 128)
    return np.asarray(rgb, dtype=np.uint8)


def draw_frame_strip(frames: np.ndarray, labels: Sequence[str], path: str | Path, title: str = "") -> Path:
    """A PNG of ``frames`` side by side with one caption each."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

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


def write_gallery(bank, records: Sequence[EpisodeRecord], trajectories: Sequence[Trajectory], out_dir: str | Path,
                  n: int = 6, c_target: float = 0.7, prefix: str = "ep", relative_to: str | Path | None = None
                  ) -> list[GalleryItem]:
    """Pictures of about ``n`` selected episodes (:func:`select_episodes`) into ``out_dir``.

    ``records`` and ``trajectories`` are parallel lists (as from :func:`record_trajectories`); the map's stage
    colouring uses ``bank.stage_confidence`` and ``c_target`` like the evaluation. Picture paths in the items
    are relative to ``relative_to`` (default: the parent of ``out_dir``).
    """
    from ..tsrm.plot import draw_episode
    from ..tsrm.reward import RewardConfig

    out_dir = Path(out_dir)
    base = Path(relative_to) if relative_to is not None else out_dir.parent
    conf = bank.stage_confidence
    items = []
    for i in select_episodes(records, n):
        r, tr = records[i], trajectories[i]
        si = bank.scene_index(tr.scene)
        scene = bank.scenes[si]
        lo, hi = int(bank.offsets[si]), int(bank.offsets[si + 1])
        local = scene.indices(tr.keys)
        stem = f"{prefix}{r.episode:05d}"
        outcome = "success" if r.success else ("failure: wrong Done" if tr.actions and tr.actions[-1] == DONE
                                               else "failure: out of steps")
        title = (f"{tr.scene} ({r.room_type}), target {tr.target}: {outcome}; {r.path_length} moves, "
                 f"optimal {r.optimal_length}")
        map_png = draw_episode(scene, local, tr.target, out_dir / f"{stem}_map.png", confidence=conf[lo:hi],
                               config=RewardConfig(c_target=c_target), title=title)
        marks = key_frames(tr)
        labels = [f"{lab}, t={f}" + (f"\n{ACTIONS[tr.actions[f]]}" if f < len(tr.actions) else "")
                  for lab, f in marks]
        try:
            frames = frame_images(scene, [tr.keys[f] for _, f in marks])
            frames_png = draw_frame_strip(frames, labels, out_dir / f"{stem}_frames.png")
            frames_rel = str(Path(frames_png).relative_to(base))
        except (ValueError, OSError, RuntimeError, ImportError):
            frames_rel = ""
        sw = ("never" if tr.switch_frame < 0 else f"at step {tr.switch_frame}")
        caption = (f"Episode {r.episode}: {title}. Pathfinding stage entered {sw}; "
                   f"SPL term {(r.optimal_length / max(r.path_length, r.optimal_length, 1)) if r.success else 0:.2f}.")
        items.append(GalleryItem(str(Path(map_png).relative_to(base)), frames_rel, caption, bool(r.success),
                                 asdict(r)))
    return items
