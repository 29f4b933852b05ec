"""(DE-)MAE model: patches, masking, loss, heads, weight loading (paper §III-C)."""

import numpy as np
import pytest
import torch

from tsnav.pretrain.model import (
    MAEConfig,
    MaskedAutoencoderViT,
    load_encoder_weights,
    patchify,
    sincos_2d,
    unpatchify,
    vit_tiny,
)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def small(use_depth=True, **kw):
    cfg = MAEConfig(
        img_size=32,
        patch_size=8,
        embed_dim=32,
        depth=2,
        num_heads=2,
        decoder_embed_dim=16,
        decoder_depth=1,
        decoder_num_heads=2,
        use_depth=use_depth,
        **kw,
    )
    torch.manual_seed(0)
    return MaskedAutoencoderViT(cfg)


@pytest.mark.parametrize("c", [3, 1])
def test_patchify_round_trip_and_layout(c):
    x = torch.randn(2, c, 32, 32)
    p = patchify(x, 8)
    assert p.shape == (2, 16, 64 * c)
    assert torch.equal(unpatchify(p, 8, c), x)
    # patch (row 1, col 2) holds pixel (8 + 3, 16 + 5) at (row 3, col 5) of the patch, channel-last
    assert torch.equal(p[:, 1 * 4 + 2].reshape(2, 8, 8, c)[:, 3, 5, :], x[:, :, 11, 21])


def test_random_masking_keeps_requested_count_and_restores_order():
    torch.manual_seed(1)
    n, l, d = 3, 16, 4
    x = torch.arange(n * l * d, dtype=torch.float32).reshape(n, l, d)
    vis, mask, ids_restore = MaskedAutoencoderViT.random_masking(x, 0.75)
    assert vis.shape == (n, 4, d)
    assert torch.all(mask.sum(1) == 12)
    # the visible tokens are exactly those of unmasked patches
    for i in range(n):
        kept = torch.nonzero(mask[i] == 0).squeeze(1)
        assert sorted(vis[i, :, 0].tolist()) == sorted(x[i, kept, 0].tolist())
    # ids_restore undoes the shuffle: visible tokens + placeholders gathered back = patch order
    full = torch.cat([vis, torch.full((n, 12, d), -1.0)], dim=1)
    restored = torch.gather(full, 1, ids_restore.unsqueeze(-1).expand(-1, -1, d))
    assert torch.equal(restored[mask == 0], x[mask == 0])
    assert torch.all(restored[mask == 1] == -1)


def test_sincos_2d_first_half_encodes_column():
    e = sincos_2d(8, 3, cls_token=True)
    assert e.shape == (10, 8) and np.all(e[0] == 0)
    # patch (row 0, col 1): column half = [sin(1), sin(1/100), cos(1), cos(1/100)], row half = sin/cos of 0
    np.testing.assert_allclose(e[1 + 1, :4], [np.sin(1), np.sin(0.01), np.cos(1), np.cos(0.01)], rtol=1e-6)
    np.testing.assert_allclose(e[1 + 1, 4:], [0, 0, 1, 1], atol=1e-7)


def test_loss_uses_masked_rgb_and_all_depth_by_hand():
    m = small()
    imgs = torch.zeros(1, 3, 32, 32)
    depths = torch.zeros(1, 1, 32, 32)
    mask = torch.zeros(1, 16)
    mask[0, [0, 5]] = 1
    pred = torch.zeros(1, 16, 192)
    pred[0, 0] = 2.0  # masked patch, error 4 per pixel
    pred[0, 5] = 1.0  # masked patch, error 1
    pred[0, 7] = 100.0  # visible patch: must not count
    pred_d = torch.zeros(1, 16, 64)
    pred_d[0, 3] = 4.0  # visible patch: depth counts everywhere (16 per pixel on 1/16 of pixels)
    loss, lr, ld = m.forward_loss(imgs, pred, mask, depths, pred_d)
    assert lr.item() == pytest.approx((4 + 1) / 2)
    assert ld.item() == pytest.approx(16 / 16)
    assert loss.item() == pytest.approx(2.5 + 1.0)
    m.config.depth_weight = 0.5
    assert m.forward_loss(imgs, pred, mask, depths, pred_d)[0].item() == pytest.approx(2.5 + 0.5)


def test_norm_pix_loss_normalises_each_patch():
    m = small(norm_pix_loss=True)
    imgs = torch.randn(2, 3, 32, 32) * 5 + 3
    t = patchify(imgs, 8)
    t = (t - t.mean(-1, keepdim=True)) / (t.var(-1, keepdim=True) + 1e-6) ** 0.5
    mask = torch.ones(2, 16)
    loss, lr, _ = m.forward_loss(imgs, t, mask)
    assert lr.item() == pytest.approx(0.0, abs=1e-8)


def test_depth_head_gets_gradients_and_mae_has_none():
    m = small(use_depth=True)
    out = m(torch.randn(2, 3, 32, 32), torch.rand(2, 1, 32, 32))
    assert out.pred_depth.shape == (2, 16, 64) and out.loss_depth.item() > 0
    out.loss.backward()
    assert m.decoder_pred_depth.weight.grad.abs().sum() > 0
    assert m.patch_embed.proj.weight.grad.abs().sum() > 0
    assert m.pos_embed.grad is None  # fixed sin-cos

    mae = small(use_depth=False)
    assert not any(k.startswith("decoder_pred_depth") for k in mae.state_dict())
    out = mae(torch.randn(2, 3, 32, 32))
    assert out.pred_depth is None and out.loss_depth.item() == 0.0
    with pytest.raises(ValueError, match="depth"):
        m(torch.randn(1, 3, 32, 32))


def test_forward_encoder_visible_tokens_and_feature_map():
    m = vit_tiny(patch_size=16, img_size=64)
    x = torch.randn(2, 3, 64, 64)
    latent, mask, _ = m.forward_encoder(x, 0.75)
    assert latent.shape == (2, 1 + 4, 192)
    assert m.feature_map(x).shape == (2, 192, 4, 4)
    # no masking: the encoder path equals forward_features
    noise = torch.arange(16).float().repeat(2, 1)  # keep all in order
    lat0, _, _ = m.forward_encoder(x, 0.0, noise)
    torch.testing.assert_close(lat0, m.forward_features(x), atol=1e-5, rtol=1e-5)


def test_bad_config_and_weight_errors(tmp_path):
    with pytest.raises(ValueError, match="multiple"):
        MAEConfig(img_size=30, patch_size=8)
    m = small()
    from safetensors.torch import save_file

    sd = {k: v.clone() for k, v in m.encoder_state_dict().items()}
    sd.pop("norm.weight")
    sd["extra.weight"] = torch.zeros(1)
    sd["decoder_pred.weight"] = torch.zeros(1)  # decoder keys are ignored
    save_file(sd, str(tmp_path / "w.safetensors"))
    with pytest.raises(ValueError, match=r"missing keys: norm\.weight; unexpected keys: extra\.weight"):
        load_encoder_weights(m, tmp_path / "w.safetensors")


def test_load_encoder_weights_round_trip_pth_and_pos_resize(tmp_path):
    a, b = small(), small()
    with torch.no_grad():
        for p in a.parameters():
            p.add_(torch.randn_like(p))
    torch.save({"model": {"module." + k: v for k, v in a.state_dict().items()}}, tmp_path / "a.pth")
    info = load_encoder_weights(b, tmp_path / "a.pth")
    assert "decoder_pred.weight" in info["ignored"]
    for k, v in a.encoder_state_dict().items():
        assert torch.equal(v, b.encoder_state_dict()[k]), k
    # a 64-px model takes the 32-px weights with a resized positional embedding
    big = MaskedAutoencoderViT(MAEConfig(**{**a.config.to_dict(), "img_size": 64}))
    load_encoder_weights(big, tmp_path / "a.pth")
    assert big.pos_embed.shape == (1, 65, 32)
    assert torch.equal(big.pos_embed[0, 0], a.pos_embed[0, 0])
