"""``tsnav features``: encode every state of every scene once and cache the feature maps (DESIGN.md data flow).

Per scene folder this writes ``features_<name>.hdf5`` with

* ``features``: ``(S, C, h, w)`` float16, the encoder's patch tokens as a grid (ViT: C = embed dim, h = w =
  img_size / patch; ResNet18: the 512 x h x w map of ``layer4``), all patches visible (no masking), in the
  order of ``Scene.keys`` (sorted state keys);
* ``keys``: ``(S,)`` the state keys;
* attributes: ``encoder`` (the spec), ``arch``, ``method``, ``img_size``, ``channels``, ``grid``,
  ``fingerprint`` (hash of the weights), ``config`` (JSON).

Each scene is written to a temp file and renamed, so a scene file that exists is complete; a rerun skips
scenes whose file was made by the same encoder (same fingerprint) and refuses to overwrite one made by
another encoder unless ``--overwrite``.

Encoder specs (``--encoder``):

* a pretraining run folder (``encoder.safetensors`` inside) or a ``tsnav`` encoder ``.safetensors`` file;
* ``vit:PATH`` published ViT / MAE / VC-1 weights (timm layout, safetensors or .pth) with ``--model``,
  ``--patch``, ``--img-size``;
* ``resnet18:PATH`` a torchvision-layout ResNet18 state dict (e.g. ImageNet weights the user has locally);
* ``untrained:vit_tiny`` (any ViT size) or ``untrained:resnet18``: random initialisation (seed 0), the
  "no pretraining" reference of the probe.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import torch
import torch.nn as nn
from tqdm import tqdm

from ..atomic import atomic_path
from ..data import lineage as L
from ..data.reader import MIRROR_SUFFIX, list_scenes, load_scene, read_stack
from ..checkpoint import load_tensors, weights_digest
from ..distributed import resolve_device
from ..errors import CommandError
from ..scene_pool import as_is, map_scenes
from .data import normalize_rgb, resize_rgb
from .archs import ENCODER_ARCHS, arch_of, seeded_untrained, untrained_names
from .model import SIZES


@dataclass
class Encoder:
    """A frozen image encoder: normalised RGB ``[N, 3, S, S]`` -> feature map ``[N, C, h, w]``."""

    module: nn.Module
    spec: str
    arch: str  # "vit" or "resnet18"
    method: str  # how it was trained: demae / mae / demae-crop / resnet18-sup / torchvision / timm / untrained
    img_size: int
    fingerprint: str  # sha256 of the weights (identifies the encoder across reruns)
    config: dict

    @torch.no_grad()
    def encode(self, rgb: torch.Tensor) -> torch.Tensor:
        """Feature map of ImageNet-normalised RGB ``[N, 3, img_size, img_size]``."""
        self.module.eval()
        return self.module.feature_map(rgb)

    @property
    def device(self) -> torch.device:
        return next(self.module.parameters()).device

    def attrs(self) -> dict:
        return {
            "encoder": self.spec,
            "arch": self.arch,
            "method": self.method,
            "img_size": self.img_size,
            "fingerprint": self.fingerprint,
            "config": json.dumps(self.config, sort_keys=True),
        }


def _fingerprint(module: nn.Module) -> str:
    """Identifies an encoder: :func:`~tsnav.checkpoint.weights_digest` of its weights without the decoder (first
    16 hex digits)."""
    return weights_digest(module.state_dict(), skip=("decoder", "mask_token", "fc."))[:16]


def load_encoder(
    spec: str, model: str = "vit_base", patch_size: int = 16, img_size: int = 224, device: str | torch.device = "cpu"
) -> Encoder:
    """Build the frozen encoder named by ``spec`` (see the module docstring for the forms); the architectures
    are those of :mod:`tsnav.pretrain.archs` (``<arch>:PATH`` for foreign weights of a registered one)."""
    kind, _, rest = spec.partition(":")
    if kind == "untrained" and rest:
        got = seeded_untrained(rest, patch_size, img_size)
        if got is None:
            raise ValueError(f"unknown encoder {spec!r}: untrained:<{'|'.join(untrained_names())}>")
        (m, arch, cfg), size, method = got, img_size, "untrained"
    elif kind in ENCODER_ARCHS and ENCODER_ARCHS[kind].from_weights is not None and rest:
        a = ENCODER_ARCHS[kind]
        m, cfg = a.from_weights(rest, model, patch_size, img_size)
        arch, method, size = kind, a.foreign_method, img_size
    else:
        path = Path(spec)
        if path.is_dir():
            path = path / "encoder.safetensors"
            if not path.exists():
                raise FileNotFoundError(f"{spec}: no encoder.safetensors (is the pretraining run finished?)")
        if not path.is_file():
            raise FileNotFoundError(
                f"{spec}: no such encoder (run folder, .safetensors file, vit:PATH, resnet18:PATH or untrained:NAME)"
            )
        sd, meta = load_tensors(path)
        if meta.get("format") != "tsnav-encoder":
            raise ValueError(f"{path}: not a tsnav encoder file (use vit:PATH or resnet18:PATH for other weights)")
        arch, method = meta["arch"], meta.get("method", "?")
        cfg = json.loads(meta.get("config") or "{}")
        m, size = arch_of(arch).from_file(cfg, img_size)
        own = m.encoder_state_dict()
        if arch == "vit" and set(own) != set(sd):
            raise ValueError(f"{path}: keys do not match the ViT in its metadata")
        missing = set(own) - set(sd)
        if missing:
            raise ValueError(f"{path}: missing keys {sorted(missing)[:5]}")
        m.load_state_dict(sd, strict=False)
    m = m.to(device).eval()
    for p in m.parameters():
        p.requires_grad_(False)
    return Encoder(m, spec, arch, method, int(size), _fingerprint(m), cfg)


def default_name(spec: str) -> str:
    """Feature-file name of an encoder spec: run folder name, file stem, or ``untrained_<size>``."""
    kind, _, rest = spec.partition(":")
    if (kind == "untrained" or kind in ENCODER_ARCHS) and rest:
        base = rest if kind == "untrained" else Path(rest).stem
        name = f"{kind}_{base}"
    else:
        p = Path(spec)
        name = p.name if p.is_dir() else p.stem
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name)


def iter_scene_features(encoder: Encoder, scene_dir: Path, keys, batch_size: int = 64, mirror: bool = False):
    """Yield ``(start, features)`` batches: float32 ``(b, C, h, w)`` features of the frames ``keys[start:start + b]``
    of ``scene_dir/images.hdf5``, each frame resized to ``encoder.img_size`` and ImageNet-normalised; with
    ``mirror``, each frame flipped left to right first (the frames of :meth:`Scene.mirrored
    <tsnav.data.reader.Scene.mirrored>`)."""
    with h5py.File(scene_dir / "images.hdf5", "r") as fi:
        missing = [k for k in keys[:] if k not in fi]
        if missing:
            raise ValueError(f"{scene_dir}: images.hdf5 lacks state {missing[0]!r} ({len(missing)} missing)")
        for a in range(0, len(keys), batch_size):
            rgb = torch.from_numpy(read_stack(fi, keys[a : a + batch_size])).permute(0, 3, 1, 2)
            if mirror:
                rgb = rgb.flip(-1)
            x = normalize_rgb(resize_rgb(rgb, encoder.img_size).to(encoder.device))
            yield a, encoder.encode(x).float().cpu().numpy()


def scene_features(
    encoder: Encoder, scene_dir: Path, keys: np.ndarray, batch_size: int = 64, bar=None, mirror: bool = False
) -> np.ndarray:
    """``(S, C, h, w)`` float16 features of the frames ``keys`` of ``scene_dir/images.hdf5``, in that order
    (flipped left to right first with ``mirror``)."""
    out = None
    for a, f in iter_scene_features(encoder, scene_dir, keys, batch_size, mirror):
        if out is None:
            out = np.empty((len(keys),) + f.shape[1:], dtype=np.float16)
        out[a : a + len(f)] = f.astype(np.float16)
        if bar is not None:
            bar.update(len(f))
    return out


def cache_features(
    encoder: Encoder,
    root: str | Path,
    name: str,
    batch_size: int = 64,
    split: str | None = None,
    overwrite: bool = False,
    progress: bool = True,
    workers: int = 0,
    mirror: bool = False,
) -> list[Path]:
    """Write ``features_<name>.hdf5`` into every complete scene of ``root`` (or of ``split``); resumable.

    ``mirror``: the features of the frames flipped left to right, as ``features_<name>-mirror.hdf5`` (file
    attribute ``mirror`` = 1), which :meth:`Scene.mirrored <tsnav.data.reader.Scene.mirrored>` scenes read.

    ``workers`` >= 1: the scenes are encoded by that many processes on one torch thread each
    (:func:`tsnav.scene_pool.map_scenes`; 1: in this process, on one thread; the files are the same bytes for
    every value). 0 (the default): in this process on the caller's torch threads, one scene after the other.
    Returns the feature files (written or already present).
    """
    scenes = [p for p in list_scenes(root, split=split)]
    if not scenes:
        raise ValueError(f"{root}: no complete scene folder" + (f" of split {split}" if split else ""))
    no_img = [p.name for p in scenes if not (p / "images.hdf5").exists()]
    if no_img:
        raise ValueError(f"{root}: scene {no_img[0]} has no images.hdf5 (build the world with images)")
    written = []
    todo = []
    file_name = name + MIRROR_SUFFIX if mirror else name
    attrs = dict(encoder.attrs(), mirror=1) if mirror else encoder.attrs()
    for p in scenes:
        f = p / f"features_{file_name}.hdf5"
        if f.exists() and not overwrite:
            with h5py.File(f, "r") as h:
                fp = h.attrs.get("fingerprint")
                fm = int(h.attrs.get("mirror", 0))
            if fm != int(mirror):
                raise ValueError(
                    f"{f} holds features of {'flipped' if fm else 'unflipped'} frames; use another "
                    f"--name or --overwrite"
                )
            if fp != encoder.fingerprint:
                raise ValueError(f"{f} was made by another encoder ({h5py_str(fp)}); use another --name or --overwrite")
            written.append(f)
            continue
        todo.append(p)
    scenes_keys = [(p, load_scene(p).keys) for p in todo]
    bar = tqdm(
        total=sum(len(k) for _, k in scenes_keys),
        desc=f"features {file_name}",
        unit="img",
        disable=not progress,
        dynamic_ncols=True,
    )
    try:
        if workers >= 1:
            tasks = [(p, keys, batch_size, file_name, mirror, attrs) for p, keys in scenes_keys]
            for i, f in map_scenes(_feature_task, tasks, as_is, encoder, workers):
                written.append(f)
                bar.update(len(scenes_keys[i][1]))
        else:
            for p, keys in scenes_keys:
                feats = scene_features(encoder, p, keys, batch_size, bar, mirror)
                f = p / f"features_{file_name}.hdf5"
                write_feature_file(f, feats, keys, attrs)
                written.append(f)
    finally:
        bar.close()
    return sorted(written)


def _feature_task(encoder: Encoder, task) -> Path:
    """One scene's feature file, in a worker of :func:`cache_features`."""
    p, keys, batch_size, file_name, mirror, attrs = task
    f = p / f"features_{file_name}.hdf5"
    write_feature_file(f, scene_features(encoder, p, keys, batch_size, mirror=mirror), keys, attrs)
    return f


def write_feature_file(path: str | Path, features: np.ndarray, keys, attrs: dict) -> None:
    """Write one scene's feature cache ``features_<name>.hdf5`` atomically: ``features`` ``(S, C, g, g)`` in the
    row order of ``keys`` (state keys), the ``attrs`` describing the encoder (in their order), then ``channels``
    = C and ``grid`` = g. The one writer of the format (encoders here, pooled pixels in :mod:`.pixels`)."""
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as h:
        h.create_dataset("features", data=features)
        h.create_dataset("keys", data=np.asarray(keys, dtype="S"))
        for k, v in attrs.items():
            h.attrs[k] = v
        h.attrs["channels"], h.attrs["grid"] = int(features.shape[1]), int(features.shape[2])


def _h5_attr(path: Path, name: str):
    """A file attribute of an HDF5 file as a str (None when absent or unreadable)."""
    try:
        with h5py.File(path, "r") as f:
            v = f.attrs.get(name)
    except OSError:
        return None
    return v.decode() if isinstance(v, bytes) else v


def write_resnet_features(
    scene_dir: str | Path, encoder, keys, batch_size: int = 16, bar=None, overwrite: bool = False
) -> bool:
    """Write the lineage's ``resnet18_featuremap.hdf5`` into ``scene_dir``: one float32 ``(1, 512, 7, 7)`` dataset per
    state key of ``keys``, ResNet18's last feature map of the frame resized to 224 x 224 (ImageNet-normalised, as
    :func:`cache_features`); atomic (temporary file renamed when complete).

    ``encoder``: an :class:`Encoder` of arch ``resnet18`` with input size 224.
    Returns False when the file exists and was made by the same encoder (fingerprint) and ``overwrite`` is
    off; raises ``ValueError`` for another encoder's file without ``overwrite``.
    """
    if encoder.arch != "resnet18" or encoder.img_size != L.RESNET_INPUT_SIZE:
        raise ValueError(
            f"the lineage's {L.RESNET_FILE} holds ResNet18 maps of {L.RESNET_INPUT_SIZE}px frames; "
            f"encoder {encoder.spec} is {encoder.arch} at {encoder.img_size}px"
        )
    scene_dir = Path(scene_dir)
    out = scene_dir / L.RESNET_FILE
    if out.exists() and not overwrite:
        fp = _h5_attr(out, "fingerprint")
        if fp == encoder.fingerprint:
            return False
        raise ValueError(f"{out} exists and was made by another encoder ({fp}); pass --overwrite to replace it")
    with atomic_path(out) as tmp, h5py.File(tmp, "w") as f:
        for a, feats in iter_scene_features(encoder, scene_dir, keys, batch_size):
            if feats.shape[1:] != L.RESNET_SHAPE[1:]:
                raise ValueError(f"encoder {encoder.spec} gives {feats.shape[1:]} maps, expected {L.RESNET_SHAPE[1:]}")
            for k, x in zip(keys[a : a + len(feats)], feats):
                f.create_dataset(str(k), data=x[None].astype(np.float32), track_times=False)
            if bar is not None:
                bar.update(len(feats))
        f.attrs["encoder"] = encoder.spec
        f.attrs["fingerprint"] = encoder.fingerprint
        f.attrs["input_size"] = L.RESNET_INPUT_SIZE
    return True


def h5py_str(x) -> str:
    return x.decode() if isinstance(x, bytes) else str(x)


def _cache_file(scene_dir: str | Path, name: str) -> Path:
    """A scene's feature cache ``features_<name>.hdf5``; ``FileNotFoundError`` when it is missing."""
    f = Path(scene_dir) / f"features_{name}.hdf5"
    if not f.exists():
        raise FileNotFoundError(f"{f}: no feature cache (run `tsnav features`)")
    return f


def feature_fingerprint(scene_dir: str | Path, name: str) -> str | None:
    """The ``fingerprint`` attribute (the encoder's weights) of a scene's feature cache, or None when it has none;
    ``FileNotFoundError`` when the cache is missing."""
    with h5py.File(_cache_file(scene_dir, name), "r") as h:
        return h5py_str(h.attrs["fingerprint"]) if "fingerprint" in h.attrs else None


def read_features(scene_dir: str | Path, name: str) -> tuple[np.ndarray, np.ndarray, dict]:
    """``(features (S, C, h, w) float16, keys (S,) str, attrs)`` of a scene's feature cache."""
    with h5py.File(_cache_file(scene_dir, name), "r") as h:
        return (
            h["features"][()],
            h["keys"][()].astype(str),
            {k: h5py_str(v) if isinstance(v, (bytes, str)) else v for k, v in h.attrs.items()},
        )


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--encoder",
        required=True,
        help="pretraining run folder, encoder .safetensors, vit:PATH, resnet18:PATH or untrained:NAME",
    )
    parser.add_argument("--data", required=True, help="dataset root")
    parser.add_argument("--name", default=None, help="feature file name features_<name>.hdf5 (default: from --encoder)")
    parser.add_argument("--split", default=None, help="only scenes of this split (default: all)")
    parser.add_argument("--model", default="vit_base", choices=sorted(SIZES), help="ViT size for vit:/untrained:")
    parser.add_argument("--patch", type=int, default=16, help="patch size for vit:/untrained:")
    parser.add_argument("--img-size", type=int, default=224, help="input size for vit:/resnet18:/untrained:")
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda")
    parser.add_argument("--overwrite", action="store_true", help="recompute files made by another encoder")
    parser.add_argument(
        "--mirror",
        action="store_true",
        help="the features of the frames flipped left to right, written as features_<name>-mirror.hdf5 "
        "(for training on mirrored rooms: `tsnav train --mirror`)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=0,
        help="CPU processes sharing the scenes, one torch thread each (e.g. 2 on a 2-core machine; "
        "the files are the same for any value); 0 (default): this process alone",
    )
    parser.add_argument("--quiet", action="store_true")


def run(args: argparse.Namespace) -> int:
    if args.workers < 0:
        raise CommandError("--workers must be >= 0")
    enc = load_encoder(args.encoder, args.model, args.patch, args.img_size, resolve_device(args.device))
    if args.workers and enc.device.type != "cpu":
        raise CommandError("--workers shares the scenes over CPU processes: use it with --device cpu")
    name = args.name or default_name(args.encoder)
    files = cache_features(
        enc,
        args.data,
        name,
        args.batch_size,
        args.split,
        args.overwrite,
        not args.quiet,
        workers=args.workers,
        mirror=args.mirror,
    )
    print(
        f"features_{name}{MIRROR_SUFFIX if args.mirror else ''}.hdf5 in {len(files)} scenes ({enc.arch}, {enc.method}, input {enc.img_size}px)"
    )
    return 0
