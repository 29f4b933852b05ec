"""A depth readout of a frozen encoder: how far is what the agent sees, estimated from its own feature map?

    tsnav analyze depth-readout --data WORLD --features NAME --out READOUT.safetensors [--epochs 1] [--seed 0]
        [--json OUT.json]

DE-MAE (paper §III-C) pretrains the encoder to predict depth beside colour; its depth decoder is left behind when
the encoder is packed into an agent (``encoder.safetensors`` holds the encoder only). This command trains a decoder
of the same shape again (a linear map of each token to 128 channels, learned position embeddings, two pre-norm
transformer blocks, a linear map of each token to its patch's depth) on the frozen, unmasked tokens that a world's
feature cache (``features_NAME.hdf5``) holds, against the world's depth frames (``depth.hdf5``, averaged to
:data:`GRID` squared, clipped to :data:`MAX_DEPTH` metres), on the train split's rooms; the val split's rooms score
it: mean absolute error in metres, and how often the median depth of a cell block agrees with the ground truth on
"within 1.5 m". Only the encoder's feature map goes in, so its estimate is something an agent may read at test
time: the stop head's ``est-depth`` input (`tsnav analyze stop-head --inputs ...,est-depth --depth-readout
READOUT.safetensors`) and agents trained with ``--target-depth READOUT.safetensors`` (``AgentConfig.target_depth``).
The model and its file: :mod:`tsnav.pretrain.depth_readout`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from ..pretrain.depth_readout import NEAR, save_readout, scene_depth_maps, score, train_readout


def scene_pairs(scene_dir: Path, features: str) -> tuple[np.ndarray, np.ndarray, dict]:
    """``(features (S, C, h, w) float16, depth (S, GRID, GRID) float16, attrs)`` of one scene folder."""
    from ..pretrain.features import read_features

    feat, keys, attrs = read_features(scene_dir, features)
    return feat, scene_depth_maps(Path(scene_dir) / "depth.hdf5", keys), attrs


def load_split(data: Path, split: str, features: str, log=print):
    """Stacked :func:`scene_pairs` of every scene of ``split``, and the feature caches' attributes (one of them)."""
    from ..data.reader import list_scenes

    scenes = list_scenes(data, split)
    if not scenes:
        raise ValueError(f"{data}: no complete scenes of split {split!r}")
    fs, ds, attrs = [], [], None
    for s in scenes:
        f, d, a = scene_pairs(s, features)
        if attrs is not None and a.get("fingerprint") != attrs.get("fingerprint"):
            raise ValueError(f"{s}: features_{features} made by another encoder than the other scenes'")
        attrs = a
        fs.append(f)
        ds.append(d)
    log(f"{split}: {len(scenes)} scenes, {sum(len(f) for f in fs)} frames")
    return np.concatenate(fs), np.concatenate(ds), attrs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze depth-readout", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--data", type=Path, required=True, help="the world (scene folders with depth.hdf5)")
    ap.add_argument("--features", required=True, help="the feature cache's name (features_NAME.hdf5)")
    ap.add_argument("--out", type=Path, required=True, help="the readout file (.safetensors)")
    ap.add_argument(
        "--epochs",
        type=int,
        default=1,
        help="passes over the train rooms' frames (one pass over the 80 iTHOR rooms took 6 min on an idle 2-core "
        "machine, with reading the frames)",
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=None, help="its scores on the train and val rooms")
    args = ap.parse_args(argv)
    if args.epochs < 1:
        print(f"tsnav analyze depth-readout: --epochs must be >= 1, got {args.epochs}", file=sys.stderr)
        return 2
    try:
        feat, depth, attrs = load_split(args.data, "train", args.features)
        vfeat, vdepth, vattrs = load_split(args.data, "val", args.features)
    except (ValueError, FileNotFoundError) as e:
        print(f"tsnav analyze depth-readout: {e}", file=sys.stderr)
        return 2
    if vattrs.get("fingerprint") != attrs.get("fingerprint"):
        print("tsnav analyze depth-readout: the val rooms' features come from another encoder", file=sys.stderr)
        return 2
    model = train_readout(feat, depth, args.epochs, args.seed)
    scores = {"train": score(model, feat, depth), "val": score(model, vfeat, vdepth)}
    # the reference a readout must beat: every cell at the train frames' mean depth of that cell
    mean_map = torch.from_numpy(depth.astype(np.float32).mean(axis=0))
    scores["val_mean_map_mae_m"] = float((torch.from_numpy(vdepth).float() - mean_map).abs().mean())
    meta = {
        "features": args.features,
        "fingerprint": str(attrs.get("fingerprint", "")),
        "epochs": str(args.epochs),
        "seed": str(args.seed),
        "scores": json.dumps(scores, sort_keys=True),
    }
    save_readout(args.out, model, meta)
    print(f"wrote {args.out}")
    for k in ("train", "val"):
        s = scores[k]
        print(
            f"{k}: {s['frames']} frames, MAE {s['mae_m']:.3f} m (under 2 m: {s['mae_under_2m']:.3f} m), "
            f"within {NEAR} m agreement {100 * s['near_agreement']:.1f} %"
        )
    print(f"val, every cell at the train frames' mean map: MAE {scores['val_mean_map_mae_m']:.3f} m")
    if args.json:
        from ..atomic import atomic_write_json

        atomic_write_json(
            args.json,
            {"format": "tsnav-depth-readout-scores", "readout": str(args.out), **meta, "scores": scores},
            sort_keys=False,
        )
        print(f"wrote {args.json}")
    return 0
