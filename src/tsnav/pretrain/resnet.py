"""ResNet18, the baseline image encoder of the lineage and of the paper's Table III (paper §IV-B).

Written here (no torchvision); parameter names follow torchvision's layout (``conv1``, ``bn1``,
``layer1.0.conv1``, ``layer2.0.downsample.0``, ``fc`` ...) so a torchvision ImageNet state dict loads by key
with :func:`load_resnet_weights`. The navigation feature is the final ``512 x h x w`` map of ``layer4``
(h = w = ceil(S / 32)).

Deviation from the paper: the paper's baseline ResNet18 is ImageNet-pretrained. ImageNet weights cannot be
downloaded here, so when the user gives no local torchvision-layout weights file, the baseline is
pretrained *supervised on the world's own train images* with a multi-label target "which of the 22 target
categories are visible" (``tsnav pretrain --method resnet18-sup``; see ``train.py``).
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn as nn

from ..constants import NUM_CATEGORIES
from .model import read_state_dict


class BasicBlock(nn.Module):
    """Two 3x3 conv-BN layers with an identity (or 1x1 conv-BN ``downsample``) shortcut."""

    def __init__(self, cin: int, cout: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.downsample = (
            nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))
            if stride != 1 or cin != cout
            else None
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + (x if self.downsample is None else self.downsample(x)))


class ResNet18(nn.Module):
    """ResNet18: ``[N, 3, S, S]`` (ImageNet-normalised) -> logits ``[N, num_classes]``.

    Args:
        num_classes: outputs of the ``fc`` head (22 target categories for the supervised baseline; 1000
            for an ImageNet classifier).
    """

    feature_dim = 512

    def __init__(self, num_classes: int = NUM_CATEGORIES) -> None:
        super().__init__()
        self.num_classes = num_classes
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        widths, cin = (64, 128, 256, 512), 64
        for i, w in enumerate(widths):
            stride = 1 if i == 0 else 2
            setattr(self, f"layer{i + 1}", nn.Sequential(BasicBlock(cin, w, stride), BasicBlock(w, w, 1)))
            cin = w
        self.avgpool = nn.AdaptiveAvgPool2d(1)
        self.fc = nn.Linear(512, num_classes)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
        for m in self.modules():  # zero-init the last BN of each block (residual starts as identity)
            if isinstance(m, BasicBlock):
                nn.init.zeros_(m.bn2.weight)

    def feature_map(self, x: torch.Tensor) -> torch.Tensor:
        """Final feature map ``[N, 512, ceil(S/32), ceil(S/32)]`` (the navigation feature)."""
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        return self.layer4(self.layer3(self.layer2(self.layer1(x))))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(torch.flatten(self.avgpool(self.feature_map(x)), 1))

    def encoder_state_dict(self) -> dict[str, torch.Tensor]:
        """Everything but the ``fc`` head."""
        return {k: v for k, v in self.state_dict().items() if not k.startswith("fc.")}


def load_resnet_weights(model: ResNet18, path: str | Path) -> dict[str, list[str]]:
    """Load a torchvision-layout ResNet18 state dict (safetensors or ``.pth``, weights only) into ``model``.

    The ``fc`` head is loaded only when its shape matches (an ImageNet head does not fit 22 outputs; it is
    then reported under ``"ignored"``). Raises ``ValueError`` listing missing / unexpected keys.
    """
    sd = read_state_dict(path)
    own = model.state_dict()
    ignored = [k for k in sd if k.startswith("fc.") and (k not in own or sd[k].shape != own[k].shape)]
    sd = {k: v for k, v in sd.items() if k not in ignored}
    need = {k for k in own if not k.startswith("fc.")}
    missing = sorted(need - set(sd))
    unexpected = sorted(set(sd) - set(own))
    wrong = sorted(k for k in set(sd) & set(own) if sd[k].shape != own[k].shape)
    if missing or unexpected or wrong:
        raise ValueError(
            f"{path}: not a ResNet18 state dict: missing keys: {', '.join(missing[:8]) or 'none'}; "
            f"unexpected keys: {', '.join(unexpected[:8]) or 'none'}; "
            f"shape mismatches: {', '.join(wrong[:8]) or 'none'}"
        )
    model.load_state_dict(sd, strict=False)
    return {"loaded": sorted(sd), "ignored": sorted(ignored)}
