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


class PixelDetectorHead(nn.Module):
    """Full-resolution keypoint logits from the input itself, added to the cell head's 64 positions.

    The cell head sees the input only through three 2x2 max-pools, so inside its 8x8 cell it
    chooses a pixel from pooled features; this branch looks at the time surface at full
    resolution (receptive field ``2 * depth + 1`` px) and moves the choice to where the local
    shape puts it. Its last conv starts at zero, so a network given this branch starts as the
    one without it (``init_weights`` of a model without the branch loads unchanged).

    Args:
        in_channels: Input (MCTS) channels.
        width: Hidden channels of the 3x3 convs.
        depth: Number of 3x3 convs (``depth - 1`` conv+BN+ReLU, then one conv to 1 channel).

    Shapes:
        (B, in_channels, H, W) -> (B, 1, H, W) logits in pixel units.
    """

    def __init__(self, in_channels: int, width: int = 16, depth: int = 3):
        super().__init__()
        if width < 1 or depth < 1:
            raise ValueError(f"detector_pixel needs width >= 1 and depth >= 1, got width={width}, depth={depth}")
        layers: list[nn.Module] = []
        c = in_channels
        for _ in range(depth - 1):
            layers.append(ConvBNAct(c, width, 3))
            c = width
        self.body = nn.Sequential(*layers)
        self.out = nn.Conv2d(c, 1, 3, padding=1)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)
        self.width, self.depth = int(width), int(depth)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) -> pixel logits (B, 1, H, W)."""
        return self.out(self.body(x))


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
