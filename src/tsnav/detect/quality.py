"""What the stage switch needs from a detector, measured on a set of scenes (paper III-B, Fig. 4).

The paper switches from searching to pathfinding when the detector's confidence for the target passes
``C_target`` (0.7). Two things decide whether a learned detector can drive that switch, besides the AP and
calibration of :mod:`tsnav.detect.evaluate`:

* *reach*: of the (scene, target) pairs an episode can ask for (classes with an instance in the scene and in
  its room type's target list, ``constants.ROOM_TARGETS``), the share where some state of the scene has the
  target's confidence above ``C_target``; without one, the agent can never switch in that pair. Every state
  of a scene is reachable (the dataset keeps the largest strongly connected set of positions). Reported
  both for any state (what the switch sees) and for states where the target is really in view. Some of these
  pairs no episode can ask for: the target is never in view within the success distance from a reachable
  state (inside a closed receptacle, or behind a wall of the rebuilt room), so the episode sampler leaves them
  out. *Episode reach* is the same share over the pairs with a success state, the ones episodes do ask for;
* *false positives*: the share of states where a class *not* in view scores above 0.5 / 0.7 / 0.9 (any of
  the 22 classes; and only the scene's possible targets, the false switches an episode can suffer), and
  the same per (state, class) pair.

:func:`reliability_figure` draws the reliability diagram of a :class:`~tsnav.detect.evaluate.Reliability`
table, :func:`detection_gallery` a grid of frames with the detector's boxes next to the ground truth.

    python -m tsnav.detect.quality --data DIR --name learned --split val --out DIR/detectors/quality
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle
from tqdm import tqdm

from ..atomic import atomic_save_figure, atomic_write_json
from ..constants import C_TARGET, DEFAULT_CLASS_SET, SUCCESS_DISTANCE, class_set as get_class_set
from ..data.detections import Detections, load_detections
from ..data.reader import list_scenes, load_scene
from .data import read_images
from .evaluate import average_precision, box_iou, evaluate_detections
from .oracle import ground_truth

#: Score thresholds at which false positives are counted.
FP_THRESHOLDS = (0.5, 0.7, 0.9)

#: Size buckets of :func:`subset_ap`: the target's visible pixels as a share of the frame (upper bounds; at
#: 128x128: small < 82 px, about 9x9; medium < 492 px, about 22x22; large the rest).
SIZE_BUCKETS = (("small", 0.005), ("medium", 0.03), ("large", float("inf")))

#: The lineage's visibility distance (AI2-THOR's ``visibilityDistance``, metres): the "near" figure counts a
#: class as in view only when its instance is within this distance.
NEAR_DISTANCE = 1.5


def scene_targets(scene) -> np.ndarray:
    """``(C,)`` bool: classes an episode in ``scene`` can target (an instance in the scene and in the room
    type's target list of its class set; every present class when the room type is unknown)."""
    mask = np.zeros(scene.num_categories, bool)
    mask[scene.categories_present()] = True
    return mask & scene.class_set.room_target_mask(scene.room_type)


@dataclass
class SwitchReport:
    """Reach and false positives of a detector over a set of scenes (module docstring).

    Attributes:
        c_target: the switch threshold used for reach.
        pairs: (scene, target) pairs; reached: of them, with some state above ``c_target``; reached_in_view:
            with some state above ``c_target`` where the target is in view.
        class_pairs, class_reached: ``(C,)`` the same per class (of ``class_set``).
        episode_pairs: pairs with a success state (target in view within ``SUCCESS_DISTANCE``), the pairs
            episodes ask for; episode_reached: of them, with some state above ``c_target``.
        fp_state_any: ``{t: share of states where some class not in view scores > t}``.
        fp_state_target: the same over the scene's possible targets only.
        fp_pair_any: ``{t: share of (state, class) pairs not in view with score > t}``.
        fp_pair_target: the same over the scene's possible targets only.
        states: states evaluated; scenes: their names.
    """

    c_target: float
    pairs: int
    reached: int
    reached_in_view: int
    class_pairs: np.ndarray
    class_reached: np.ndarray
    fp_state_any: dict
    fp_state_target: dict
    fp_pair_any: dict
    fp_pair_target: dict
    states: int = 0
    scenes: list = field(default_factory=list)
    episode_pairs: int = 0
    episode_reached: int = 0
    class_set: str = DEFAULT_CLASS_SET

    @property
    def reach(self) -> float:
        return self.reached / self.pairs if self.pairs else float("nan")

    @property
    def episode_reach(self) -> float:
        return self.episode_reached / self.episode_pairs if self.episode_pairs else float("nan")

    def to_json(self) -> dict:
        return {
            "c_target": self.c_target,
            "pairs": self.pairs,
            "reached": self.reached,
            "reached_in_view": self.reached_in_view,
            "reach": self.reach,
            "episode_pairs": self.episode_pairs,
            "episode_reached": self.episode_reached,
            "episode_reach": self.episode_reach,
            "classes": {
                c: {"pairs": int(self.class_pairs[i]), "reached": int(self.class_reached[i])}
                for i, c in enumerate(get_class_set(self.class_set).categories)
                if self.class_pairs[i]
            },
            "false_positives": {
                "state_any": _keys(self.fp_state_any),
                "state_target": _keys(self.fp_state_target),
                "pair_any": _keys(self.fp_pair_any),
                "pair_target": _keys(self.fp_pair_target),
            },
            "states": self.states,
            "scenes": self.scenes,
        }

    def format(self) -> str:
        lines = [
            f"{len(self.scenes)} scenes, {self.states} states",
            f"(scene, target) pairs reaching confidence > {self.c_target:g}: {self.reached} / {self.pairs} "
            f"({100 * self.reach:.1f} %); with the target in view: {self.reached_in_view}",
            f"of the pairs episodes ask for (a success state exists): {self.episode_reached} / "
            f"{self.episode_pairs} ({100 * self.episode_reach:.1f} %)",
            "false positives (class not in view scores above t):",
            f"{'t':>5} {'states, any class':>18} {'states, scene targets':>22} {'pairs, any':>11} "
            f"{'pairs, targets':>15}",
        ]
        for t in sorted(self.fp_state_any):
            lines.append(
                f"{t:5.2f} {100 * self.fp_state_any[t]:17.2f}% {100 * self.fp_state_target[t]:21.2f}% "
                f"{100 * self.fp_pair_any[t]:10.3f}% {100 * self.fp_pair_target[t]:14.3f}%"
            )
        return "\n".join(lines)


def _keys(d: dict) -> dict:
    return {f"{k:g}": float(v) for k, v in d.items()}


def switch_report(
    scenes: Sequence,
    detections: Sequence[Detections],
    c_target: float = C_TARGET,
    thresholds: Sequence[float] = FP_THRESHOLDS,
) -> SwitchReport:
    """Reach and false positives (module docstring) of per-scene tables ``detections`` aligned with
    ``scenes``."""
    if len(scenes) != len(detections):
        raise ValueError(f"{len(scenes)} scenes but {len(detections)} detection tables")
    if not scenes:
        raise ValueError("nothing to evaluate: no scenes")
    classes = scenes[0].class_set
    class_pairs = np.zeros(classes.size, np.int64)
    class_reached = np.zeros(classes.size, np.int64)
    in_view_reached = 0
    episode_pairs = episode_reached = 0
    n_states = 0
    fp_s_any = {t: 0 for t in thresholds}
    fp_s_tgt = {t: 0 for t in thresholds}
    fp_p_any = {t: 0 for t in thresholds}
    fp_p_tgt = {t: 0 for t in thresholds}
    neg_any = neg_tgt = 0
    for s, d in zip(scenes, detections):
        if len(d.keys) != len(s.keys) or not (d.keys == s.keys).all():
            raise ValueError(f"detections of scene {s.name} do not match its states")
        present = ground_truth(s).present  # (S, C)
        tgt = scene_targets(s)
        above = d.scores > c_target
        class_pairs += tgt
        class_reached += tgt & above.any(axis=0)
        in_view_reached += int((tgt & (above & present).any(axis=0)).sum())
        askable = tgt & s.category_visible_within(SUCCESS_DISTANCE).any(axis=0)
        episode_pairs += int(askable.sum())
        episode_reached += int((askable & above.any(axis=0)).sum())
        n_states += len(present)
        absent = ~present
        neg_any += int(absent.sum())
        neg_tgt += int((absent & tgt).sum())
        for t in thresholds:
            fp = (d.scores > t) & absent
            fp_s_any[t] += int(fp.any(axis=1).sum())
            fp_s_tgt[t] += int((fp & tgt).any(axis=1).sum())
            fp_p_any[t] += int(fp.sum())
            fp_p_tgt[t] += int((fp & tgt).sum())

    def share(x: int, n: int) -> float:
        return x / n if n else float("nan")

    return SwitchReport(
        c_target=c_target,
        pairs=int(class_pairs.sum()),
        reached=int(class_reached.sum()),
        reached_in_view=in_view_reached,
        class_pairs=class_pairs,
        class_reached=class_reached,
        fp_state_any={t: share(v, n_states) for t, v in fp_s_any.items()},
        fp_state_target={t: share(v, n_states) for t, v in fp_s_tgt.items()},
        fp_pair_any={t: share(v, neg_any) for t, v in fp_p_any.items()},
        fp_pair_target={t: share(v, neg_tgt) for t, v in fp_p_tgt.items()},
        states=n_states,
        scenes=[s.name for s in scenes],
        episode_pairs=episode_pairs,
        episode_reached=episode_reached,
        class_set=classes.name,
    )


def subset_ap(scores: np.ndarray, present: np.ndarray, subset: np.ndarray) -> np.ndarray:
    """``(C,)`` presence AP per class counting only the in-view (state, class) pairs of ``subset`` as
    positives: in-view pairs outside it are left out (neither positive nor negative), pairs not in view are the
    negatives (COCO's area ranges, applied to presence). NaN for a class without positives in ``subset``."""
    out = np.full(present.shape[1], np.nan)
    for c in range(present.shape[1]):
        keep = ~present[:, c] | subset[:, c]
        pos = present[keep, c] & subset[keep, c]
        if pos.any():
            out[c] = average_precision(scores[keep, c], pos)
    return out


def subset_report(scenes: Sequence, detections: Sequence[Detections]) -> dict:
    """Presence AP by the target's size in the frame (:data:`SIZE_BUCKETS`) and for targets within
    :data:`NEAR_DISTANCE` (an AI2-THOR-style figure, reported beside the issue's definition, never instead):
    ``{bucket: {"mean_presence_ap", "positives", "classes": {class: AP}}}``."""
    scores, present, pixels, distance = [], [], [], []
    for s, d in zip(scenes, detections):
        gt = ground_truth(s)
        scores.append(d.scores)
        present.append(gt.present)
        pixels.append(gt.pixels / float(s.image_size**2))
        distance.append(gt.distance)
    scores, present = np.concatenate(scores), np.concatenate(present)
    share, distance = np.concatenate(pixels), np.concatenate(distance)
    subsets, lo = {}, 0.0
    for name, hi in SIZE_BUCKETS:
        subsets[name] = (share >= lo) & (share < hi)
        lo = hi
    subsets[f"within {NEAR_DISTANCE:g} m"] = np.nan_to_num(distance, nan=np.inf) <= NEAR_DISTANCE
    out = {}
    for name, sub in subsets.items():
        ap = subset_ap(scores, present, sub)
        out[name] = {
            "mean_presence_ap": float(np.nanmean(ap)) if np.isfinite(ap).any() else None,
            "positives": int((present & sub).sum()),
            "classes": {c: float(ap[i]) for i, c in enumerate(scenes[0].class_set.categories) if np.isfinite(ap[i])},
        }
    return out


def format_subsets(report: dict) -> str:
    """:func:`subset_report` as text: mean presence AP and positives per subset."""
    lines = [f"{'subset':<16} {'positives':>9} {'classes':>7} {'mean presence AP':>17}"]
    for name, r in report.items():
        ap = r["mean_presence_ap"]
        lines.append(
            f"{name:<16} {r['positives']:9d} {len(r['classes']):7d} {(f'{ap:.3f}' if ap is not None else '-'):>17}"
        )
    return "\n".join(lines)


def switch_report_reference(
    scenes: Sequence,
    detections: Sequence[Detections],
    c_target: float = C_TARGET,
    thresholds: Sequence[float] = FP_THRESHOLDS,
) -> dict:
    """Slow reference for :func:`switch_report` (loops over scenes, classes and states); returns
    ``{"pairs", "reached", "reached_in_view", "episode_pairs", "episode_reached", "fp_state_any",
    "fp_state_target", "fp_pair_any", "fp_pair_target"}`` with the same meaning."""
    pairs = reached = in_view = states = episode_pairs = episode_reached = 0
    cnt = {k: {t: 0 for t in thresholds} for k in ("sa", "st", "pa", "pt")}
    neg_any = neg_tgt = 0
    for s, d in zip(scenes, detections):
        gt = ground_truth(s).present
        rooms = s.class_set.room_targets
        targets = [
            c
            for c in s.categories_present()
            if s.room_type not in rooms or s.class_set.categories[c] in rooms[s.room_type]
        ]
        success = s.category_visible_within(SUCCESS_DISTANCE)
        for c in targets:
            pairs += 1
            hits = [i for i in range(len(gt)) if d.scores[i, c] > c_target]
            reached += bool(hits)
            in_view += any(gt[i, c] for i in hits)
            if any(success[i, c] for i in range(len(gt))):
                episode_pairs += 1
                episode_reached += bool(hits)
        for i in range(len(gt)):
            states += 1
            for t in thresholds:
                bad = [c for c in range(s.num_categories) if not gt[i, c] and d.scores[i, c] > t]
                cnt["sa"][t] += bool(bad)
                cnt["st"][t] += any(c in targets for c in bad)
                cnt["pa"][t] += len(bad)
                cnt["pt"][t] += sum(c in targets for c in bad)
            neg_any += sum(not gt[i, c] for c in range(s.num_categories))
            neg_tgt += sum(not gt[i, c] for c in targets)
    return {
        "pairs": pairs,
        "reached": reached,
        "reached_in_view": in_view,
        "episode_pairs": episode_pairs,
        "episode_reached": episode_reached,
        "fp_state_any": {t: v / states for t, v in cnt["sa"].items()},
        "fp_state_target": {t: v / states for t, v in cnt["st"].items()},
        "fp_pair_any": {t: v / neg_any for t, v in cnt["pa"].items()},
        "fp_pair_target": {t: v / neg_tgt for t, v in cnt["pt"].items()},
    }


# ---------------------------------------------------------------------------------------------- figures
def reliability_figure(tables: Sequence[tuple[str, object]], path: str | Path, title: str = "") -> Path:
    """Reliability diagram (atomic PNG): per ``(label, Reliability)`` the accuracy of each confidence bin
    against its mean confidence, the diagonal of perfect calibration, and the number of pairs per bin."""
    fig = Figure(figsize=(10, 4.4), layout="constrained")
    FigureCanvasAgg(fig)
    a0, a1 = fig.subplots(1, 2)
    a0.plot([0, 1], [0, 1], color="0.6", ls="--", lw=1, label="perfect calibration")
    colors = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd")
    for k, (label, rel) in enumerate(tables):
        ok = rel.count > 0
        c = colors[k % len(colors)]
        a0.plot(rel.confidence[ok], rel.accuracy[ok], "o-", color=c, ms=4, label=f"{label} (ECE {100 * rel.ece:.2f} %)")
        centres = (rel.edges[:-1] + rel.edges[1:]) / 2
        w = (rel.edges[1] - rel.edges[0]) / (len(tables) + 1)
        a1.bar(centres + (k - (len(tables) - 1) / 2) * w, rel.count, width=w, color=c, label=label)
    a0.set_xlim(0, 1)
    a0.set_ylim(0, 1)
    a0.set_xlabel("mean confidence of the bin")
    a0.set_ylabel("share of pairs where the class is in view")
    a0.legend(fontsize=8, loc="upper left")
    a0.grid(alpha=0.3)
    a0.set_title("reliability", fontsize=10)
    a1.set_yscale("log")
    a1.set_xlabel("confidence bin")
    a1.set_ylabel("(state, class) pairs")
    a1.set_title("pairs per bin", fontsize=10)
    a1.legend(fontsize=8)
    a1.grid(alpha=0.3, axis="y")
    if title:
        fig.suptitle(title, fontsize=11)
    return atomic_save_figure(fig, path, dpi=100)


def pick_gallery_states(scenes: Sequence, per_scene: int = 2, seed: int = 0) -> list[tuple[int, int]]:
    """``(scene index, state id)`` of ``per_scene`` random states per scene that show at least one of the
    scene's possible targets (seeded; the frames of :func:`detection_gallery`)."""
    rng = np.random.default_rng(seed)
    out = []
    for i, s in enumerate(scenes):
        show = (ground_truth(s).present & scene_targets(s)).any(axis=1)
        ids = np.flatnonzero(show)
        if len(ids):
            out += [(i, int(j)) for j in np.sort(rng.choice(ids, min(per_scene, len(ids)), replace=False))]
    return out


def detection_gallery(
    scenes: Sequence,
    detections: Sequence[Detections],
    picks: Sequence[tuple[int, int]],
    path: str | Path,
    min_score: float = 0.5,
    cols: int = 6,
    title: str = "",
) -> Path:
    """Grid of frames (atomic PNG): the detector's boxes of every class scoring at least ``min_score``
    (solid, green when the class is in view and the box overlaps the truth with IoU >= 0.5, orange when in
    view but the box misses, red when the class is not in view), labelled with class and score; the
    ground-truth boxes of the classes in view (dashed white)."""
    rows = max(1, -(-len(picks) // cols))
    fig = Figure(figsize=(2.9 * cols, 3.1 * rows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, cols, squeeze=False)
    gts = {}
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (i, j) in zip(axes.ravel(), picks):
        s, d = scenes[i], detections[i]
        if i not in gts:
            gts[i] = ground_truth(s)
        gt = gts[i]
        img = read_images(s.path, [s.keys[j]])[0]
        ax.imshow(img, interpolation="nearest")
        for c in np.flatnonzero(gt.present[j]):
            x0, y0, x1, y1 = gt.boxes[j, c]
            ax.add_patch(
                Rectangle((x0 - 0.5, y0 - 0.5), x1 - x0 + 1, y1 - y0 + 1, fill=False, ec="white", ls="--", lw=0.9)
            )
        shown = [c for c in np.argsort(-d.scores[j]) if d.scores[j, c] >= min_score and d.labels[j, c] >= 0]
        for c in shown:
            x0, y0, x1, y1 = d.boxes[j, c]
            if not gt.present[j, c]:
                col = "#ff2020"
            elif box_iou(d.boxes[j, c][None], gt.boxes[j, c][None])[0] >= 0.5:
                col = "#20e020"
            else:
                col = "#ff9900"
            ax.add_patch(Rectangle((x0 - 0.5, y0 - 0.5), x1 - x0 + 1, y1 - y0 + 1, fill=False, ec=col, lw=1.4))
            ax.text(
                x0,
                max(y0 - 1, 0),
                f"{s.class_set.categories[c]} {d.scores[j, c]:.2f}",
                color="black",
                fontsize=5.5,
                va="bottom",
                bbox=dict(facecolor=col, alpha=0.8, pad=0.6, lw=0),
            )
        missed = [s.class_set.categories[c] for c in np.flatnonzero(gt.present[j]) if d.scores[j, c] < min_score]
        ax.set_title(f"{s.name} {s.keys[j]}" + (f"\nmissed: {', '.join(missed)}" if missed else "\n"), fontsize=6.5)
    if title:
        fig.suptitle(title, fontsize=11)
    return atomic_save_figure(fig, path, dpi=90)


# ---------------------------------------------------------------------------------------------- command
def main(argv: Sequence[str] | None = None) -> int:
    """Evaluate stored tables ``detections_<name>.hdf5`` of a split: AP, calibration, reach, false
    positives; writes ``quality_<split>.json``, ``reliability_<split>.png`` and ``gallery_<split>.png``."""
    ap = argparse.ArgumentParser(
        allow_abbrev=False, prog="python -m tsnav.detect.quality", description=main.__doc__.split(";")[0]
    )
    ap.add_argument("--data", required=True, help="dataset root")
    ap.add_argument("--name", default="learned", help="table name detections_<name>.hdf5 (default learned)")
    ap.add_argument("--split", default="val", help="scenes of this split (default val)")
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--c-target", type=float, default=C_TARGET, help=f"switch threshold for reach (paper: {C_TARGET})")
    ap.add_argument("--gallery-per-scene", type=int, default=1, help="gallery frames per scene (default 1)")
    args = ap.parse_args(argv)
    paths = [p for p in list_scenes(args.data, split=args.split) if (p / f"detections_{args.name}.hdf5").exists()]
    if not paths:
        raise SystemExit(f"{args.data}: no {args.split} scene with detections_{args.name}.hdf5")
    scenes = [load_scene(p) for p in tqdm(paths, desc="scenes", unit="scene")]
    dets = [load_detections(s.path, args.name) for s in scenes]
    report = evaluate_detections(scenes, dets)
    switch = switch_report(scenes, dets, args.c_target)
    subsets = subset_report(scenes, dets)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(
        out / f"quality_{args.split}.json",
        {
            "name": args.name,
            "detector": dets[0].detector,
            "fingerprint": dets[0].fingerprint,
            "config": dets[0].config,
            "evaluation": report.to_json(),
            "switch": switch.to_json(),
            "subsets": subsets,
        },
        indent=1,
    )
    reliability_figure(
        [
            ("all (state, class) pairs", report.reliability),
            ("classes present in the scene", report.reliability_present),
        ],
        out / f"reliability_{args.split}.png",
        title=f"detector '{args.name}' on {len(scenes)} {args.split} scenes",
    )
    picks = pick_gallery_states(scenes, args.gallery_per_scene)
    detection_gallery(
        scenes,
        dets,
        picks,
        out / f"gallery_{args.split}.png",
        cols=5,
        title=f"detector '{args.name}', {args.split} frames: boxes scoring >= 0.5 (green hit, orange "
        f"box missed, red class not in view), ground truth dashed",
    )
    print(report.format())
    print(switch.format())
    print("presence AP by the target's size in the frame, and within 1.5 m (AI2-THOR-style, beside the above):")
    print(format_subsets(subsets))
    print(f"wrote {out / f'quality_{args.split}.json'}, reliability_{args.split}.png, gallery_{args.split}.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
