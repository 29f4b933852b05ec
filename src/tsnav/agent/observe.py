"""What the agent sees (paper III-D): cached encoder features and the target's detection, gathered for a
batch of global state ids of a :class:`~tsnav.sim.batch.SceneBank`.

* :func:`load_bank_features` stacks the per-scene feature caches ``features_<name>.hdf5`` of
  :mod:`tsnav.pretrain.features` into one ``(total_S, C, h, w)`` float16 tensor in the bank's global order.
* :class:`DetectionTable` holds, per state and target category, the detector's confidence and box (the
  lineage stores the best detection per class), from the detection table installed in the bank (``tsnav
  detect``: the learned detector, or the oracle when named explicitly). Without one it refuses: the agent's
  inputs are the image features and a detector's table, as in the paper, never ground truth.
* :class:`Observer` turns ``(state, target)`` arrays into an :class:`AgentObs` with gathers only. The
  detection feature of a box is the image feature map averaged over the box (area-weighted over the grid
  cells it covers), standing in for DETR's 256-d decoder feature of the lineage; the detector's own per-class
  features ``(S, C, D)`` (``tsnav.detect`` tables) are used instead when given.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..pretrain.features import read_features


@dataclass
class AgentObs:
    """One observation batch for :class:`~tsnav.agent.model.ActorCritic` (``B`` rows).

    Attributes:
        image: ``(B, C, h, w)`` float32 encoder feature map of the current frame.
        target: ``(B,)`` int64 target category id.
        det_score: ``(B,)`` float32 detector confidence of the target in this frame, in [0, 1].
        det_box: ``(B, 4)`` float32 box ``[x0, y0, x1, y1]`` of the target, as fractions of the image side
            (zeros when nothing is detected).
        det_feat: ``(B, D)`` float32 feature of that detection.
        pose: ``(B, 4)`` float32 ``(x m, z m, rotation deg, horizon deg)`` of the agent (AI2-THOR conventions).
        det_depth: ``(B, 4)`` float32 estimated depth inside the target's box (:class:`TargetDepth`), for an agent
            with ``AgentConfig.target_depth``; None otherwise.
        mirror: the observation of the same states in the rooms' mirror images (frames flipped left to right, the
            detector's table of the flipped frames, mirrored poses), for an agent with ``AgentConfig.mirror_policy``;
            None otherwise.
    """

    image: torch.Tensor
    target: torch.Tensor
    det_score: torch.Tensor
    det_box: torch.Tensor
    det_feat: torch.Tensor
    pose: torch.Tensor
    det_depth: torch.Tensor | None = None
    mirror: "AgentObs | None" = None

    def index(self, rows) -> "AgentObs":
        """The sub-batch ``rows`` (tensor / array of row ids or bool mask)."""
        rows = torch.as_tensor(rows)
        return AgentObs(
            *(
                None
                if getattr(self, f) is None
                else (getattr(self, f).index(rows) if f == "mirror" else getattr(self, f)[rows])
                for f in self.__dataclass_fields__
            )
        )


def load_bank_features(bank, name: str) -> torch.Tensor:
    """``(total_S, C, h, w)`` float16 tensor of the caches ``features_<name>.hdf5`` of every scene of ``bank``,
    in global state order (``features_<name>-mirror.hdf5`` for a mirrored scene, :meth:`Scene.cache_name`). Raises ``FileNotFoundError`` / ``ValueError`` naming the scene when a cache is
    missing, was written for other states, or has another shape than the others."""
    out = None
    shape = None
    for i, scene in enumerate(bank.scenes):
        own = scene.cache_name(name)  # a mirrored scene reads the features of its flipped frames
        if own != name and not (scene.path / f"features_{own}.hdf5").exists():
            raise FileNotFoundError(
                f"{scene.path}/features_{own}.hdf5: no features of the mirrored room (run "
                f"`tsnav features --mirror --name {name}` with the encoder of {name})"
            )
        feats, keys, _ = read_features(scene.path, own)
        if len(keys) != scene.num_states or not np.array_equal(keys, scene.keys):
            raise ValueError(
                f"{scene.path}/features_{own}.hdf5 does not match the scene's states "
                f"(recompute it with `tsnav features --overwrite`)"
            )
        if shape is None:
            shape = feats.shape[1:]
            out = torch.empty((bank.num_states,) + tuple(shape), dtype=torch.float16)
        elif feats.shape[1:] != shape:
            raise ValueError(
                f"{scene.path}/features_{own}.hdf5 has feature shape {feats.shape[1:]}, other scenes {shape}"
            )
        out[int(bank.offsets[i]) : int(bank.offsets[i + 1])] = torch.from_numpy(np.ascontiguousarray(feats))
    return out


#: The one-line error of an agent stage asked to observe a bank without a detection table.
NO_DETECTIONS = (
    "no detection table installed in the scene bank: the agent reads only a detector's table "
    "(run `tsnav detect --detector learned`, or pass `--detections oracle` explicitly)"
)


class DetectionTable:
    """Per-state, per-category detection of the target: ``score (S, C)`` and ``box (S, C, 4)`` (fractions), ``C`` the
    bank's class set's size (22 for ``ithor22``, 12 for ``robothor12``); ``class_set`` its name.

    From ``bank.detections`` (rows score, label, x0, y0, x1, y1 in pixels), the table of a named detector
    (``tsnav detect``; ``oracle`` when asked for by name). There is no fallback to ground truth: a bank without
    an installed table raises ``ValueError`` (:data:`NO_DETECTIONS`), so nothing privileged (the in-frame flag
    of ``bank.stage_confidence``, ground-truth boxes, distances) can reach the agent by default (issue 14).
    ``source`` is ``"detector"``.
    """

    def __init__(self, bank, features: np.ndarray | None = None):
        """``features``: optional ``(S, C, D)`` per-class detection features, row-aligned with the bank."""
        if bank.detections is None:
            raise ValueError(NO_DETECTIONS)
        det = bank.detections
        side = np.array([s.image_size or 1 for s in bank.scenes], dtype=np.float32)[bank.scene_of]
        self.score = det[..., 0].astype(np.float32)
        self.box = np.clip(det[..., 2:6] / side[:, None, None], 0.0, 1.0).astype(np.float32)
        self.source = "detector"
        self.class_set = bank.class_set.name
        self.box[self.score <= 0] = 0.0
        if features is not None and np.shape(features)[:2] != (bank.num_states, bank.num_categories):
            raise ValueError(
                f"detection features must have shape ({bank.num_states}, {bank.num_categories}, D), "
                f"got {np.shape(features)}"
            )
        self.features = None if features is None else torch.as_tensor(np.asarray(features, dtype=np.float16))


def roi_pool(image: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """Average of a feature map over a box: ``image (B, C, h, w)``, ``box (B, 4)`` fractions ``[x0, y0, x1,
    y1]`` -> ``(B, C)``. Each grid cell is weighted by the area of its overlap with the box; a box of zero
    area gives zeros."""
    b, _, h, w = image.shape
    cy = torch.arange(h, dtype=image.dtype, device=image.device) / h  # cell top edges
    cx = torch.arange(w, dtype=image.dtype, device=image.device) / w
    oy = (torch.minimum(box[:, 3:4], cy + 1.0 / h) - torch.maximum(box[:, 1:2], cy)).clamp(min=0)  # (B, h)
    ox = (torch.minimum(box[:, 2:3], cx + 1.0 / w) - torch.maximum(box[:, 0:1], cx)).clamp(min=0)  # (B, w)
    wgt = oy[:, :, None] * ox[:, None, :]  # (B, h, w)
    tot = wgt.sum(dim=(1, 2), keepdim=True)
    wgt = torch.where(tot > 0, wgt / tot.clamp(min=1e-12), torch.zeros_like(wgt))
    return torch.einsum("bchw,bhw->bc", image, wgt)


#: ``AgentConfig.target_depth`` value of the diagnostic that reads the world's true depth frames instead of an
#: estimate: privileged, so never an agent to ship; it bounds what a better estimate could give.
GROUND_TRUTH = "ground-truth"

#: Depth (metres) an estimate is clipped to, and the value of every statistic where nothing is detected.
FAR = 5.0


def box_cells(box: torch.Tensor, grid: int) -> torch.Tensor:
    """``(B, 4)`` cell bounds x0, y0, x1, y1 (int64) of boxes given as fractions of the frame, at least one cell."""
    c = torch.clamp(torch.round(box * grid).long(), 0, grid)
    lo = torch.minimum(c[:, :2], torch.full_like(c[:, :2], grid - 1))
    hi = torch.maximum(c[:, 2:], lo + 1)
    return torch.cat([lo, hi], dim=1)


def box_depth_stats(maps: torch.Tensor, box: torch.Tensor, score: torch.Tensor) -> torch.Tensor:
    """``(B, 4)``: the median, minimum and 10th percentile (the lower element: ``np.quantile(..., method="lower")``)
    of each depth map ``maps (B, G, G)`` inside its box (fractions of the frame, at least one cell), clipped to
    :data:`FAR` and divided by it, and a 1 where something is detected (``score > 0``); ``1, 1, 1, 0`` where
    nothing is. One sort over the batch; :func:`box_depth_stats_reference` is the loop beside it."""
    b, g, _ = maps.shape
    c = box_cells(box, g)
    idx = torch.arange(g, device=maps.device)
    inx = (idx[None, :] >= c[:, 0:1]) & (idx[None, :] < c[:, 2:3])
    iny = (idx[None, :] >= c[:, 1:2]) & (idx[None, :] < c[:, 3:4])
    inside = (iny[:, :, None] & inx[:, None, :]).reshape(b, -1)
    vals = torch.where(inside, maps.reshape(b, -1).float(), torch.full_like(inside, float("inf"), dtype=torch.float32))
    srt = vals.sort(dim=1).values
    n = inside.sum(dim=1)
    pick = torch.stack([(n - 1) // 2, torch.zeros_like(n), torch.floor(0.1 * (n - 1)).long()], dim=1)
    stats = srt.gather(1, pick).clamp(max=FAR) / FAR
    seen = score > 0
    far = torch.ones_like(stats)
    return torch.cat([torch.where(seen[:, None], stats, far), seen[:, None].float()], dim=1)


def box_depth_stats_reference(maps, box, score) -> np.ndarray:
    """Slow reference of :func:`box_depth_stats`: one box at a time, with numpy's quantiles."""
    maps, box, score = np.asarray(maps, dtype=np.float32), np.asarray(box), np.asarray(score)
    g = maps.shape[1]
    out = np.tile(np.array([1.0, 1.0, 1.0, 0.0], dtype=np.float32), (len(maps), 1))
    for r in range(len(maps)):
        if score[r] <= 0:
            continue
        x0, y0, x1, y1 = box_cells(torch.as_tensor(box[r : r + 1], dtype=torch.float32), g)[0].tolist()
        patch = maps[r, y0:y1, x0:x1].ravel()
        q = [np.quantile(patch, 0.5, method="lower"), patch.min(), np.quantile(patch, 0.1, method="lower")]
        out[r, :3] = np.minimum(q, FAR) / FAR
        out[r, 3] = 1.0
    return out


class TargetDepth:
    """The depth a readout of the encoder's feature map estimates for every state of a bank
    (:mod:`tsnav.pretrain.depth_readout`), kept as ``(S, G, G)`` float16 maps; called with states and the target's
    boxes and scores it gives :func:`box_depth_stats`. Read by agents with ``AgentConfig.target_depth`` (a
    deviation from the paper)."""

    def __init__(self, maps: torch.Tensor, source: str = ""):
        self.maps, self.source = maps, source

    @classmethod
    def from_readout(cls, path, features: torch.Tensor, batch: int = 4096, fingerprint: str | None = None):
        """The readout file ``path`` run over the bank's feature maps ``features (S, C, h, w)``; ``fingerprint``
        (the feature caches' encoder) must be the one the readout was trained on (``ValueError`` otherwise)."""
        from ..pretrain.depth_readout import load_readout

        model, meta = load_readout(path)
        if fingerprint and meta.get("fingerprint") and meta["fingerprint"] != fingerprint:
            raise ValueError(
                f"{path}: a readout of the features of encoder {meta['fingerprint']} (features_{meta.get('features')}"
                f"), not of these ({fingerprint})"
            )
        maps = torch.empty(
            (features.shape[0],) + (model.ph * features.shape[2], model.pw * features.shape[3]), dtype=torch.float16
        )
        with torch.no_grad():
            for i in range(0, features.shape[0], batch):
                maps[i : i + batch] = model(features[i : i + batch].float()).half()
        return cls(maps, str(path))

    @classmethod
    def from_world(cls, bank) -> "TargetDepth":
        """The world's true depth frames (``depth.hdf5`` of each scene) averaged to the readout's grid: the
        :data:`GROUND_TRUTH` diagnostic."""
        from ..pretrain.depth_readout import GRID, scene_depth_maps

        maps = torch.empty((bank.num_states, GRID, GRID), dtype=torch.float16)
        for i, scene in enumerate(bank.scenes):
            path = scene.depth_path()
            if path is None:
                raise ValueError(f"{scene.path}: no depth.hdf5 (target_depth {GROUND_TRUTH!r} reads the depth frames)")
            # the frames of a mirrored room are flipped left to right (its features are)
            d = scene_depth_maps(path, scene.keys, flip=scene.mirror)
            maps[int(bank.offsets[i]) : int(bank.offsets[i + 1])] = torch.from_numpy(d)
        return cls(maps, GROUND_TRUTH)

    @classmethod
    def of(cls, spec: str, bank, features: torch.Tensor, features_name: str | None = None) -> "TargetDepth":
        """``AgentConfig.target_depth`` made real: :data:`GROUND_TRUTH` (:meth:`from_world`) or a readout file
        (:meth:`from_readout`, a relative path read from the working directory), checked against the encoder of
        the bank's feature caches ``features_<features_name>.hdf5`` when named."""
        if spec == GROUND_TRUTH:
            return cls.from_world(bank)
        fingerprint = None
        if features_name:
            from ..pretrain.features import feature_fingerprint

            scene = bank.scenes[0]
            fingerprint = feature_fingerprint(scene.path, scene.cache_name(features_name))
        return cls.from_readout(Path(spec), features, fingerprint=fingerprint)

    def __call__(self, state: torch.Tensor, box: torch.Tensor, score: torch.Tensor) -> torch.Tensor:
        return box_depth_stats(self.maps[state].to(box.device), box, score)


class Observer:
    """Gathers :class:`AgentObs` for global state ids of ``bank`` (array operations only).

    ``features`` is the ``(total_S, C, h, w)`` float16 tensor of :func:`load_bank_features` (may live in
    shared memory for A3C workers); ``detections`` defaults to ``DetectionTable(bank)`` (which needs a
    detection table installed in ``bank``). ``mirror``: the observer of the bank's mirror image (:func:`mirror_bank`:
    the same state ids), whose observation of the same states each observation carries as ``mirror``
    (``AgentConfig.mirror_policy``).
    """

    def __init__(
        self,
        bank,
        features: torch.Tensor,
        detections: DetectionTable | None = None,
        device: str | torch.device = "cpu",
        target_depth: TargetDepth | None = None,
        mirror: "Observer | None" = None,
    ):
        if features.shape[0] != bank.num_states:
            raise ValueError(f"features cover {features.shape[0]} states but the bank has {bank.num_states}")
        self.bank = bank
        self.features = features
        self.detections = detections or DetectionTable(bank)
        self.device = torch.device(device)
        if target_depth is not None and target_depth.maps.shape[0] != bank.num_states:
            raise ValueError(f"depth maps cover {target_depth.maps.shape[0]} states but the bank has {bank.num_states}")
        self.target_depth = target_depth
        if mirror is not None and mirror.bank.num_states != bank.num_states:
            raise ValueError(
                f"the mirror observer covers {mirror.bank.num_states} states but the bank has {bank.num_states}"
            )
        self.mirror = mirror
        self._score = torch.from_numpy(self.detections.score)
        self._box = torch.from_numpy(self.detections.box)
        self._pose = torch.from_numpy(
            np.stack(
                [bank.x, bank.z, bank.rotation.astype(np.float32), bank.horizon.astype(np.float32)], axis=1
            ).astype(np.float32)
        )

    @property
    def feature_shape(self) -> tuple[int, int, int]:
        """``(C, h, w)`` of the image features."""
        return tuple(self.features.shape[1:])

    @property
    def class_set(self) -> str:
        """Name of the bank's class set: the agent's target ids index its classes."""
        return self.bank.class_set.name

    @property
    def det_dim(self) -> int:
        """Size D of the detection feature."""
        f = self.detections.features
        return int(f.shape[-1]) if f is not None else int(self.features.shape[1])

    def __call__(self, state: np.ndarray, target: np.ndarray) -> AgentObs:
        s = torch.as_tensor(np.asarray(state, dtype=np.int64))
        g = torch.as_tensor(np.asarray(target, dtype=np.int64))
        image = self.features[s].to(self.device, torch.float32)
        score = self._score[s, g].to(self.device)
        box = self._box[s, g].to(self.device)
        if self.detections.features is not None:
            feat = self.detections.features[s, g].to(self.device, torch.float32)
        else:
            feat = roi_pool(image, box)
        return AgentObs(
            image=image,
            target=g.to(self.device),
            det_score=score,
            det_box=box,
            det_feat=feat,
            pose=self._pose[s].to(self.device),
            det_depth=None if self.target_depth is None else self.target_depth(s, box, score),
            mirror=None if self.mirror is None else self.mirror(state, target),
        )
