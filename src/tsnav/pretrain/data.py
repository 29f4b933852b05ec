"""RGB-D pretraining images from the offline dataset (paper §III-C, "Data Collection and Pretraining").

Images come from the TRAIN scenes only (``list_scenes(root, split="train")``); each scene folder stores
``images.hdf5`` (one uint8 ``H x W x 3`` dataset per state key) and ``depth.hdf5`` (one float32 ``H x W``
dataset per state key, metres). Frames are resized to the model's square input on load.

Augmentation (batched, on tensors): horizontal flip only (the paper's setting; depth flips with RGB);
``crop=True`` adds a random resized crop applied identically to RGB and depth (the paper's "w/ crop"
ablation of Table III). All randomness is drawn from an explicit ``torch.Generator`` for the whole global
batch and then sliced per process, so runs are reproducible, resumable and independent of the number of
processes.

Normalisation: RGB with the ImageNet mean/std; the depth target is ``(metres - DEPTH_MEAN) / DEPTH_STD``
after clipping to ``[0, MAX_DEPTH]`` (non-finite depths become ``MAX_DEPTH``). Standardising depth like RGB
gives both terms of the DE-MAE loss a comparable scale, which is what "identical weights" (§III-C) needs to
mean anything: a depth target in plain metres / 5 has a variance ~100x smaller than normalised RGB and
barely moved the encoder in our runs.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import torch
import torch.nn.functional as F

from ..constants import NUM_CATEGORIES
from ..data.reader import SceneFormatError, list_scenes, load_scene, read_stack


IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
#: Depth target = (metres - DEPTH_MEAN) / DEPTH_STD (indoor depths, standardised like ImageNet RGB).
DEPTH_MEAN = 2.0
DEPTH_STD = 1.0
#: Depths beyond this many metres (and non-finite ones) are clipped to it.
MAX_DEPTH = 10.0


@dataclass
class AugmentConfig:
    """Batch augmentation (§III-C: flip only; crop is the "w/ crop" ablation)."""

    flip_prob: float = 0.5
    """Probability of a horizontal flip per image (RGB and depth together)."""
    crop: bool = False
    """Random resized crop, identical for RGB and depth (paper's "DE-MAE w/ crop")."""
    crop_scale: tuple[float, float] = (0.2, 1.0)
    """Range of the crop's area as a share of the image (MAE's RandomResizedCrop)."""
    crop_ratio: tuple[float, float] = (3 / 4, 4 / 3)
    """Range of the crop's aspect ratio (width / height)."""


class RGBDImages:
    """All (RGB, depth) frames of a split, addressed by a global index (scene-major, sorted keys).

    Args:
        root: dataset root folder.
        split: ``"train"`` for pretraining (the paper's data), ``"val"`` for probes and pictures.
        img_size: side of the square output frames, pixels.
        labels: also provide ``[22]`` multi-label "category visible" targets (``Scene.pixels >= min
            pixels``), for the supervised ResNet18 baseline and the probe.
        preload: read every frame into memory at construction (uint8 RGB, float16 metres); otherwise
            frames are read from the HDF5 files per batch (file handles opened lazily per process).
        max_scenes: use only the first this many scenes (None: all).
    """

    def __init__(
        self,
        root: str | Path,
        split: str = "train",
        img_size: int = 224,
        labels: bool = False,
        preload: bool = True,
        max_scenes: int | None = None,
    ) -> None:
        self.root = Path(root)
        self.split, self.img_size, self.with_labels, self.preload = split, int(img_size), labels, preload
        scenes = list_scenes(self.root, split=split)
        scenes = [p for p in scenes if (p / "images.hdf5").exists() and (p / "depth.hdf5").exists()]
        if max_scenes is not None:
            scenes = scenes[:max_scenes]
        if not scenes:
            raise ValueError(f"{self.root}: no complete {split} scene with images.hdf5 and depth.hdf5")

        self.scenes: list[Path] = scenes
        self.keys: list[np.ndarray] = []
        self.labels: list[np.ndarray] = []
        for p in scenes:
            try:
                with h5py.File(p / "images.hdf5", "r") as fi, h5py.File(p / "depth.hdf5", "r") as fd:
                    keys = np.array(sorted(set(fi.keys()) & set(fd.keys())))
            except OSError as e:
                raise SceneFormatError(f"{p}: unreadable images/depth ({e})") from None
            self.keys.append(keys)
            if labels:
                self.labels.append(visible_categories(p, keys))
        counts = np.array([len(k) for k in self.keys], dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(counts)])
        self._files: dict = {}
        self._pid = os.getpid()
        self._rgb: list[torch.Tensor] = []
        self._depth: list[torch.Tensor] = []
        if preload:
            for si in range(len(scenes)):
                rgb, depth = self._read(si, np.arange(len(self.keys[si])))
                self._rgb.append(rgb)
                self._depth.append(depth.half())

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def locate(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Global indices -> (scene index, row within the scene)."""
        index = np.asarray(index, dtype=np.int64)
        if index.size and (index.min() < 0 or index.max() >= len(self)):
            raise IndexError(f"image index out of range [0, {len(self)})")
        si = np.searchsorted(self.offsets, index, side="right") - 1
        return si, index - self.offsets[si]

    def key(self, index: int) -> tuple[Path, str]:
        si, row = self.locate(np.array([index]))
        return self.scenes[int(si[0])], str(self.keys[int(si[0])][int(row[0])])

    def _handles(self, si: int):
        if self._pid != os.getpid():  # forked worker: never share HDF5 handles across processes
            self._files, self._pid = {}, os.getpid()
        if si not in self._files:
            p = self.scenes[si]
            self._files[si] = (h5py.File(p / "images.hdf5", "r"), h5py.File(p / "depth.hdf5", "r"))
        return self._files[si]

    def _read(self, si: int, rows: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Frames ``rows`` of scene ``si`` at ``img_size``: ``uint8 [n, 3, S, S]``, ``float32 [n, 1, S, S]`` m."""
        fi, fd = self._handles(si)
        keys = self.keys[si][rows]
        rgb = read_stack(fi, keys) if len(keys) else np.zeros((0, 1, 1, 3), np.uint8)
        depth = read_stack(fd, keys) if len(keys) else np.zeros((0, 1, 1), np.float32)
        if rgb.ndim != 4 or rgb.shape[-1] != 3 or depth.shape != rgb.shape[:3]:
            raise SceneFormatError(f"{self.scenes[si]}: expected RGB HxWx3 and depth HxW frames of the same size")
        out_rgb, out_depth = [], []
        for a in range(0, len(keys), 256):  # bounded memory while resizing a whole scene
            r = torch.from_numpy(rgb[a : a + 256]).permute(0, 3, 1, 2)
            d = torch.from_numpy(np.asarray(depth[a : a + 256], np.float32))[:, None]
            out_rgb.append(resize_rgb(r, self.img_size))
            out_depth.append(resize_depth(clean_depth(d), self.img_size))
        return torch.cat(out_rgb), torch.cat(out_depth)

    def get(self, index) -> dict[str, torch.Tensor]:
        """A batch: ``rgb uint8 [B, 3, S, S]``, ``depth float32 [B, 1, S, S]`` metres, ``labels [B, 22]``."""
        index = np.asarray(index, dtype=np.int64).reshape(-1)
        si, row = self.locate(index)
        b, s = len(index), self.img_size
        rgb = torch.empty(b, 3, s, s, dtype=torch.uint8)
        depth = torch.empty(b, 1, s, s, dtype=torch.float32)
        for scene in np.unique(si):
            sel = np.flatnonzero(si == scene)
            if self.preload:
                t = torch.from_numpy(row[sel])
                rgb[sel] = self._rgb[scene][t]
                depth[sel] = self._depth[scene][t].float()
            else:
                rgb[sel], depth[sel] = self._read(int(scene), row[sel])
        out = {"rgb": rgb, "depth": depth, "index": torch.from_numpy(index)}
        if self.with_labels:
            lab = np.zeros((b, self.labels[int(si[0])].shape[1] if b else NUM_CATEGORIES), dtype=np.float32)
            for scene in np.unique(si):
                sel = np.flatnonzero(si == scene)
                lab[sel] = self.labels[scene][row[sel]]
            out["labels"] = torch.from_numpy(lab)
        return out

    def close(self) -> None:
        for fi, fd in self._files.values():
            fi.close()
            fd.close()
        self._files = {}


class BatchView(torch.utils.data.Dataset):
    """Adapter so a ``DataLoader(BatchView(images), sampler=list_of_index_arrays, batch_size=None,
    num_workers=k)`` reads whole batches in worker processes."""

    def __init__(self, images: RGBDImages) -> None:
        self.images = images

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, index):
        return self.images.get(index)


def visible_categories(scene_path: Path, keys: np.ndarray) -> np.ndarray:
    """``[len(keys), C]`` float 0/1 (``C`` the scene's class set's size, 22 for ``ithor22``): some object of the
    category shows at least the scene's min pixels."""
    scene = load_scene(scene_path)
    vis = scene.visible_at_any_range()  # [S, O]
    out = np.zeros((scene.num_states, scene.num_categories), dtype=np.float32)
    tgt = scene.object_category >= 0
    if tgt.any():
        onehot = np.zeros((int(tgt.sum()), scene.num_categories), dtype=np.float32)
        onehot[np.arange(int(tgt.sum())), scene.object_category[tgt]] = 1
        out = ((vis[:, tgt].astype(np.float32) @ onehot) > 0).astype(np.float32)
    return out[scene.indices(keys)] if len(keys) else out[:0]


def clean_depth(depth: torch.Tensor, max_depth: float = MAX_DEPTH) -> torch.Tensor:
    """Clip depth to ``[0, max_depth]`` metres; NaN and +inf become ``max_depth``."""
    return torch.nan_to_num(depth, nan=max_depth, posinf=max_depth, neginf=0.0).clamp_(0.0, max_depth)


def resize_rgb(rgb: torch.Tensor, size: int) -> torch.Tensor:
    """``uint8 [n, 3, H, W] -> uint8 [n, 3, size, size]`` (bilinear with antialiasing; no-op at size)."""
    if rgb.shape[-1] == size and rgb.shape[-2] == size:
        return rgb.contiguous()
    x = F.interpolate(rgb.float(), size=(size, size), mode="bilinear", align_corners=False, antialias=True)
    return x.round_().clamp_(0, 255).to(torch.uint8)


def resize_depth(depth: torch.Tensor, size: int) -> torch.Tensor:
    """``[n, 1, H, W] -> [n, 1, size, size]`` metres by nearest sampling (never invents depths at edges)."""
    if depth.shape[-1] == size and depth.shape[-2] == size:
        return depth.contiguous()
    return F.interpolate(depth, size=(size, size), mode="nearest-exact")


def normalize_rgb(rgb: torch.Tensor) -> torch.Tensor:
    """``uint8 [B, 3, H, W]`` -> float, ImageNet mean/std normalised."""
    mean = torch.tensor(IMAGENET_MEAN, device=rgb.device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, device=rgb.device).view(1, 3, 1, 1)
    return (rgb.float() / 255.0 - mean) / std


def denormalize_rgb(x: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`normalize_rgb` into float ``[0, 1]`` (clamped)."""
    mean = torch.tensor(IMAGENET_MEAN, device=x.device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, device=x.device).view(1, 3, 1, 1)
    return (x * std + mean).clamp(0, 1)


def depth_to_target(depth_m: torch.Tensor) -> torch.Tensor:
    """Metres -> the DE-MAE depth target ``(d - DEPTH_MEAN) / DEPTH_STD``."""
    return (depth_m - DEPTH_MEAN) / DEPTH_STD


def target_to_depth(target: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`depth_to_target`: metres."""
    return target * DEPTH_STD + DEPTH_MEAN


def draw_augment(gen: torch.Generator, n: int, cfg: AugmentConfig) -> dict[str, torch.Tensor]:
    """Random augmentation parameters for ``n`` images from ``gen``: ``flip [n]`` bool and, with crop,
    ``box [n, 4]`` = (centre x, centre y, width, height) as shares of the image side."""
    out = {"flip": torch.rand(n, generator=gen) < cfg.flip_prob}
    if cfg.crop:
        area = torch.empty(n).uniform_(cfg.crop_scale[0], cfg.crop_scale[1], generator=gen)
        logr = torch.empty(n).uniform_(math.log(cfg.crop_ratio[0]), math.log(cfg.crop_ratio[1]), generator=gen)
        ratio = torch.exp(logr)
        w = torch.sqrt(area * ratio).clamp(max=1.0)
        h = torch.sqrt(area / ratio).clamp(max=1.0)
        cx = w / 2 + torch.rand(n, generator=gen) * (1 - w)
        cy = h / 2 + torch.rand(n, generator=gen) * (1 - h)
        out["box"] = torch.stack([cx, cy, w, h], dim=1)
    return out


def slice_augment(params: dict[str, torch.Tensor], sel) -> dict[str, torch.Tensor]:
    return {k: v[sel] for k, v in params.items()}


def apply_augment(rgb: torch.Tensor, depth: torch.Tensor, params: dict[str, torch.Tensor]):
    """Apply flip (and crop) to float ``rgb [B, 3, S, S]`` and ``depth [B, 1, S, S]`` identically.

    The crop resamples the box back to ``S x S``: bilinear for RGB, nearest for depth.
    """
    flip = params["flip"].to(rgb.device)
    if "box" in params:
        box = params["box"].to(rgb.device, rgb.dtype)
        b = rgb.shape[0]
        theta = torch.zeros(b, 2, 3, device=rgb.device, dtype=rgb.dtype)
        sign = torch.where(flip, -1.0, 1.0).to(rgb.dtype)
        theta[:, 0, 0] = box[:, 2] * sign  # output x in [-1, 1] -> input x
        theta[:, 0, 2] = box[:, 0] * 2 - 1
        theta[:, 1, 1] = box[:, 3]
        theta[:, 1, 2] = box[:, 1] * 2 - 1
        grid = F.affine_grid(theta, list(rgb.shape), align_corners=False)
        rgb = F.grid_sample(rgb, grid, mode="bilinear", padding_mode="border", align_corners=False)
        depth = F.grid_sample(depth, grid, mode="nearest", padding_mode="border", align_corners=False)
        return rgb, depth
    if flip.any():
        rgb = torch.where(flip.view(-1, 1, 1, 1), rgb.flip(-1), rgb)
        depth = torch.where(flip.view(-1, 1, 1, 1), depth.flip(-1), depth)
    return rgb, depth


def prepare_batch(
    batch: dict[str, torch.Tensor], params: dict[str, torch.Tensor] | None, device: torch.device | str = "cpu"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Batch from :meth:`RGBDImages.get` -> model inputs: normalised RGB ``[B, 3, S, S]`` and depth target
    ``[B, 1, S, S]`` (:func:`depth_to_target`), augmented with ``params`` when given."""
    rgb = normalize_rgb(batch["rgb"].to(device))
    depth = depth_to_target(batch["depth"].to(device).float())
    if params is not None:
        rgb, depth = apply_augment(rgb, depth, params)
    return rgb, depth


def scene_split_images(root: str | Path, split: str, img_size: int, **kw) -> RGBDImages | None:
    """:class:`RGBDImages` of ``split``, or None when the split has no scene with images."""
    try:
        return RGBDImages(root, split=split, img_size=img_size, **kw)
    except ValueError:
        return None
