"""A small CPU-trainable dense detector (FCOS / CenterNet family) for the target classes of a class set (C: the 22
of ``ithor22``, the 12 of ``robothor12``; ``DetectorConfig.class_set``).

Why not DETR (the paper's detector, Fig. 2): DETR needs an ImageNet-pretrained backbone and hundreds of GPU
epochs (its set-based loss converges slowly); neither pretrained weights nor a GPU are available here. A
DETR reduced to one query per class was tried first and after 400 steps on the demo world had learned
little more than room priors (val presence mAP 0.15). A dense head supervised at every cell learns much
faster, and still yields the lineage's table (best detection per class: score, box, feature).

Architecture, for ``S x S`` frames (64 x 64 by default), ``G = S / 8`` cells a side:

* backbone: conv3x3-BN-ReLU layers with strides 2, 2, 1, 2, 1 and a dilated (2) conv3x3 for context
  (receptive field 71 px): ``[N, 3, S, S] -> [N, C, G, G]``;
* neck: 1x1 conv to ``dim`` channels + ReLU: the per-cell feature ``[N, dim, G, G]``; with
  ``DetectorConfig.fine`` the grid is twice as fine (``G = S / 4``): the neck's output is upsampled and added
  to a 1x1 projection of the stride-4 stage, then smoothed by a conv3x3-BN-ReLU (one FPN level);
* heads (1x1 convs): a logit per class and cell ``[N, C, G, G]``, and per class and cell a box as offsets
  of its four edges from the cell centre, in frame units ``[N, C, 4, G, G]``.

Per image and class (:meth:`GridDetector.forward`): the presence logit is ``logsumexp`` over the cells of
the class's cell logits plus a learned class bias (a smooth max); the box and the feature are those of
the cell with the largest logit.

Training targets per cell (:func:`dense_targets`): a cell is positive for class ``c`` when its centre lies
inside the box of a visible instance of ``c`` (at least ``min_pixels``), or is the cell that contains that
box's centre (so every instance, however small, has a positive cell); the cell's box target is the smallest
such box. Cells covered only by instances with fewer than ``min_pixels`` pixels are ignored.

Loss (:func:`detection_loss`): sigmoid focal loss over the cells (RetinaNet, alpha 0.25, gamma 2, normalised
by the number of positive cells) + binary cross-entropy of the per-image presence logits (which trains the
score the table stores) + over the positive cells ``l1`` x L1 + ``giou`` x (1 - GIoU) of the boxes
(DETR's box losses and weights).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..constants import DEFAULT_CLASS_SET, NUM_CATEGORIES, class_set as get_class_set
from ..data.detections import pixel_to_unit, unit_to_pixel  # noqa: F401  (the box conversions, kept importable here)


@dataclass
class DetectorConfig:
    """Architecture of :class:`GridDetector`."""

    image_size: int = 64
    """Side of the square input frames, pixels (the dataset's image size); a multiple of 8."""
    widths: tuple[int, int, int] = (16, 32, 64)
    """Channels of the three backbone stages (about 10 M multiply-adds per 64x64 frame with the defaults,
    so that training fits in minutes on 2 CPU cores)."""
    dim: int = 64
    """Channels of the per-cell feature; also the size of the per-class feature stored in the table."""
    num_classes: int | None = None
    """Number of classes: the class set's (None), 22 for ``ithor22``; a value that differs from it is refused."""
    class_set: str = DEFAULT_CLASS_SET
    """The target classes the detector scores (:class:`~tsnav.constants.ClassSet` name: ``ithor22`` or
    ``robothor12``); checkpoints written before class sets existed are ``ithor22``. Its tables are written and
    read only for scenes of this class set."""
    stem: int = 1
    """Space-to-depth factor of the input (pixel unshuffle): with 2, a 128x128 frame enters the backbone as 12
    channels at 64x64, so the network costs about what it costs at 64x64 yet sees every pixel."""
    fine: bool = False
    """Finer output grid: cells of stride 4 after the stem instead of 8 (twice as many a side). The last
    stage's feature is upsampled (nearest) and added to a 1x1 projection of the second stage's (an FPN-style
    lateral), then smoothed by a conv3x3-BN-ReLU; small objects (a phone, a remote) then own cells of their
    own. Checkpoints written before this field have ``fine`` False."""

    def __post_init__(self) -> None:
        n = get_class_set(self.class_set).size
        if self.num_classes is None:
            self.num_classes = n
        elif int(self.num_classes) != n:
            raise ValueError(
                f"detector config: num_classes {self.num_classes} but class set {self.class_set} has {n} classes"
            )

    @property
    def grid(self) -> int:
        """Cells per side of the output grid (stride 8 after the space-to-depth stem, 4 when ``fine``)."""
        return self.image_size // (8 * self.stem) * (2 if self.fine else 1)

    @classmethod
    def from_dict(cls, d: dict) -> "DetectorConfig":
        d = dict(d)
        if "widths" in d:
            d["widths"] = tuple(int(w) for w in d["widths"])
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown detector config fields: {sorted(unknown)}")
        return cls(**d)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["widths"] = list(self.widths)
        if d["class_set"] == DEFAULT_CLASS_SET:  # absent reads as ithor22: iTHOR checkpoints keep their bytes
            del d["class_set"]
        return d


def default_config(image_size: int, class_set: str = DEFAULT_CLASS_SET) -> DetectorConfig:
    """The architecture ``tsnav detect --detector learned`` gives a new checkpoint for ``image_size`` px
    frames: a space-to-depth stem of ``image_size / 64`` (a 128px frame costs what a 64px one does); from 128px
    on, the wider backbone (32, 64, 128) with the fine (stride-4) grid, the best measured on the `ithor-real`
    world (BENCHMARKS.md, "Learned detector"); below, the small default (16, 32, 64) of the demo world. The classes
    are ``class_set``'s (the train scenes')."""
    stem = max(1, image_size // 64)
    if image_size >= 128:
        return DetectorConfig(image_size=image_size, stem=stem, widths=(32, 64, 128), fine=True, class_set=class_set)
    return DetectorConfig(image_size=image_size, stem=stem, class_set=class_set)


def _conv(cin: int, cout: int, stride: int, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride, dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


def cell_centres(grid: int) -> torch.Tensor:
    """``[grid * grid, 2]`` (x, y) centres of the cells in frame units (row-major cells)."""
    c = (torch.arange(grid, dtype=torch.float32) + 0.5) / grid
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    return torch.stack([xx.reshape(-1), yy.reshape(-1)], dim=1)


class GridDetector(nn.Module):
    """RGB frames -> per-class presence logits, boxes and features (module docstring)."""

    def __init__(self, cfg: DetectorConfig | None = None):
        super().__init__()
        self.cfg = cfg = cfg or DetectorConfig()
        if cfg.stem < 1 or cfg.image_size % (8 * cfg.stem) or cfg.image_size < 16 * cfg.stem:
            raise ValueError(
                f"image_size must be a multiple of {8 * cfg.stem} and at least {16 * cfg.stem} "
                f"(stem {cfg.stem}), got {cfg.image_size}"
            )
        w1, w2, w3 = cfg.widths
        C = cfg.num_classes
        self.backbone = nn.Sequential(
            _conv(3 * cfg.stem**2, w1, 2),
            _conv(w1, w2, 2),
            _conv(w2, w2, 1),
            _conv(w2, w3, 2),
            _conv(w3, w3, 1),
            _conv(w3, w3, 1, dilation=2),
        )
        self.neck = nn.Sequential(nn.Conv2d(w3, cfg.dim, 1), nn.ReLU(inplace=True))
        if cfg.fine:
            self.lateral = nn.Conv2d(w2, cfg.dim, 1)
            self.smooth = _conv(cfg.dim, cfg.dim, 1)
        self.cls_head = nn.Conv2d(cfg.dim, C, 1)
        self.box_head = nn.Conv2d(cfg.dim, C * 4, 1)
        # Start: cells at the focal-loss prior 0.01 (RetinaNet); boxes 0.2 frame wide around the cell centre.
        nn.init.normal_(self.cls_head.weight, std=0.01)
        nn.init.constant_(self.cls_head.bias, -4.6)
        nn.init.normal_(self.box_head.weight, std=0.01)
        with torch.no_grad():
            self.box_head.bias.copy_(torch.tensor([-0.1, -0.1, 0.1, 0.1]).repeat(C))
        # Presence logit at start: -4.6 + ln(L) + bias = -3, about the base rate of a class in view.
        self.class_bias = nn.Parameter(torch.full((C,), 1.6 - float(np.log(cfg.grid**2))))
        self.register_buffer("centres", cell_centres(cfg.grid), persistent=False)

    @staticmethod
    def normalize(rgb: torch.Tensor) -> torch.Tensor:
        """RGB ``[N, H, W, 3]`` in [0, 255] (uint8 or float) -> float ``[N, 3, H, W]`` roughly zero-mean."""
        return (rgb.permute(0, 3, 1, 2).float() / 255.0 - 0.5) / 0.25

    def dense(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Normalised ``[N, 3, S, S]`` -> (cell logits ``[N, C, L]``, cell boxes ``[N, C, L, 4]`` normalised
        ``[x0, y0, x1, y1]`` (corners ordered, not clipped), cell features ``[N, L, dim]``), ``L = G * G``."""
        if self.cfg.stem > 1:
            x = F.pixel_unshuffle(x, self.cfg.stem)
        if self.cfg.fine:
            stage2 = self.backbone[:3](x)  # [N, w2, 2G', 2G'] (stride 4)
            coarse = self.neck(self.backbone[3:](stage2))  # [N, dim, G', G'] (stride 8)
            f = self.smooth(F.interpolate(coarse, scale_factor=2, mode="nearest") + self.lateral(stage2))
        else:
            f = self.neck(self.backbone(x))  # [N, dim, G, G]
        N, C = x.shape[0], self.cfg.num_classes
        logits = self.cls_head(f).flatten(2)  # [N, C, L]
        d = self.box_head(f).reshape(N, C, 4, -1).transpose(2, 3)  # [N, C, L, 4]
        raw = d + self.centres.repeat(1, 2)  # edges = cell centre + offsets
        lo = torch.minimum(raw[..., :2], raw[..., 2:])
        hi = torch.maximum(raw[..., :2], raw[..., 2:])
        return logits, torch.cat([lo, hi], dim=-1), f.flatten(2).transpose(1, 2)

    def pool(
        self, logits: torch.Tensor, boxes: torch.Tensor, feats: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Per image and class: (presence logit ``[N, C]`` = logsumexp over cells + class bias, box of the
        best cell ``[N, C, 4]`` clipped to [0, 1], feature of the best cell ``[N, C, dim]``)."""
        presence = torch.logsumexp(logits, dim=-1) + self.class_bias
        best = logits.argmax(dim=-1)  # [N, C]
        box = torch.gather(boxes, 2, best[..., None, None].expand(-1, -1, 1, 4)).squeeze(2).clamp(0, 1)
        feat = torch.gather(feats, 1, best[..., None].expand(-1, -1, feats.shape[-1]))
        return presence, box, feat

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Normalised ``[N, 3, S, S]`` -> (presence logits ``[N, C]``, boxes ``[N, C, 4]`` normalised
        continuous ``[x0, y0, x1, y1]`` in [0, 1], features ``[N, C, dim]``)."""
        return self.pool(*self.dense(x))


# ---------------------------------------------------------------------------------------------- targets
def dense_targets(
    boxes: torch.Tensor, category: torch.Tensor, state: torch.Tensor, grid: int, num_classes: int = NUM_CATEGORIES
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-cell training targets (module docstring), batched.

    Args:
        boxes: ``[B, K, 4]`` object boxes as normalised continuous ``[x0, y0, x1, y1]``.
        category: ``[B, K]`` class of each object (-1: padding or not a target class).
        state: ``[B, K]`` 0 not in view, 1 in view with fewer than ``min_pixels`` (ignored), 2 visible.
        grid: cells per side.

    Returns:
        positive ``[B, C, L]`` bool, ignore ``[B, C, L]`` bool, box target ``[B, C, L, 4]`` (the smallest
        visible box of the class that claims the cell; zeros where not positive).
    """
    B, K = category.shape
    L = grid * grid
    c = cell_centres(grid).to(boxes.device)  # [L, 2]
    cx, cy = c[:, 0], c[:, 1]
    b = boxes[..., None, :]  # [B, K, 1, 4]
    inside = (cx >= b[..., 0]) & (cx < b[..., 2]) & (cy >= b[..., 1]) & (cy < b[..., 3])  # [B, K, L]
    mx = ((boxes[..., 0] + boxes[..., 2]) / 2 * grid).floor().clamp(0, grid - 1)
    my = ((boxes[..., 1] + boxes[..., 3]) / 2 * grid).floor().clamp(0, grid - 1)
    centre_cell = (my * grid + mx).long()  # [B, K]
    claims = inside | (torch.arange(L, device=boxes.device) == centre_cell[..., None])  # [B, K, L]
    # Each object has one class: reduce over objects into per-class maps by scatter (no [B, K, C, L] tensor).
    # Objects without a target class (-1) go to a dummy class row ``num_classes`` that is dropped at the end.
    cls = torch.where(category >= 0, category, torch.full_like(category, num_classes)).long()
    index = cls[..., None].expand(-1, -1, L)  # [B, K, L]
    vis = claims & (state == 2)[..., None]  # [B, K, L]
    weak = claims & (state == 1)[..., None]
    inf = torch.tensor(float("inf"), device=boxes.device)
    area = (boxes[..., 2] - boxes[..., 0]) * (boxes[..., 3] - boxes[..., 1])  # [B, K]
    masked = torch.where(vis, area[..., None], inf)  # [B, K, L]
    smallest = torch.full((B, num_classes + 1, L), float("inf"), device=boxes.device)
    smallest = smallest.scatter_reduce(1, index, masked, reduce="amin")  # [B, 23, L]
    positive = torch.isfinite(smallest[:, :num_classes])  # [B, C, L]
    # The first object of the class whose area is the smallest (the reference's tie rule).
    first = torch.where(
        vis & (masked == torch.gather(smallest, 1, index)), torch.arange(K, device=boxes.device)[None, :, None], K
    )  # [B, K, L]
    k = torch.full((B, num_classes + 1, L), K, device=boxes.device, dtype=torch.long)
    k = k.scatter_reduce(1, index, first, reduce="amin")[:, :num_classes].clamp(max=max(K - 1, 0))
    weak_c = torch.zeros((B, num_classes + 1, L), device=boxes.device, dtype=torch.long)
    weak_c = weak_c.scatter_reduce(1, index, weak.long(), reduce="amax")[:, :num_classes].bool()
    ignore = weak_c & ~positive
    target = torch.gather(
        boxes[:, None, :, :].expand(-1, num_classes, -1, -1), 2, k[..., None].expand(-1, -1, -1, 4)
    )  # [B, C, L, 4]
    target = torch.where(positive[..., None], target, torch.zeros_like(target))
    return positive, ignore, target


def dense_targets_reference(boxes, category, state, grid: int, num_classes: int = NUM_CATEGORIES):
    """Slow reference for :func:`dense_targets`: loops over images, cells, classes and objects."""
    boxes = np.asarray(boxes, dtype=np.float32)
    category, state = np.asarray(category), np.asarray(state)
    B, K = category.shape
    L = grid * grid
    positive = np.zeros((B, num_classes, L), bool)
    ignore = np.zeros((B, num_classes, L), bool)
    target = np.zeros((B, num_classes, L, 4), np.float32)
    for b in range(B):
        for cell in range(L):
            i, j = divmod(cell, grid)
            cx, cy = np.float32((j + 0.5) / grid), np.float32((i + 0.5) / grid)
            for cls in range(num_classes):
                best, best_area, weak = None, np.inf, False
                for k in range(K):
                    if category[b, k] != cls or state[b, k] == 0:
                        continue
                    x0, y0, x1, y1 = boxes[b, k]
                    mx = min(max(int(np.floor((x0 + x1) / 2 * grid)), 0), grid - 1)
                    my = min(max(int(np.floor((y0 + y1) / 2 * grid)), 0), grid - 1)
                    claims = (x0 <= cx < x1 and y0 <= cy < y1) or (my * grid + mx == cell)
                    if not claims:
                        continue
                    if state[b, k] == 1:
                        weak = True
                        continue
                    area = (x1 - x0) * (y1 - y0)
                    if area < best_area:
                        best, best_area = k, area
                if best is not None:
                    positive[b, cls, cell] = True
                    target[b, cls, cell] = boxes[b, best]
                elif weak:
                    ignore[b, cls, cell] = True
    return positive, ignore, target


# ---------------------------------------------------------------------------------------------- loss
def generalized_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Element-wise GIoU of continuous boxes ``[..., 4]`` ``[x0, y0, x1, y1]`` (Rezatofighi et al. 2019)."""
    area_a = (a[..., 2] - a[..., 0]).clamp(min=0) * (a[..., 3] - a[..., 1]).clamp(min=0)
    area_b = (b[..., 2] - b[..., 0]).clamp(min=0) * (b[..., 3] - b[..., 1]).clamp(min=0)
    lt = torch.maximum(a[..., :2], b[..., :2])
    rb = torch.minimum(a[..., 2:], b[..., 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    union = area_a + area_b - inter
    iou = inter / union.clamp(min=1e-9)
    lt_c = torch.minimum(a[..., :2], b[..., :2])
    rb_c = torch.maximum(a[..., 2:], b[..., 2:])
    hull = (rb_c - lt_c).clamp(min=0).prod(-1)
    return iou - (hull - union) / hull.clamp(min=1e-9)


@dataclass
class LossWeights:
    """Weights of the terms of :func:`detection_loss`."""

    cells: float = 1.0
    """Sigmoid focal loss over cells (normalised by the number of positive cells)."""
    presence: float = 1.0
    """Binary cross-entropy of the per-image presence logits (mean over image and class)."""
    l1: float = 5.0
    """L1 distance of normalised box edges over positive cells (DETR: 5)."""
    giou: float = 2.0
    """1 - GIoU of the boxes over positive cells (DETR: 2)."""
    focal_alpha: float = 0.25
    """Focal loss weight of positive cells (RetinaNet: 0.25)."""
    focal_gamma: float = 2.0
    """Focal loss focusing exponent (RetinaNet: 2)."""
    presence_pos_weight: float = 1.0
    """Weight of the present classes in the presence cross-entropy (``pos_weight``; issue 23: an agent pays for
    targets in view that score low far more than for false positives); 1 weighs both alike."""


def focal_loss(logits: torch.Tensor, positive: torch.Tensor, alpha: float, gamma: float) -> torch.Tensor:
    """Element-wise sigmoid focal loss (Lin et al. 2017)."""
    t = positive.float()
    p = torch.sigmoid(logits)
    ce = F.binary_cross_entropy_with_logits(logits, t, reduction="none")
    pt = p * t + (1 - p) * (1 - t)
    return (alpha * t + (1 - alpha) * (1 - t)) * (1 - pt) ** gamma * ce


def detection_loss(
    model: GridDetector,
    x: torch.Tensor,
    present: torch.Tensor,
    boxes: torch.Tensor,
    category: torch.Tensor,
    state: torch.Tensor,
    w: LossWeights | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Total loss and its terms for normalised frames ``x`` with per-image ``present`` ``[B, C]`` and
    per-object ``boxes`` / ``category`` / ``state`` ``[B, K, ...]`` (see :func:`dense_targets`)."""
    w = w or LossWeights()
    cell_logits, cell_boxes, feats = model.dense(x)
    positive, ignore, target = dense_targets(boxes, category, state, model.cfg.grid, model.cfg.num_classes)
    npos = positive.sum().clamp(min=1).float()
    fl = focal_loss(cell_logits, positive, w.focal_alpha, w.focal_gamma)
    cells = (fl * (~ignore)).sum() / npos
    presence_logit, _, _ = model.pool(cell_logits, cell_boxes, feats)
    if w.presence_pos_weight == 1.0:  # the call every existing detector was trained with, kept bit for bit
        bce = F.binary_cross_entropy_with_logits(presence_logit, present.float())
    else:
        bce = F.binary_cross_entropy_with_logits(
            presence_logit, present.float(), pos_weight=presence_logit.new_tensor(w.presence_pos_weight)
        )
    if positive.any():
        pb, tb = cell_boxes[positive], target[positive]
        l1 = (pb - tb).abs().sum(-1).mean()
        giou = (1 - generalized_iou(pb, tb)).mean()
    else:
        l1 = giou = cell_logits.sum() * 0
    total = w.cells * cells + w.presence * bce + w.l1 * l1 + w.giou * giou
    terms = {"loss": total, "cells": cells, "bce": bce, "l1": l1, "giou": giou}
    return total, {k: float(v.detach()) for k, v in terms.items()}
