"""A small CPU-trainable detector with one query per class (a DETR-like head without set matching).

The paper (Fig. 2, III-D) takes per-class detections and 256-d decoder features from DETR, as the lineage
(SAVN -> IOM) does. DETR needs ImageNet-pretrained backbones and days of GPU training; neither pretrained
weights nor a GPU are available here. Because the table keeps only the *best detection per class*, a DETR
with one learned query per class already gives the right output shape, and with one query per class the
Hungarian matching reduces to the identity. This module is that reduced DETR, sized for 64x64 frames:

* backbone: 5 conv3x3-BN-ReLU layers (strides 2, 2, 1, 2, 1): ``[N, 3, 64, 64] -> [N, C, 8, 8]``;
* memory: 1x1 projection to ``dim`` channels plus fixed 2-D sine-cosine positional embeddings
  (``[N, 64, dim]`` tokens);
* decoder: 22 learned class queries, one multi-head cross-attention layer over the memory and an MLP, each
  with a residual connection and LayerNorm (DETR's decoder layer without self-attention);
* heads: presence logit per class (a class-specific linear read-out of its query) and a shared box head
  that refines a box anchored at the point the class query attends to (see :meth:`ClassQueryDetector.forward`).

The per-class decoder output (``dim`` = 64 by default) is the feature stored in the detection table.

Loss (:func:`detection_loss`): binary cross-entropy of the presence logits over every (image, class) pair,
plus, over the present pairs, ``l1_weight`` x L1 + ``giou_weight`` x (1 - GIoU) on normalised boxes
(DETR's box losses with its weights 5 and 2).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..constants import NUM_CATEGORIES


@dataclass
class DetectorConfig:
    """Architecture of :class:`ClassQueryDetector`."""

    image_size: int = 64
    """Side of the square input frames, pixels (the dataset's image size)."""
    widths: tuple[int, int, int] = (16, 32, 64)
    """Channels of the three backbone stages (a stride-2 conv3x3; then a stride-2 and a stride-1 conv3x3
    twice): about 7.5 M multiply-adds per 64x64 frame, so that training fits in minutes on 2 CPU cores."""
    dim: int = 64
    """Width of the memory tokens and class queries; also the stored per-class feature size."""
    heads: int = 4
    """Attention heads of the cross-attention."""
    mlp_ratio: int = 2
    """Hidden width of the decoder MLP as a multiple of ``dim``."""
    num_classes: int = NUM_CATEGORIES
    """Number of class queries (the 22 target classes)."""

    @classmethod
    def from_dict(cls, d: dict) -> "DetectorConfig":
        d = dict(d)
        if "widths" in d:
            d["widths"] = tuple(int(w) for w in d["widths"])
        known = set(cls.__dataclass_fields__)
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown detector config fields: {sorted(unknown)}")
        return cls(**d)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["widths"] = list(self.widths)
        return d


def sincos_2d(grid: int, dim: int) -> torch.Tensor:
    """``[grid*grid, dim]`` fixed 2-D sine-cosine positional embedding (half the channels for y, half for x)."""
    if dim % 4:
        raise ValueError(f"dim must be a multiple of 4, got {dim}")
    q = dim // 4
    omega = 1.0 / 10000 ** (torch.arange(q, dtype=torch.float64) / q)
    ys, xs = torch.meshgrid(torch.arange(grid, dtype=torch.float64), torch.arange(grid, dtype=torch.float64),
                            indexing="ij")

    def emb(pos: torch.Tensor) -> torch.Tensor:
        out = pos.reshape(-1, 1) * omega[None]  # [L, q]
        return torch.cat([out.sin(), out.cos()], dim=1)

    return torch.cat([emb(ys), emb(xs)], dim=1).float()


def _conv(cin: int, cout: int, stride: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class ClassQueryDetector(nn.Module):
    """RGB frames -> per-class presence logits, boxes and features (module docstring)."""

    def __init__(self, cfg: DetectorConfig | None = None):
        super().__init__()
        self.cfg = cfg = cfg or DetectorConfig()
        if cfg.image_size % 8:
            raise ValueError(f"image_size must be a multiple of 8, got {cfg.image_size}")
        w1, w2, w3 = cfg.widths
        self.backbone = nn.Sequential(_conv(3, w1, 2), _conv(w1, w2, 2), _conv(w2, w2, 1), _conv(w2, w3, 2),
                                      _conv(w3, w3, 1))
        self.proj = nn.Conv2d(w3, cfg.dim, 1)
        self.register_buffer("pos_embed", sincos_2d(cfg.image_size // 8, cfg.dim), persistent=False)
        self.query = nn.Parameter(torch.randn(cfg.num_classes, cfg.dim) * 0.1)
        self.attn = nn.MultiheadAttention(cfg.dim, cfg.heads, batch_first=True)
        self.norm1 = nn.LayerNorm(cfg.dim)
        self.mlp = nn.Sequential(nn.Linear(cfg.dim, cfg.dim * cfg.mlp_ratio), nn.ReLU(inplace=True),
                                 nn.Linear(cfg.dim * cfg.mlp_ratio, cfg.dim))
        self.norm2 = nn.LayerNorm(cfg.dim)
        self.cls_weight = nn.Parameter(torch.zeros(cfg.num_classes, cfg.dim))
        # Start from the base rate of a class being in view (about 5 %), as detectors' focal-loss init does.
        self.cls_bias = nn.Parameter(torch.full((cfg.num_classes,), -3.0))
        self.box_head = nn.Sequential(nn.Linear(cfg.dim, cfg.dim), nn.ReLU(inplace=True), nn.Linear(cfg.dim, 4))
        nn.init.zeros_(self.box_head[2].weight)  # start: boxes of half the frame around the reference point
        nn.init.zeros_(self.box_head[2].bias)
        g = cfg.image_size // 8
        c = (torch.arange(g, dtype=torch.float32) + 0.5) / g
        yy, xx = torch.meshgrid(c, c, indexing="ij")
        self.register_buffer("cell_xy", torch.stack([xx.reshape(-1), yy.reshape(-1)], dim=1), persistent=False)

    @staticmethod
    def normalize(rgb: torch.Tensor) -> torch.Tensor:
        """uint8 ``[N, H, W, 3]`` (or float in [0, 255], channels last) -> float ``[N, 3, H, W]`` around 0."""
        return (rgb.permute(0, 3, 1, 2).float() / 255.0 - 0.5) / 0.25

    def _decode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(per-class features ``[N, 22, dim]``, attention-weighted reference point ``[N, 22, 2]`` in (0, 1))."""
        m = self.proj(self.backbone(x))  # [N, dim, h, w]
        m = m.flatten(2).transpose(1, 2) + self.pos_embed  # [N, L, dim]
        q = self.query.unsqueeze(0).expand(x.shape[0], -1, -1)  # [N, 22, dim]
        a, w = self.attn(q, m, m, need_weights=True, average_attn_weights=True)  # w: [N, 22, L]
        f = self.norm1(q + a)
        return self.norm2(f + self.mlp(f)), w @ self.cell_xy

    def forward_features(self, x: torch.Tensor) -> torch.Tensor:
        """Normalised ``[N, 3, S, S]`` -> per-class decoder features ``[N, 22, dim]``."""
        return self._decode(x)[0]

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Normalised ``[N, 3, S, S]`` -> (presence logits ``[N, 22]``, boxes ``[N, 22, 4]`` normalised
        continuous ``[x0, y0, x1, y1]`` in [0, 1], features ``[N, 22, dim]``).

        Boxes are anchored at the class query's reference point (where it attends), as in Conditional /
        Deformable DETR, which makes box regression converge much faster than from the query alone: the
        anchor ``(ax, ay) = sigmoid(logit(ref) + d[:2])``, the size ``(w, h) = sigmoid(d[2:])``, and the box
        ``x0 = ax (1 - w), x1 = x0 + w`` (likewise in y), so it is never inverted nor outside the frame."""
        f, ref = self._decode(x)
        logits = (f * self.cls_weight).sum(-1) + self.cls_bias  # [N, 22]
        d = self.box_head(f)  # [N, 22, 4]
        ref = ref.clamp(1e-4, 1 - 1e-4)
        anchor = torch.sigmoid(torch.log(ref / (1 - ref)) + d[..., :2])  # [N, 22, 2]
        size = torch.sigmoid(d[..., 2:])
        lo = anchor * (1 - size)
        return logits, torch.cat([lo, lo + size], dim=-1), f


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
    """Weights of the terms of :func:`detection_loss` (DETR's box weights)."""

    presence: float = 1.0
    """Binary cross-entropy of the presence logits."""
    l1: float = 5.0
    """L1 distance of normalised box corners, over present pairs."""
    giou: float = 2.0
    """1 - GIoU of the boxes, over present pairs."""


def detection_loss(logits: torch.Tensor, boxes: torch.Tensor, present: torch.Tensor, gt_boxes: torch.Tensor,
                   w: LossWeights | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """Total loss and its terms. ``present`` ``[N, 22]`` bool; ``gt_boxes`` ``[N, 22, 4]`` normalised
    continuous boxes (ignored where not present)."""
    w = w or LossWeights()
    bce = F.binary_cross_entropy_with_logits(logits, present.float())
    if present.any():
        pb, gb = boxes[present], gt_boxes[present]
        l1 = (pb - gb).abs().sum(-1).mean()
        giou = (1 - generalized_iou(pb, gb)).mean()
    else:
        l1 = giou = logits.sum() * 0
    total = w.presence * bce + w.l1 * l1 + w.giou * giou
    terms = {"loss": total, "bce": bce, "l1": l1, "giou": giou}
    return total, {k: float(v.detach()) for k, v in terms.items()}


def pixel_to_unit(boxes: np.ndarray, image_size: int) -> np.ndarray:
    """Inclusive pixel boxes ``[x0, y0, x1, y1]`` -> continuous boxes normalised to [0, 1]."""
    b = np.asarray(boxes, dtype=np.float32)
    out = np.stack([b[..., 0], b[..., 1], b[..., 2] + 1, b[..., 3] + 1], axis=-1) / float(image_size)
    return out.astype(np.float32)


def unit_to_pixel(boxes: np.ndarray, image_size: int) -> np.ndarray:
    """Inverse of :func:`pixel_to_unit` (float pixels, inclusive corners; at least one pixel wide)."""
    b = np.asarray(boxes, dtype=np.float32) * float(image_size)
    x1 = np.maximum(b[..., 2] - 1, b[..., 0])  # a box narrower than a pixel still covers one column
    y1 = np.maximum(b[..., 3] - 1, b[..., 1])
    return np.stack([b[..., 0], b[..., 1], x1, y1], axis=-1).astype(np.float32)
