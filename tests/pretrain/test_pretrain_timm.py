"""Published-ViT compatibility: timm weights load by key and our encoder reproduces timm's features."""

import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from tsnav.pretrain.model import MAEConfig, MaskedAutoencoderViT, load_encoder_weights


pytestmark = pytest.mark.usefixtures("one_torch_thread")

FIX = Path(__file__).resolve().parents[1] / "fixtures" / "pretrain"


def test_timm_vit_weights_reproduce_timm_features():
    arch = json.loads((FIX / "timm_meta.json").read_text())["arch"]
    cfg = MAEConfig(
        img_size=arch["img_size"],
        patch_size=arch["patch_size"],
        embed_dim=arch["embed_dim"],
        depth=arch["depth"],
        num_heads=arch["num_heads"],
        mlp_ratio=arch["mlp_ratio"],
        decoder_embed_dim=32,
        decoder_depth=1,
        decoder_num_heads=2,
    )
    model = MaskedAutoencoderViT(cfg).eval()
    info = load_encoder_weights(model, FIX / "timm_vit.safetensors")
    assert "blocks.1.mlp.fc2.weight" in info["loaded"] and "pos_embed" in info["loaded"]
    io = load_file(str(FIX / "timm_io.safetensors"))
    with torch.no_grad():
        y = model.forward_features(io["x"])
    assert y.shape == io["y"].shape
    torch.testing.assert_close(y, io["y"], atol=1e-5, rtol=1e-5)
    # and the grid of patch tokens is timm's tokens 1.. reshaped
    fm = model.feature_map(io["x"])
    torch.testing.assert_close(fm[:, :, 1, 2], io["y"][:, 1 + 1 * 4 + 2], atol=1e-5, rtol=1e-5)
