"""Encoder architectures: how the networks named by :mod:`tsnav.pretrain.encoders` are built, saved and loaded.

An architecture is what ``encoder.safetensors`` records as ``arch`` (``vit``, ``resnet18``); every network
of one has ``feature_map(rgb) -> [N, C, h, w]`` (the navigation feature) and ``encoder_state_dict()`` (the
weights an encoder file keeps: no decoder, no head; a classification head is named ``fc``). A supervised
network's ``forward`` returns the 22 category logits.

=========================  =================================================================================
field                      used by
=========================  =================================================================================
``build(cfg)``             ``tsnav pretrain`` (:func:`tsnav.pretrain.train.build_model`): the network a method
                           trains, from its :class:`~tsnav.pretrain.train.PretrainConfig`
``model_config(cfg)``      the network's own config, saved in ``config.json`` and in the encoder file ({}: none)
``from_file(cfg, size)``   :func:`tsnav.pretrain.features.load_encoder` on an encoder file: the network before
                           its weights are loaded, and its input size
``untrained(name, ...)``   ``untrained:NAME`` specs (None when ``NAME`` is not one of this architecture; optional)
``from_weights(path, ..)`` ``<arch>:PATH`` specs: weights in a foreign layout (torchvision, timm; optional)
=========================  =================================================================================
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import nn

from ..constants import NUM_CATEGORIES
from .encoders import method_kind
from .model import SIZES, MAEConfig, MaskedAutoencoderViT, load_encoder_weights, make_config
from .resnet import ResNet18, load_resnet_weights


@dataclass(frozen=True)
class EncoderArch:
    """One architecture of encoder weights (see the module docstring)."""

    name: str
    build: Callable[[object], nn.Module]
    from_file: Callable[[dict, int], tuple[nn.Module, int]]
    model_config: Callable[[object], dict] = lambda cfg: {}
    untrained: Callable[[str, int, int], tuple[nn.Module, dict] | None] | None = None
    from_weights: Callable[[str, str, int, int], tuple[nn.Module, dict]] | None = None
    foreign_method: str = "foreign"
    """``Encoder.method`` of weights loaded by ``from_weights``."""

    def metadata(self, model: nn.Module, method: str) -> dict[str, str]:
        """safetensors metadata that lets :func:`~tsnav.pretrain.features.load_encoder` rebuild the encoder."""
        cfg = model.config.to_dict() if hasattr(model, "config") and hasattr(model.config, "to_dict") else {}
        return {
            "format": "tsnav-encoder",
            "arch": self.name,
            "method": method,
            "config": json.dumps(cfg, sort_keys=True) if cfg else "{}",
        }


#: Every architecture by the name encoder files record.
ENCODER_ARCHS: dict[str, EncoderArch] = {}


def register_arch(arch: EncoderArch) -> EncoderArch:
    """Add an architecture (an encoder of :mod:`tsnav.pretrain.encoders` names it by ``arch.name``)."""
    if arch.name in ENCODER_ARCHS and ENCODER_ARCHS[arch.name] != arch:
        raise ValueError(f"encoder architecture {arch.name!r} is already registered")
    ENCODER_ARCHS[arch.name] = arch
    return arch


def arch_of(name: str) -> EncoderArch:
    """The registered architecture ``name``; ``ValueError`` naming the choices otherwise."""
    if name not in ENCODER_ARCHS:
        raise ValueError(f"unknown encoder architecture {name!r} (registered: {', '.join(ENCODER_ARCHS)})")
    return ENCODER_ARCHS[name]


# -- ViT (MAE / DE-MAE, timm layout) ------------------------------------------------------------------------
def vit_for_features(cfg: dict) -> MaskedAutoencoderViT:
    """A ViT of a saved :class:`~tsnav.pretrain.model.MAEConfig` with a tiny decoder (features need none)."""
    c = MAEConfig.from_dict(cfg)
    c.decoder_embed_dim, c.decoder_depth, c.decoder_num_heads, c.use_depth = 16, 0, 1, False
    return MaskedAutoencoderViT(c)


def vit_mae_config(cfg) -> MAEConfig:
    """The :class:`~tsnav.pretrain.model.MAEConfig` a ViT method trains (depth head per its encoder kind)."""
    return make_config(
        cfg.model,
        cfg.patch_size,
        cfg.img_size,
        mask_ratio=cfg.mask_ratio,
        norm_pix_loss=cfg.norm_pix_loss,
        use_depth=method_kind(cfg.method).depth,
        depth_weight=cfg.depth_weight,
    )


def _vit_untrained(name: str, patch_size: int, img_size: int):
    if name not in SIZES:
        return None
    c = make_config(name, patch_size, img_size).to_dict()
    return vit_for_features(c), c


def _vit_from_weights(path: str, model: str, patch_size: int, img_size: int):
    c = make_config(model, patch_size, img_size).to_dict()
    m = vit_for_features(c)
    load_encoder_weights(m, path)
    return m, c


def _vit_from_file(cfg: dict, img_size: int):
    return vit_for_features(cfg), int(cfg["img_size"])


register_arch(
    EncoderArch(
        "vit",
        build=lambda cfg: MaskedAutoencoderViT(vit_mae_config(cfg)),
        from_file=_vit_from_file,
        model_config=lambda cfg: vit_mae_config(cfg).to_dict(),
        untrained=_vit_untrained,
        from_weights=_vit_from_weights,
        foreign_method="timm",
    )
)


# -- ResNet18 (torchvision layout) --------------------------------------------------------------------------
def _resnet_from_weights(path: str, model: str, patch_size: int, img_size: int):
    m = ResNet18()
    load_resnet_weights(m, path)
    return m, {}


register_arch(
    EncoderArch(
        "resnet18",
        build=lambda cfg: ResNet18(num_classes=NUM_CATEGORIES),
        from_file=lambda cfg, img_size: (ResNet18(), img_size),
        untrained=lambda name, patch_size, img_size: (ResNet18(), {}) if name == "resnet18" else None,
        from_weights=_resnet_from_weights,
        foreign_method="torchvision",
    )
)


def untrained_names() -> list[str]:
    """The ``untrained:NAME`` names every architecture accepts (for error messages)."""
    return (
        ["resnet18"]
        + list(SIZES)
        + [a for a, arch in ENCODER_ARCHS.items() if arch.untrained is not None and a not in ("vit", "resnet18")]
    )


def seeded_untrained(name: str, patch_size: int, img_size: int):
    """``untrained:NAME``: the first architecture that knows ``NAME``, initialised from ``torch.manual_seed(0)``;
    ``(module, arch, config)`` or None."""
    for arch in ENCODER_ARCHS.values():
        if arch.untrained is None:
            continue
        torch.manual_seed(0)
        got = arch.untrained(name, patch_size, img_size)
        if got is not None:
            return got[0], arch.name, got[1]
    return None
