"""Pictures of what a (DE-)MAE learned: input, masked input, RGB reconstruction, predicted and true depth."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from matplotlib import colormaps

from ..atomic import atomic_write_bytes
from .data import MAX_DEPTH, denormalize_rgb, target_to_depth
from .model import MaskedAutoencoderViT


def _depth_colors(d: np.ndarray, vmax: np.ndarray) -> np.ndarray:
    """``[N, H, W]`` metres -> ``[N, H, W, 3]`` colours (``viridis``, 0 m dark, ``vmax[n]`` metres bright)."""
    return colormaps["viridis"](np.clip(d / vmax[:, None, None], 0, 1))[..., :3]


@torch.no_grad()
def reconstruction_grid(
    model: MaskedAutoencoderViT,
    images: torch.Tensor,
    depths: torch.Tensor | None,
    path: str | Path,
    seed: int = 0,
    mask_ratio: float | None = None,
) -> np.ndarray:
    """Write a PNG grid, one row per image: input, masked input, RGB reconstruction (visible patches pasted
    back, as MAE shows it), predicted depth (DE-MAE; grey for MAE), true depth. Returns the grid as uint8.

    images: normalised RGB ``[N, 3, S, S]``; depths: ``[N, 1, S, S]`` depth targets (:func:`~tsnav.pretrain.data.depth_to_target`) or None.
    """
    was_training = model.training
    model.eval()
    g = torch.Generator().manual_seed(seed)
    n, _, s, _ = images.shape
    noise = torch.rand(n, model.config.num_patches, generator=g).to(images.device)
    out = model(images, depths if model.config.use_depth else None, mask_ratio=mask_ratio, noise=noise)
    model.train(was_training)
    p = model.config.patch_size
    mask = out.mask.unsqueeze(-1).expand(-1, -1, p * p * 3)
    mask_img = model.unpatchify(mask.float(), 3)  # [N, 3, S, S], 1 = masked
    pred = out.pred
    if model.config.norm_pix_loss:  # undo the per-patch normalisation with the true patch statistics
        t = model.patchify(images)
        pred = pred * (t.var(-1, keepdim=True) + 1e-6) ** 0.5 + t.mean(-1, keepdim=True)
    rec = model.unpatchify(pred.float(), 3)
    cols = [
        denormalize_rgb(images),
        denormalize_rgb(images) * (1 - mask_img) + 0.5 * mask_img,
        denormalize_rgb(images * (1 - mask_img) + rec * mask_img),
    ]
    cols = [c.permute(0, 2, 3, 1).cpu().numpy() for c in cols]
    grey = np.full((n, s, s, 3), 0.5)
    true = target_to_depth(depths[:, 0]).cpu().numpy() if depths is not None else None
    # one colour scale per row: 0 m to the row's farthest true depth (both depth columns share it)
    vmax = np.maximum(true.reshape(n, -1).max(1), 0.5) if true is not None else np.full(n, MAX_DEPTH / 2)
    if out.pred_depth is not None:
        pd = target_to_depth(model.unpatchify(out.pred_depth.float(), 1)[:, 0]).cpu().numpy()
        cols.append(_depth_colors(pd, vmax))
    else:
        cols.append(grey)
    cols.append(_depth_colors(true, vmax) if true is not None else grey)
    pad = 2
    grid = np.ones((n * (s + pad) + pad, len(cols) * (s + pad) + pad, 3))
    for i in range(n):
        for j, c in enumerate(cols):
            grid[pad + i * (s + pad) : pad + i * (s + pad) + s, pad + j * (s + pad) : pad + j * (s + pad) + s] = c[i]
    grid = (np.clip(grid, 0, 1) * 255).round().astype(np.uint8)
    scale = max(1, 96 // s)  # small frames are enlarged so the picture can be read
    img = Image.fromarray(grid).resize((grid.shape[1] * scale, grid.shape[0] * scale), Image.NEAREST)
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    atomic_write_bytes(path, buf.getvalue())
    return grid
