"""Reconstruction picture: layout, the visible patches shown unchanged, MAE without a depth column."""

import numpy as np
import pytest
import torch
from PIL import Image

from tsnav.pretrain.model import MAEConfig, MaskedAutoencoderViT
from tsnav.pretrain.viz import reconstruction_grid


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def model(use_depth):
    torch.manual_seed(0)
    return MaskedAutoencoderViT(
        MAEConfig(
            img_size=32,
            patch_size=8,
            embed_dim=32,
            depth=1,
            num_heads=2,
            decoder_embed_dim=16,
            decoder_depth=1,
            decoder_num_heads=2,
            use_depth=use_depth,
        )
    )


def test_grid_layout_and_visible_patches(tmp_path):
    imgs, depths = torch.randn(3, 3, 32, 32) * 0.5, torch.randn(3, 1, 32, 32) * 0.3
    grid = reconstruction_grid(model(True), imgs, depths, tmp_path / "g.png", seed=1)
    pad, s = 2, 32
    assert grid.shape == (3 * (s + pad) + pad, 5 * (s + pad) + pad, 3)
    im = Image.open(tmp_path / "g.png")
    assert im.size == (grid.shape[1] * 3, grid.shape[0] * 3)  # 32-px frames enlarged x3
    row = grid[pad : pad + s]
    inp, masked, rec = (row[:, pad + j * (s + pad) : pad + j * (s + pad) + s].astype(int) for j in range(3))
    grey = np.all(masked == 128, axis=-1)
    assert 0.5 < grey.mean() < 0.95  # about 75 % masked
    # visible patches of the reconstruction are the input's pixels
    assert np.abs(rec[~grey] - inp[~grey]).max() <= 1
    g2 = reconstruction_grid(model(False), imgs, None, tmp_path / "m.png")
    assert np.all(g2[pad : pad + s, pad + 3 * (s + pad) : pad + 3 * (s + pad) + s] == 128)  # no depth head: grey
