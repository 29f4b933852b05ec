"""Masked autoencoders for navigation encoders: standard MAE and Depth-Enhanced MAE (paper §III-C, Fig. 3).

The encoder is a plain Vision Transformer that sees only the visible RGB patches of a masked image (2-D
sine-cosine positional embeddings, fixed). A smaller ViT decoder sees the encoded visible tokens plus mask
tokens and ends in linear heads: ``decoder_pred`` (RGB pixels of each patch) and, for DE-MAE only,
``decoder_pred_depth`` (depth pixels of each patch). Standard MAE is the same model with no depth head.

Loss (§III-C): MSE between reconstruction and image in pixel space, RGB over the *masked* patches plus depth
over *all* patches, with identical weights (``depth_weight = 1``).

Parameter names follow the common ViT checkpoint layout (``patch_embed.proj``, ``cls_token``, ``pos_embed``,
``blocks.N.norm1 / attn.qkv / attn.proj / norm2 / mlp.fc1 / mlp.fc2``, ``norm``; decoder parts prefixed
``decoder_`` and ``mask_token`` as MAE releases name them), so published ViT / MAE / VC-1 encoder weights
load by key with :func:`load_encoder_weights`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from safetensors.torch import load_file

from ..errors import from_fields


# ---------------------------------------------------------------------------------------------------------
# Configuration and size presets
# ---------------------------------------------------------------------------------------------------------


@dataclass
class MAEConfig:
    """Architecture and loss of a (DE-)MAE. Defaults are the paper's ViT-Base DE-MAE (§III-C)."""

    img_size: int = 224
    """Side of the square input image, pixels; must be a multiple of ``patch_size``."""
    patch_size: int = 16
    """Side of a square patch, pixels."""
    in_chans: int = 3
    """Input channels of the encoder (RGB)."""
    embed_dim: int = 768
    """Encoder token width (ViT-Base: 768)."""
    depth: int = 12
    """Number of encoder transformer blocks (ViT-Base: 12)."""
    num_heads: int = 12
    """Encoder attention heads (ViT-Base: 12)."""
    decoder_embed_dim: int = 512
    """Decoder token width (MAE's decoder for ViT-Base: 512)."""
    decoder_depth: int = 8
    """Decoder transformer blocks (MAE: 8)."""
    decoder_num_heads: int = 16
    """Decoder attention heads (MAE: 16)."""
    mlp_ratio: float = 4.0
    """Hidden width of each block's MLP relative to the token width."""
    mask_ratio: float = 0.75
    """Share of patches hidden from the encoder during pretraining (MAE: 0.75)."""
    norm_pix_loss: bool = False
    """Normalise each target RGB patch by its own mean/std before the MSE (MAE option; the paper's loss
    is plain pixel MSE, so off by default)."""
    use_depth: bool = True
    """DE-MAE (True): add the depth head and loss. Standard MAE (False): no depth head at all."""
    depth_weight: float = 1.0
    """Weight of the depth MSE relative to the RGB MSE ("identical weights", §III-C)."""

    def __post_init__(self) -> None:
        if self.img_size <= 0 or self.patch_size <= 0 or self.img_size % self.patch_size:
            raise ValueError(f"img_size {self.img_size} must be a positive multiple of patch_size {self.patch_size}")
        if self.embed_dim % self.num_heads or self.decoder_embed_dim % self.decoder_num_heads:
            raise ValueError("embed_dim / decoder_embed_dim must be divisible by their number of heads")
        if self.embed_dim % 4 or self.decoder_embed_dim % 4:
            raise ValueError("2-D sin-cos positional embeddings need token widths divisible by 4")
        if not 0.0 <= self.mask_ratio < 1.0:
            raise ValueError(f"mask_ratio must be in [0, 1), got {self.mask_ratio}")

    @property
    def grid_size(self) -> int:
        """Patches per image side."""
        return self.img_size // self.patch_size

    @property
    def num_patches(self) -> int:
        return self.grid_size**2

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "MAEConfig":
        return from_fields(cls, d, "MAE config")


#: Encoder sizes (width, depth, heads) and the smaller decoders used with them. ViT-Base and its decoder
#: are the paper's / MAE's; tiny and small decoders are scaled down for CPU (this project's choice);
#: ``vit_micro`` exists for tests and smoke runs only.
SIZES = {
    "vit_micro": dict(embed_dim=64, depth=2, num_heads=2, decoder_embed_dim=32, decoder_depth=1, decoder_num_heads=2),
    "vit_tiny": dict(embed_dim=192, depth=12, num_heads=3, decoder_embed_dim=128, decoder_depth=2, decoder_num_heads=4),
    "vit_small": dict(
        embed_dim=384, depth=12, num_heads=6, decoder_embed_dim=256, decoder_depth=4, decoder_num_heads=8
    ),
    "vit_base": dict(
        embed_dim=768, depth=12, num_heads=12, decoder_embed_dim=512, decoder_depth=8, decoder_num_heads=16
    ),
}


def make_config(name: str, patch_size: int = 16, img_size: int = 224, **overrides) -> MAEConfig:
    """Config of a named size (``vit_tiny`` / ``vit_small`` / ``vit_base``) with any field overridden."""
    if name not in SIZES:
        raise ValueError(f"unknown model {name!r} (choose from {', '.join(SIZES)})")
    return MAEConfig(patch_size=patch_size, img_size=img_size, **{**SIZES[name], **overrides})


def vit_tiny(patch_size: int = 16, img_size: int = 224, **kw) -> "MaskedAutoencoderViT":
    """ViT-Tiny (192 wide, 12 blocks, 3 heads) (DE-)MAE."""
    return MaskedAutoencoderViT(make_config("vit_tiny", patch_size, img_size, **kw))


def vit_small(patch_size: int = 16, img_size: int = 224, **kw) -> "MaskedAutoencoderViT":
    """ViT-Small (384 wide, 12 blocks, 6 heads) (DE-)MAE."""
    return MaskedAutoencoderViT(make_config("vit_small", patch_size, img_size, **kw))


def vit_base(patch_size: int = 16, img_size: int = 224, **kw) -> "MaskedAutoencoderViT":
    """ViT-Base (768 wide, 12 blocks, 12 heads) (DE-)MAE, the paper's encoder."""
    return MaskedAutoencoderViT(make_config("vit_base", patch_size, img_size, **kw))


# ---------------------------------------------------------------------------------------------------------
# Positional embeddings
# ---------------------------------------------------------------------------------------------------------


def sincos_1d(dim: int, pos: np.ndarray) -> np.ndarray:
    """``[M, dim]`` sine-cosine embedding of positions ``pos`` (any shape, flattened); ``dim`` even."""
    omega = 1.0 / 10000 ** (np.arange(dim // 2, dtype=np.float64) / (dim / 2.0))  # [dim/2]
    out = np.outer(pos.reshape(-1).astype(np.float64), omega)  # [M, dim/2]
    return np.concatenate([np.sin(out), np.cos(out)], axis=1)  # [M, dim]


def sincos_2d(dim: int, grid_size: int, cls_token: bool = True) -> np.ndarray:
    """Fixed 2-D sine-cosine positional embedding ``[(1 +) g*g, dim]``, row-major patch order.

    The first half of the channels encodes the column (x) index, the second half the row (y) index; the
    class-token row (when present) is zeros.
    """
    ys, xs = np.meshgrid(np.arange(grid_size), np.arange(grid_size), indexing="ij")  # [g, g] each
    emb = np.concatenate([sincos_1d(dim // 2, xs), sincos_1d(dim // 2, ys)], axis=1)  # [g*g, dim]
    if cls_token:
        emb = np.concatenate([np.zeros((1, dim)), emb], axis=0)
    return emb.astype(np.float32)


# ---------------------------------------------------------------------------------------------------------
# Transformer blocks (timm layout)
# ---------------------------------------------------------------------------------------------------------


class PatchEmbed(nn.Module):
    """Non-overlapping ``p x p`` patches -> tokens: ``[N, C, H, W] -> [N, L, D]`` (conv with stride p)."""

    def __init__(self, patch_size: int, in_chans: int, embed_dim: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(in_chans, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)  # [N, L, D]


class Attention(nn.Module):
    """Multi-head self-attention with one fused ``qkv`` projection and an output ``proj``."""

    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, dim * 3)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, l, d = x.shape
        qkv = self.qkv(x).reshape(n, l, 3, self.num_heads, d // self.num_heads).permute(2, 0, 3, 1, 4)
        q, k, v = qkv.unbind(0)  # [N, heads, L, d_head] each
        x = F.scaled_dot_product_attention(q, k, v)  # [N, heads, L, d_head]
        return self.proj(x.transpose(1, 2).reshape(n, l, d))  # [N, L, D]


class Mlp(nn.Module):
    """Two-layer MLP with exact GELU."""

    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


class Block(nn.Module):
    """Pre-norm transformer block: ``x + attn(norm1(x))`` then ``x + mlp(norm2(x))`` (LayerNorm eps 1e-6)."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float = 4.0) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = Attention(dim, num_heads)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


# ---------------------------------------------------------------------------------------------------------
# The model
# ---------------------------------------------------------------------------------------------------------


class MAEOutput(NamedTuple):
    """Result of :meth:`MaskedAutoencoderViT.forward`.

    loss: total loss (scalar); loss_rgb / loss_depth: its parts (``loss_depth`` is 0 for standard MAE);
    pred: ``[N, L, p*p*3]`` RGB prediction per patch; pred_depth: ``[N, L, p*p]`` or None;
    mask: ``[N, L]`` 1 = masked (hidden from the encoder), 0 = visible.
    """

    loss: torch.Tensor
    loss_rgb: torch.Tensor
    loss_depth: torch.Tensor
    pred: torch.Tensor
    pred_depth: torch.Tensor | None
    mask: torch.Tensor


class MaskedAutoencoderViT(nn.Module):
    """(DE-)MAE with a ViT encoder (paper §III-C). ``config.use_depth`` selects DE-MAE vs standard MAE."""

    def __init__(self, config: MAEConfig | None = None) -> None:
        super().__init__()
        c = self.config = config or MAEConfig()
        p, L = c.patch_size, c.num_patches
        # --- encoder (timm ViT names) ---
        self.patch_embed = PatchEmbed(p, c.in_chans, c.embed_dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, c.embed_dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, L + 1, c.embed_dim), requires_grad=False)  # fixed
        self.blocks = nn.ModuleList([Block(c.embed_dim, c.num_heads, c.mlp_ratio) for _ in range(c.depth)])
        self.norm = nn.LayerNorm(c.embed_dim, eps=1e-6)
        # --- decoder (MAE names) ---
        self.decoder_embed = nn.Linear(c.embed_dim, c.decoder_embed_dim)
        self.mask_token = nn.Parameter(torch.zeros(1, 1, c.decoder_embed_dim))
        self.decoder_pos_embed = nn.Parameter(torch.zeros(1, L + 1, c.decoder_embed_dim), requires_grad=False)
        self.decoder_blocks = nn.ModuleList(
            [Block(c.decoder_embed_dim, c.decoder_num_heads, c.mlp_ratio) for _ in range(c.decoder_depth)]
        )
        self.decoder_norm = nn.LayerNorm(c.decoder_embed_dim, eps=1e-6)
        self.decoder_pred = nn.Linear(c.decoder_embed_dim, p * p * 3)
        if c.use_depth:
            self.decoder_pred_depth = nn.Linear(c.decoder_embed_dim, p * p * 1)
        else:
            self.decoder_pred_depth = None  # standard MAE: no depth head, no depth parameters
        self.initialize_weights()

    # -- initialisation (as MAE: fixed sin-cos positions, xavier linears, N(0, .02) tokens) --
    def initialize_weights(self) -> None:
        c = self.config
        self.pos_embed.data.copy_(torch.from_numpy(sincos_2d(c.embed_dim, c.grid_size))[None])
        self.decoder_pos_embed.data.copy_(torch.from_numpy(sincos_2d(c.decoder_embed_dim, c.grid_size))[None])
        w = self.patch_embed.proj.weight.data
        nn.init.xavier_uniform_(w.view(w.shape[0], -1))
        nn.init.zeros_(self.patch_embed.proj.bias)
        nn.init.normal_(self.cls_token, std=0.02)
        nn.init.normal_(self.mask_token, std=0.02)
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.xavier_uniform_(m.weight)
                nn.init.zeros_(m.bias)
            elif isinstance(m, nn.LayerNorm):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    # -- patches --
    def patchify(self, imgs: torch.Tensor) -> torch.Tensor:
        """``[N, C, H, W] -> [N, L, p*p*C]`` for any channel count C (row-major patches, (i, j, c) inside)."""
        return patchify(imgs, self.config.patch_size)

    def unpatchify(self, x: torch.Tensor, channels: int = 3) -> torch.Tensor:
        """Inverse of :meth:`patchify`: ``[N, L, p*p*C] -> [N, C, H, W]``."""
        return unpatchify(x, self.config.patch_size, channels)

    # -- masking --
    @staticmethod
    def random_masking(x: torch.Tensor, mask_ratio: float, noise: torch.Tensor | None = None):
        """Keep a random ``round(L * (1 - mask_ratio))`` patches per sample (shuffle by argsort of noise).

        Args: x ``[N, L, D]`` tokens; noise ``[N, L]`` in [0, 1) (drawn when None; smaller = kept).
        Returns: ``x_visible [N, K, D]``, ``mask [N, L]`` (1 = masked) in the original patch order,
        ``ids_restore [N, L]`` such that ``gather(shuffled, ids_restore)`` undoes the shuffle.
        """
        n, l, d = x.shape
        keep = int(round(l * (1 - mask_ratio)))
        keep = max(1, min(l, keep))
        if noise is None:
            noise = torch.rand(n, l, device=x.device)  # [N, L]
        ids_shuffle = torch.argsort(noise, dim=1)  # ascending: small noise kept
        ids_restore = torch.argsort(ids_shuffle, dim=1)  # [N, L]
        ids_keep = ids_shuffle[:, :keep]  # [N, K]
        x_visible = torch.gather(x, 1, ids_keep.unsqueeze(-1).expand(-1, -1, d))  # [N, K, D]
        mask = torch.ones(n, l, device=x.device)
        mask[:, :keep] = 0
        mask = torch.gather(mask, 1, ids_restore)  # [N, L] in patch order
        return x_visible, mask, ids_restore

    # -- encoder --
    def forward_encoder(self, imgs: torch.Tensor, mask_ratio: float, noise: torch.Tensor | None = None):
        """Encode visible patches: returns ``latent [N, 1+K, D]`` (class token first), mask, ids_restore."""
        x = self.patch_embed(imgs)  # [N, L, D]
        x = x + self.pos_embed[:, 1:, :]
        x, mask, ids_restore = self.random_masking(x, mask_ratio, noise)  # [N, K, D]
        cls = (self.cls_token + self.pos_embed[:, :1, :]).expand(x.shape[0], -1, -1)  # [N, 1, D]
        x = torch.cat([cls, x], dim=1)  # [N, 1+K, D]
        for blk in self.blocks:
            x = blk(x)
        return self.norm(x), mask, ids_restore

    def forward_features(self, imgs: torch.Tensor) -> torch.Tensor:
        """Encoder on the full image (no masking), as timm's ``forward_features``: ``[N, 1+L, D]``."""
        x = self.patch_embed(imgs)  # [N, L, D]
        cls = self.cls_token.expand(x.shape[0], -1, -1)
        x = torch.cat([cls, x], dim=1) + self.pos_embed  # [N, 1+L, D]
        for blk in self.blocks:
            x = blk(x)
        return self.norm(x)

    def feature_map(self, imgs: torch.Tensor) -> torch.Tensor:
        """Patch tokens of the unmasked image as a grid ``[N, D, h, w]`` (the navigation feature map)."""
        x = self.forward_features(imgs)[:, 1:, :]  # [N, L, D]
        g = self.config.grid_size
        return x.transpose(1, 2).reshape(x.shape[0], -1, g, g)

    # -- decoder --
    def forward_decoder(self, latent: torch.Tensor, ids_restore: torch.Tensor):
        """Decode ``latent [N, 1+K, D]``: returns ``pred [N, L, p*p*3]`` and ``pred_depth [N, L, p*p]`` or None."""
        x = self.decoder_embed(latent)  # [N, 1+K, Dd]
        n, k1, dd = x.shape
        l = ids_restore.shape[1]
        mask_tokens = self.mask_token.expand(n, l + 1 - k1, -1)  # [N, L-K, Dd]
        x_ = torch.cat([x[:, 1:, :], mask_tokens], dim=1)  # [N, L, Dd] shuffled order
        x_ = torch.gather(x_, 1, ids_restore.unsqueeze(-1).expand(-1, -1, dd))  # [N, L, Dd] patch order
        x = torch.cat([x[:, :1, :], x_], dim=1) + self.decoder_pos_embed  # [N, 1+L, Dd]
        for blk in self.decoder_blocks:
            x = blk(x)
        x = self.decoder_norm(x)[:, 1:, :]  # [N, L, Dd]
        pred = self.decoder_pred(x)  # [N, L, p*p*3]
        pred_depth = self.decoder_pred_depth(x) if self.decoder_pred_depth is not None else None  # [N, L, p*p]
        return pred, pred_depth

    # -- loss --
    def forward_loss(
        self,
        imgs: torch.Tensor,
        pred: torch.Tensor,
        mask: torch.Tensor,
        depths: torch.Tensor | None = None,
        pred_depth: torch.Tensor | None = None,
    ):
        """(DE-)MAE loss (§III-C). Returns ``(loss, loss_rgb, loss_depth)``.

        loss_rgb: per-patch pixel MSE averaged over the masked patches only (``mask == 1``);
        loss_depth: pixel MSE averaged over all patches; loss = loss_rgb + depth_weight * loss_depth.
        imgs ``[N, 3, H, W]`` (normalised RGB), depths ``[N, 1, H, W]`` (scaled metres).
        """
        target = self.patchify(imgs)  # [N, L, p*p*3]
        if self.config.norm_pix_loss:
            mean = target.mean(dim=-1, keepdim=True)
            var = target.var(dim=-1, keepdim=True)
            target = (target - mean) / (var + 1.0e-6) ** 0.5
        per_patch = ((pred.float() - target) ** 2).mean(dim=-1)  # [N, L]
        loss_rgb = (per_patch * mask).sum() / mask.sum().clamp_min(1.0)
        loss_depth = torch.zeros((), device=imgs.device)
        if pred_depth is not None:
            if depths is None:
                raise ValueError("DE-MAE needs depth images (depths=None)")
            target_d = self.patchify(depths)  # [N, L, p*p]
            loss_depth = ((pred_depth.float() - target_d) ** 2).mean()
        return loss_rgb + self.config.depth_weight * loss_depth, loss_rgb, loss_depth

    def forward(
        self,
        imgs: torch.Tensor,
        depths: torch.Tensor | None = None,
        mask_ratio: float | None = None,
        noise: torch.Tensor | None = None,
    ) -> MAEOutput:
        """Mask, encode, decode, score. ``imgs [N, 3, H, W]``; ``depths [N, 1, H, W]`` for DE-MAE."""
        ratio = self.config.mask_ratio if mask_ratio is None else mask_ratio
        latent, mask, ids_restore = self.forward_encoder(imgs, ratio, noise)
        pred, pred_depth = self.forward_decoder(latent, ids_restore)
        loss, loss_rgb, loss_depth = self.forward_loss(imgs, pred, mask, depths, pred_depth)
        return MAEOutput(loss, loss_rgb, loss_depth, pred, pred_depth, mask)

    def encoder_state_dict(self) -> dict[str, torch.Tensor]:
        """The encoder's parameters only (keys in the ViT layout, no ``decoder_*`` / ``mask_token``)."""
        return {k: v for k, v in self.state_dict().items() if is_encoder_key(k)}


def patchify(imgs: torch.Tensor, p: int) -> torch.Tensor:
    """``[N, C, H, W] -> [N, L, p*p*C]``; L = (H/p)(W/p) row-major; inside a patch order (row, col, channel)."""
    n, c, h, w = imgs.shape
    if h % p or w % p:
        raise ValueError(f"image {h}x{w} is not divisible into {p}x{p} patches")
    x = imgs.reshape(n, c, h // p, p, w // p, p)
    x = torch.einsum("nchpwq->nhwpqc", x)
    return x.reshape(n, (h // p) * (w // p), p * p * c)


def unpatchify(x: torch.Tensor, p: int, channels: int = 3) -> torch.Tensor:
    """Inverse of :func:`patchify` for square images: ``[N, L, p*p*C] -> [N, C, H, W]``."""
    n, l, e = x.shape
    g = int(round(math.sqrt(l)))
    if g * g != l or e != p * p * channels:
        raise ValueError(f"cannot unpatchify [N, {l}, {e}] with patch {p} and {channels} channels")
    x = x.reshape(n, g, g, p, p, channels)
    x = torch.einsum("nhwpqc->nchpwq", x)
    return x.reshape(n, channels, g * p, g * p)


# ---------------------------------------------------------------------------------------------------------
# Loading published / saved encoder weights
# ---------------------------------------------------------------------------------------------------------

#: Key prefixes that belong to decoders or classification heads of published checkpoints, not the encoder.
NON_ENCODER_PREFIXES = ("decoder_", "mask_token", "head.", "head_dist.", "fc_norm.", "pre_logits.")


def is_encoder_key(key: str) -> bool:
    return not key.startswith(NON_ENCODER_PREFIXES)


def read_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """Tensors of a ``.safetensors`` file or a ``.pth``/``.pt`` file (``torch.load(weights_only=True)``).

    Nested ``{"model": ...}`` / ``{"state_dict": ...}`` wrappers and a ``module.`` prefix (DDP) are removed.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such weights file")
    if path.suffix == ".safetensors":
        sd = load_file(str(path))
    else:
        try:
            sd = torch.load(str(path), map_location="cpu", weights_only=True)
        except Exception as e:  # noqa: BLE001 - any unpickling refusal becomes one line
            raise ValueError(f"{path}: cannot read as a weights-only torch file ({type(e).__name__})") from None
        for wrapper in ("model", "state_dict", "model_state"):
            if isinstance(sd, dict) and wrapper in sd and isinstance(sd[wrapper], dict):
                sd = sd[wrapper]
                break
    if not isinstance(sd, dict) or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise ValueError(f"{path}: not a state dict of tensors")
    return {(k[len("module.") :] if k.startswith("module.") else k): v for k, v in sd.items()}


def resize_pos_embed(pos: torch.Tensor, grid: int) -> torch.Tensor:
    """Bicubic resize of a ``[1, 1+g*g, D]`` positional embedding to ``[1, 1+grid*grid, D]`` (class row kept)."""
    cls, body = pos[:, :1], pos[:, 1:]
    g0 = int(round(math.sqrt(body.shape[1])))
    body = body.reshape(1, g0, g0, -1).permute(0, 3, 1, 2)
    body = F.interpolate(body.float(), size=(grid, grid), mode="bicubic", align_corners=False)
    return torch.cat([cls, body.permute(0, 2, 3, 1).reshape(1, grid * grid, -1).to(pos.dtype)], dim=1)


def load_encoder_weights(model: MaskedAutoencoderViT, path: str | Path) -> dict[str, list[str]]:
    """Load ViT encoder weights (timm / MAE / VC-1 layout) from safetensors or ``.pth`` into ``model``.

    Decoder and classification-head keys of the file are ignored (reported under ``"ignored"``); a
    ``pos_embed`` of another grid size is resized bicubically. Raises ``ValueError`` listing the missing
    and unexpected encoder keys (and shape mismatches) when the file does not fit.
    """
    sd = read_state_dict(path)
    own = model.encoder_state_dict()
    ignored = sorted(k for k in sd if not is_encoder_key(k))
    enc = {k: v for k, v in sd.items() if is_encoder_key(k)}
    if (
        "pos_embed" in enc
        and enc["pos_embed"].shape != own["pos_embed"].shape
        and enc["pos_embed"].ndim == 3
        and enc["pos_embed"].shape[-1] == own["pos_embed"].shape[-1]
    ):
        enc["pos_embed"] = resize_pos_embed(enc["pos_embed"], model.config.grid_size)
    missing = sorted(set(own) - set(enc))
    unexpected = sorted(set(enc) - set(own))
    wrong = sorted(
        f"{k} {tuple(enc[k].shape)} vs {tuple(own[k].shape)}"
        for k in set(own) & set(enc)
        if enc[k].shape != own[k].shape
    )
    if missing or unexpected or wrong:

        def short(xs):
            return ", ".join(xs[:8]) + (f" (+{len(xs) - 8} more)" if len(xs) > 8 else "") if xs else "none"

        raise ValueError(
            f"{path}: encoder weights do not fit this model: missing keys: {short(missing)}; "
            f"unexpected keys: {short(unexpected)}; shape mismatches: {short(wrong)}"
        )
    with torch.no_grad():
        params = dict(model.named_parameters())
        for k, v in enc.items():
            params[k].copy_(v.to(params[k].dtype))
    return {"loaded": sorted(enc), "ignored": ignored}
