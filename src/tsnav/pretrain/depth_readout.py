"""A depth readout of a frozen encoder: DE-MAE's depth decoder (paper §III-C) made again on the encoder's unmasked
tokens, so that how far things are can be estimated from the feature map an agent reads.

DE-MAE pretrains the encoder to predict depth beside colour; its depth decoder is left behind when the encoder is
packed into an agent (``encoder.safetensors`` holds the encoder only). :class:`DepthReadout` has the decoder's shape
(a linear map of each token to 128 channels, learned position embeddings, two pre-norm transformer blocks, a linear
map of each token to its patch's depth) and is trained by :func:`train_readout` on feature maps against depth frames
averaged to :data:`GRID` squared (:func:`average_depth`). ``tsnav analyze depth-readout`` trains one on a world's
feature cache and scores it; the stop head's ``est-depth`` input and agents with ``AgentConfig.target_depth`` read it.
The file is safetensors with the feature cache's name, shape and fingerprint in its metadata.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn

#: Side of the depth map the readout predicts (and that ``true-depth`` reads): 32 x 32 cells of the frame.
GRID = 32
#: Depths are clipped to this many metres (the stop decision lives under 2 m; far walls only need to read as far).
MAX_DEPTH = 5.0
#: Distance the cell agreement is scored at: the lineage's visibility distance.
NEAR = 1.5


class DepthReadout(nn.Module):
    """Feature map ``(B, C, h, w)`` -> depth ``(B, GRID, GRID)`` metres in ``[0, MAX_DEPTH]``: per token a
    ``(GRID/h) x (GRID/w)`` patch, after two transformer blocks over the tokens (the DE-MAE decoder's shape)."""

    def __init__(self, channels: int, h: int, w: int, dim: int = 128, heads: int = 4, blocks: int = 2):
        super().__init__()
        from .model import Block

        if GRID % h or GRID % w:
            raise ValueError(f"a {h}x{w} feature grid does not divide the {GRID}x{GRID} depth map")
        self.shape = (channels, h, w)
        self.ph, self.pw = GRID // h, GRID // w
        self.norm_in = nn.LayerNorm(channels)
        self.embed = nn.Linear(channels, dim)
        self.pos = nn.Parameter(torch.zeros(1, h * w, dim))
        nn.init.normal_(self.pos, std=0.02)
        self.blocks = nn.ModuleList([Block(dim, heads) for _ in range(blocks)])
        self.norm = nn.LayerNorm(dim, eps=1e-6)
        self.pred = nn.Linear(dim, self.ph * self.pw)

    def forward(self, feat: torch.Tensor) -> torch.Tensor:
        b, c, h, w = feat.shape
        if (c, h, w) != self.shape:
            raise ValueError(f"feature maps of shape {(c, h, w)}; the readout was trained on {self.shape}")
        x = self.embed(self.norm_in(feat.flatten(2).transpose(1, 2))) + self.pos
        for blk in self.blocks:
            x = blk(x)
        p = torch.sigmoid(self.pred(self.norm(x))) * MAX_DEPTH  # (B, h*w, ph*pw)
        p = p.view(b, h, w, self.ph, self.pw).permute(0, 1, 3, 2, 4)
        return p.reshape(b, GRID, GRID)


def average_depth(d: np.ndarray, max_depth: float | None = MAX_DEPTH) -> np.ndarray:
    """Square depth frames ``(..., H, H)`` (side a multiple of :data:`GRID`) averaged to ``(..., GRID, GRID)``,
    clipped to ``[0, max_depth]`` first (NaN and infinity read as ``max_depth``; None: averaged as they are)."""
    d = np.asarray(d, dtype=np.float32)
    if d.ndim < 2 or d.shape[-1] != d.shape[-2] or d.shape[-1] % GRID:
        raise ValueError(f"depth frames of shape {d.shape}; square frames whose side is a multiple of {GRID} needed")
    if max_depth is not None:
        d = np.clip(np.nan_to_num(d, nan=max_depth, posinf=max_depth, neginf=0.0), 0.0, max_depth)
    k = d.shape[-1] // GRID
    return d.reshape(*d.shape[:-2], GRID, k, GRID, k).mean(axis=(-3, -1))


def scene_depth_maps(path: str | Path, keys, max_depth: float | None = MAX_DEPTH, flip: bool = False) -> np.ndarray:
    """``(len(keys), GRID, GRID)`` float16: the frames ``keys`` of a scene's ``depth.hdf5`` at ``path``
    (:func:`~tsnav.data.reader.read_stack`), flipped left to right when ``flip`` (a mirrored room), averaged by
    :func:`average_depth`; ``ValueError`` naming the file for a missing file, frame or a frame of another shape."""
    import h5py

    from ..data.reader import SceneFormatError, read_stack

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such depth file (the world's depth frames are read here)")
    try:
        with h5py.File(path, "r") as f:
            frames = read_stack(f, keys)
    except (KeyError, SceneFormatError) as e:
        raise ValueError(str(e.args[0])) from None
    if flip:
        frames = frames[..., ::-1]
    try:
        return average_depth(frames, max_depth).astype(np.float16)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


@torch.no_grad()
def score(model: DepthReadout, feat: np.ndarray, depth: np.ndarray, batch: int = 1024) -> dict:
    """Mean absolute error (metres) over every cell, over cells truly nearer than 2 m, and the share of 4x4-cell
    blocks whose median agrees with the ground truth's on "within :data:`NEAR` m"."""
    model.eval()
    err, n, near_err, near_n, agree, blocks = 0.0, 0, 0.0, 0, 0, 0
    for i in range(0, len(feat), batch):
        p = model(torch.from_numpy(feat[i : i + batch]).float())
        t = torch.from_numpy(depth[i : i + batch]).float()
        e = (p - t).abs()
        err, n = err + float(e.sum()), n + e.numel()
        m = t < 2.0
        near_err, near_n = near_err + float(e[m].sum()), near_n + int(m.sum())
        pb = p.view(-1, GRID // 4, 4, GRID // 4, 4).permute(0, 1, 3, 2, 4).flatten(3).median(dim=3).values
        tb = t.view(-1, GRID // 4, 4, GRID // 4, 4).permute(0, 1, 3, 2, 4).flatten(3).median(dim=3).values
        agree, blocks = agree + int(((pb < NEAR) == (tb < NEAR)).sum()), blocks + tb.numel()
    return {
        "mae_m": err / max(n, 1),
        "mae_under_2m": near_err / max(near_n, 1),
        "near_agreement": agree / max(blocks, 1),
        "frames": int(len(feat)),
    }


def train_readout(feat, depth, epochs=4, seed=0, batch=256, lr=1e-3) -> DepthReadout:
    """AdamW (weight decay 0.01, cosine schedule) on the L1 error in metres of every cell, ``epochs`` passes over
    the frames in batches of ``batch`` (all of them when fewer; the last partial batch of a pass is left out)."""
    if len(feat) == 0:
        raise ValueError("no frames to train a depth readout on")
    batch = min(batch, len(feat))
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    model = DepthReadout(*feat.shape[1:])
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=0.01)
    steps = epochs * (len(feat) // batch)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(steps, 1))
    from tqdm import tqdm

    bar = tqdm(total=steps, desc="depth readout", unit="step", file=sys.stderr, disable=None)
    for _ in range(epochs):
        model.train()
        order = rng.permutation(len(feat))
        for i in range(0, len(order) - batch + 1, batch):
            idx = np.sort(order[i : i + batch])
            p = model(torch.from_numpy(feat[idx]).float())
            loss = (p - torch.from_numpy(depth[idx]).float()).abs().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            bar.update(1)
            bar.set_postfix(l1=f"{loss.item():.3f}")
    bar.close()
    model.eval()
    return model


def save_readout(path: Path, model: DepthReadout, meta: dict) -> None:
    from ..checkpoint import save_tensors

    c, h, w = model.shape
    save_tensors(
        path,
        model.state_dict(),
        {"format": "tsnav-depth-readout", "shape": json.dumps([c, h, w]), "grid": str(GRID), **meta},
    )


def load_readout(path: str | Path) -> tuple[DepthReadout, dict]:
    """The readout of a :func:`save_readout` file and its metadata; ``ValueError`` for another file."""
    from ..checkpoint import BrokenCheckpoint, load_tensors

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such depth readout file")
    try:
        tensors, meta = load_tensors(path)
    except BrokenCheckpoint as e:
        raise ValueError(str(e)) from None
    if meta.get("format") != "tsnav-depth-readout":
        raise ValueError(f"{path}: not a depth readout (`tsnav analyze depth-readout` writes them)")
    if int(meta.get("grid", 0)) != GRID:
        raise ValueError(f"{path}: a {meta.get('grid')}-cell readout; this tsnav reads {GRID}")
    model = DepthReadout(*json.loads(meta["shape"]))
    model.load_state_dict(tensors)
    model.eval()
    return model, meta
