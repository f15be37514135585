"""SuperPoint-style heads on the stride-8 encoder grid.

Both heads are 3x3 conv -> ``width`` (BatchNorm, ReLU) -> 1x1 conv. The final 1x1 convs keep
their bias and have no BatchNorm: their outputs are logits / raw descriptors.
"""

from __future__ import annotations

import torch
from torch import nn

from aerovis_train.models.encoders import ConvBNAct


class DetectorHead(nn.Module):
    """Keypoint logits per 8x8 cell: 64 positions (channel ``8 * dy + dx``) + 1 dustbin.

    Args:
        in_channels: Encoder output channels.
        width: Hidden channels of the 3x3 conv (256 in SuperPoint).
        cell: Cell side; the head predicts ``cell**2 + 1`` classes.

    Shapes:
        (B, in_channels, h, w) -> (B, cell**2 + 1, h, w).
    """

    def __init__(self, in_channels: int, width: int = 256, cell: int = 8):
        super().__init__()
        self.conv = ConvBNAct(in_channels, width, 3)
        self.out = nn.Conv2d(width, cell * cell + 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, h, w) -> logits (B, cell**2 + 1, h, w)."""
        return self.out(self.conv(x))


class DescriptorHead(nn.Module):
    """Dense descriptors on the stride-8 grid (not normalised here; the network does it).

    Args:
        in_channels: Encoder output channels.
        descriptor_dim: Output channels D.
        width: Hidden channels of the 3x3 conv (256 in SuperPoint).

    Shapes:
        (B, in_channels, h, w) -> (B, descriptor_dim, h, w).
    """

    def __init__(self, in_channels: int, descriptor_dim: int, width: int = 256):
        super().__init__()
        self.conv = ConvBNAct(in_channels, width, 3)
        self.out = nn.Conv2d(width, descriptor_dim, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, h, w) -> raw descriptors (B, D, h, w)."""
        return self.out(self.conv(x))
