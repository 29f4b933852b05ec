"""Detector evaluation: per-class average precision and calibration (reliability table, ECE).

Ground truth is that of :func:`tsnav.detect.oracle.ground_truth` (class present when an instance shows at
least ``min_pixels``; box of the visible instance with most pixels).

* *Presence AP* ranks every (state, class) pair of a class by score; positives are the states where the
  class is present. It measures what the stage switch of the paper (III-B) relies on: the confidence that
  the target is in the frame.
* *Box AP@0.5* ranks the kept detections (label != -1) of a class; a detection is a true positive when the
  class is present and its box overlaps the ground-truth box with IoU >= 0.5 (one detection per class and
  state, so no duplicate matching is needed); recall is over all present states.
* AP is the all-point interpolated area under the precision-recall curve (PASCAL VOC 2010+): precision is
  replaced by its running maximum from the right, summed over recall steps. Tied scores enter together.
* Reliability: confidences in 10 equal-width bins over [0, 1] (a confidence of exactly 1 falls in the last
  bin); per bin the count, the mean confidence and the accuracy (share of pairs where the class is present);
  ECE = sum_b (n_b / N) |accuracy_b - confidence_b| (Guo et al. 2017).

Boxes use inclusive pixel corners (``Scene.boxes``): ``[x0, y0, x1, y1]`` covers ``x1 - x0 + 1`` columns.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..constants import DEFAULT_CLASS_SET, class_set as get_class_set
from .oracle import ground_truth
from ..data.detections import Detections


def average_precision(scores: np.ndarray, positive: np.ndarray, num_positives: int | None = None) -> float:
    """All-point interpolated AP of a ranked list (module docstring); NaN when there are no positives.

    Args:
        scores: ``(n,)`` detection scores (higher ranks first; equal scores enter together).
        positive: ``(n,)`` bool, the detection is a true positive.
        num_positives: ground-truth count for recall (default: ``positive.sum()``); larger when some
            ground truth has no detection in the list.
    """
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    positive = np.asarray(positive, dtype=bool).reshape(-1)
    if scores.shape != positive.shape:
        raise ValueError(f"scores {scores.shape} and positive {positive.shape} differ in shape")
    npos = int(positive.sum()) if num_positives is None else int(num_positives)
    if npos < positive.sum():
        raise ValueError("num_positives is smaller than the number of true positives")
    if npos == 0:
        return float("nan")
    if scores.size == 0:
        return 0.0
    order = np.argsort(-scores, kind="stable")
    s, p = scores[order], positive[order]
    tp = np.cumsum(p)
    fp = np.cumsum(~p)
    # Keep the last row of each group of equal scores (a threshold admits all of them at once).
    last = np.r_[s[1:] != s[:-1], True]
    tp, fp = tp[last], fp[last]
    precision = tp / (tp + fp)
    recall = tp / npos
    envelope = np.maximum.accumulate(precision[::-1])[::-1]
    steps = np.diff(np.r_[0.0, recall])
    return float((steps * envelope).sum())


def average_precision_reference(scores, positive, num_positives: int | None = None) -> float:
    """Slow reference for :func:`average_precision`: one threshold at a time, by counting."""
    scores = [float(x) for x in np.asarray(scores).reshape(-1)]
    positive = [bool(x) for x in np.asarray(positive).reshape(-1)]
    npos = sum(positive) if num_positives is None else int(num_positives)
    if npos == 0:
        return float("nan")
    thresholds = sorted(set(scores), reverse=True)
    prec, rec = [], []
    for t in thresholds:
        tp = sum(1 for x, y in zip(scores, positive) if x >= t and y)
        fp = sum(1 for x, y in zip(scores, positive) if x >= t and not y)
        prec.append(tp / (tp + fp))
        rec.append(tp / npos)
    ap, prev = 0.0, 0.0
    for i in range(len(thresholds)):
        ap += (rec[i] - prev) * max(prec[i:])
        prev = rec[i]
    return ap


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Element-wise IoU of boxes ``a`` and ``b`` (``(..., 4)`` inclusive pixel corners); 0 for invalid boxes."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    ax0, ay0, ax1, ay1 = a[..., 0], a[..., 1], a[..., 2] + 1, a[..., 3] + 1
    bx0, by0, bx1, by1 = b[..., 0], b[..., 1], b[..., 2] + 1, b[..., 3] + 1
    iw = np.clip(np.minimum(ax1, bx1) - np.maximum(ax0, bx0), 0, None)
    ih = np.clip(np.minimum(ay1, by1) - np.maximum(ay0, by0), 0, None)
    inter = iw * ih
    area_a = np.clip(ax1 - ax0, 0, None) * np.clip(ay1 - ay0, 0, None)
    area_b = np.clip(bx1 - bx0, 0, None) * np.clip(by1 - by0, 0, None)
    union = area_a + area_b - inter
    valid = (a[..., 0] >= 0) & (b[..., 0] >= 0) & (union > 0)
    return np.where(valid, inter / np.where(union > 0, union, 1.0), 0.0)


@dataclass
class Reliability:
    """Reliability table over equal-width confidence bins (module docstring).

    Attributes:
        edges: ``(B+1,)`` bin edges over [0, 1].
        count: ``(B,)`` pairs per bin.
        confidence: ``(B,)`` mean confidence per bin (NaN for empty bins).
        accuracy: ``(B,)`` share of positives per bin (NaN for empty bins).
        ece: expected calibration error, sum_b (n_b / N) |accuracy_b - confidence_b|.
    """

    edges: np.ndarray
    count: np.ndarray
    confidence: np.ndarray
    accuracy: np.ndarray
    ece: float

    def format(self) -> str:
        """The table as aligned text lines."""
        lines = [f"{'bin':>11} {'count':>9} {'mean conf':>10} {'accuracy':>9}"]
        for i in range(len(self.count)):
            c = f"{self.confidence[i]:10.3f}" if self.count[i] else f"{'-':>10}"
            a = f"{self.accuracy[i]:9.3f}" if self.count[i] else f"{'-':>9}"
            lines.append(f"{self.edges[i]:4.1f}-{self.edges[i + 1]:4.1f}  {int(self.count[i]):9d} {c} {a}")
        lines.append(f"ECE = {self.ece:.4f} over {int(self.count.sum())} (state, class) pairs")
        return "\n".join(lines)


def reliability_table(confidence: np.ndarray, positive: np.ndarray, bins: int = 10) -> Reliability:
    """Reliability table and ECE of ``confidence`` (any shape, values in [0, 1]) against ``positive``."""
    conf = np.asarray(confidence, dtype=np.float64).reshape(-1)
    pos = np.asarray(positive, dtype=bool).reshape(-1)
    if conf.shape != pos.shape:
        raise ValueError(f"confidence {conf.shape} and positive {pos.shape} differ in shape")
    if conf.size and (conf.min() < 0 or conf.max() > 1 or not np.isfinite(conf).all()):
        raise ValueError("confidences must be finite and in [0, 1]")
    edges = np.linspace(0.0, 1.0, bins + 1)
    idx = np.minimum((conf * bins).astype(np.int64), bins - 1)
    count = np.bincount(idx, minlength=bins).astype(np.int64)
    sum_conf = np.bincount(idx, weights=conf, minlength=bins)
    sum_pos = np.bincount(idx, weights=pos.astype(np.float64), minlength=bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_conf = np.where(count > 0, sum_conf / count, np.nan)
        acc = np.where(count > 0, sum_pos / count, np.nan)
    n = max(int(count.sum()), 1)
    ece = float(np.nansum(count / n * np.abs(acc - mean_conf)))
    return Reliability(edges, count, mean_conf, acc, ece)


def reliability_reference(confidence, positive, bins: int = 10) -> Reliability:
    """Slow reference for :func:`reliability_table`: each pair placed in its bin by comparisons."""
    conf = [float(x) for x in np.asarray(confidence).reshape(-1)]
    pos = [bool(x) for x in np.asarray(positive).reshape(-1)]
    edges = [i / bins for i in range(bins + 1)]
    members: list[list[int]] = [[] for _ in range(bins)]
    for j, c in enumerate(conf):
        for b in range(bins):
            if edges[b] <= c < edges[b + 1] or (b == bins - 1 and c == 1.0):
                members[b].append(j)
                break
    count = np.array([len(m) for m in members])
    mc = np.array([np.mean([conf[j] for j in m]) if m else np.nan for m in members])
    acc = np.array([np.mean([pos[j] for j in m]) if m else np.nan for m in members])
    ece = sum(len(m) / max(len(conf), 1) * abs(acc[b] - mc[b]) for b, m in enumerate(members) if m)
    return Reliability(np.array(edges), count, mc, acc, float(ece))


@dataclass
class DetectionReport:
    """Evaluation of a detector on a set of scenes.

    Attributes:
        presence_ap, box_ap: ``(C,)`` per-class AP (NaN where the class never appears).
        positives: ``(C,)`` present (state, class) pairs per class.
        reliability: :class:`Reliability` over every (state, class) pair.
        reliability_present: the same over the classes that have an instance in each pair's scene.
        scenes: names of the scenes evaluated; states: their number of states.
    """

    presence_ap: np.ndarray
    box_ap: np.ndarray
    positives: np.ndarray
    reliability: Reliability
    reliability_present: Reliability
    scenes: list = field(default_factory=list)
    states: int = 0
    class_set: str = DEFAULT_CLASS_SET

    @property
    def categories(self) -> tuple[str, ...]:
        """Names of the classes, the order of the per-class arrays."""
        return get_class_set(self.class_set).categories

    @property
    def mean_presence_ap(self) -> float:
        return float(np.nanmean(self.presence_ap)) if np.isfinite(self.presence_ap).any() else float("nan")

    @property
    def mean_box_ap(self) -> float:
        return float(np.nanmean(self.box_ap)) if np.isfinite(self.box_ap).any() else float("nan")

    def to_json(self) -> dict:
        def rel(r: Reliability) -> dict:
            return {
                "edges": r.edges.tolist(),
                "count": r.count.tolist(),
                "confidence": [None if np.isnan(x) else float(x) for x in r.confidence],
                "accuracy": [None if np.isnan(x) else float(x) for x in r.accuracy],
                "ece": r.ece,
            }

        def nn(x: float):
            return None if np.isnan(x) else float(x)

        return {
            "scenes": self.scenes,
            "states": self.states,
            "classes": {
                c: {
                    "positives": int(self.positives[i]),
                    "presence_ap": nn(self.presence_ap[i]),
                    "box_ap50": nn(self.box_ap[i]),
                }
                for i, c in enumerate(self.categories)
            },
            "mean_presence_ap": nn(self.mean_presence_ap),
            "mean_box_ap50": nn(self.mean_box_ap),
            "reliability": rel(self.reliability),
            "reliability_present": rel(self.reliability_present),
        }

    def format(self) -> str:
        """Per-class AP table and reliability table as text."""
        lines = [
            f"{len(self.scenes)} scenes, {self.states} states",
            f"{'class':<14} {'positives':>9} {'presence AP':>12} {'box AP@0.5':>11}",
        ]
        for i, c in enumerate(self.categories):
            if self.positives[i] == 0:
                continue
            lines.append(f"{c:<14} {int(self.positives[i]):9d} {self.presence_ap[i]:12.3f} {self.box_ap[i]:11.3f}")
        lines.append(
            f"{'mean':<14} {int(self.positives.sum()):9d} {self.mean_presence_ap:12.3f} {self.mean_box_ap:11.3f}"
        )
        lines.append("reliability, all (state, class) pairs:")
        lines.append(self.reliability.format())
        lines.append("reliability, classes present in the scene:")
        lines.append(self.reliability_present.format())
        return "\n".join(lines)


def evaluate_detections(
    scenes: Sequence, detections: Sequence[Detections], iou: float = 0.5, bins: int = 10
) -> DetectionReport:
    """Evaluate per-scene tables ``detections`` (aligned with ``scenes``) against the ground truth."""
    if len(scenes) != len(detections):
        raise ValueError(f"{len(scenes)} scenes but {len(detections)} detection tables")
    if not scenes:
        raise ValueError("nothing to evaluate: no scenes")
    present, gt_boxes, in_scene = [], [], []
    for s, d in zip(scenes, detections):
        if len(d.keys) != len(s.keys) or not (d.keys == s.keys).all():
            raise ValueError(f"detections of scene {s.name} do not match its states")
        gt = ground_truth(s)
        present.append(gt.present)
        gt_boxes.append(gt.boxes)
        mask = np.zeros(s.num_categories, bool)
        mask[s.categories_present()] = True
        in_scene.append(np.broadcast_to(mask, gt.present.shape))
    det = Detections.concatenate(list(detections))
    C = get_class_set(det.class_set).size
    present = np.concatenate(present)
    gt_boxes = np.concatenate(gt_boxes)
    in_scene = np.concatenate(in_scene)
    overlap = box_iou(det.boxes, gt_boxes) >= iou
    kept = det.labels >= 0
    p_ap = np.full(C, np.nan)
    b_ap = np.full(C, np.nan)
    for c in range(C):
        npos = int(present[:, c].sum())
        if npos == 0:
            continue
        p_ap[c] = average_precision(det.scores[:, c], present[:, c])
        k = kept[:, c]
        b_ap[c] = average_precision(det.scores[k, c], (present & overlap)[k, c], num_positives=npos)
    return DetectionReport(
        presence_ap=p_ap,
        box_ap=b_ap,
        positives=present.sum(0),
        reliability=reliability_table(det.scores, present, bins),
        reliability_present=reliability_table(det.scores[in_scene], present[in_scene], bins),
        scenes=[s.name for s in scenes],
        states=int(len(present)),
        class_set=det.class_set,
    )
