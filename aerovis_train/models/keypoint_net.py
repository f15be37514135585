"""The keypoint network: encoder (stride 8) + detector head + descriptor head, dense outputs.

Cell convention (shared with the detector loss and every exported model): inside an 8x8 cell,
the pixel at row ``dy`` and column ``dx`` is logit channel ``k = 8 * dy + dx``; channel 64 is
the "no keypoint" dustbin. :func:`depth_to_space` turns the 64 position channels into the
full-resolution map with that order and is the same arrangement as ``pixel_shuffle`` (ONNX
DepthToSpace, mode CRD); :func:`space_to_depth` is its inverse for building cell labels.

NMS, top-k and descriptor sampling stay outside the network (they are not part of the
exported graph).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from aerovis_train.models.encoders import Encoder
from aerovis_train.models.heads import DescriptorHead, DetectorHead, PixelDetectorHead


def depth_to_space(x: torch.Tensor, cell: int = 8) -> torch.Tensor:
    """Cell channels to pixels: (B, cell*cell, h, w) -> (B, h*cell, w*cell).

    ``out[b, y*cell + dy, x*cell + dx] = x[b, cell*dy + dx, y, x]``. Written as
    reshape/permute so that torch and every exporter agree on the order.
    """
    _, c, h, w = x.shape
    if c != cell * cell:
        raise ValueError(f"depth_to_space needs {cell * cell} channels, got {c}")
    x = x.reshape(-1, cell, cell, h, w).permute(0, 3, 1, 4, 2)  # (B, h, dy, w, dx)
    return x.reshape(-1, h * cell, w * cell)


def space_to_depth(x: torch.Tensor, cell: int = 8) -> torch.Tensor:
    """Inverse of :func:`depth_to_space`: (B, H, W) -> (B, cell*cell, H/cell, W/cell)."""
    b, hh, ww = x.shape
    if hh % cell or ww % cell:
        raise ValueError(f"space_to_depth needs sides divisible by {cell}, got {hh}x{ww}")
    x = x.reshape(b, hh // cell, cell, ww // cell, cell).permute(0, 2, 4, 1, 3)  # (B, dy, dx, h, w)
    return x.reshape(b, cell * cell, hh // cell, ww // cell)


class KeypointNet(nn.Module):
    """SuperPoint-style event keypoint network (SuperEvent, SuperEvent+, SuperLitE, ...).

    Args:
        encoder: Any :class:`~aerovis_train.models.encoders.Encoder` (stride 8).
        descriptor_dim: Descriptor length D.
        head_width: Hidden width of both heads (256 in SuperPoint).
        name: Model name (e.g. ``superlite``), carried into export metadata.
        encoder_name: Registry name of the encoder (e.g. ``vgg_lite``).
        mcts: The time-surface this network expects, ``{"kind": "ne"|"dt", "params": [...]}``
            (events per pixel for ``ne``, windows in ms for ``dt``); carried along, checked
            against ``in_channels`` (2 polarities x len(params)).
        detector_pixel: ``{"width", "depth"[, "within_cell"]}`` of a
            :class:`~aerovis_train.models.heads.PixelDetectorHead` whose full-resolution logits are
            added to the detector's 64 position channels; None (default): the cell head alone, as
            SuperPoint. ``within_cell: true`` shifts the sum back per cell so that its log-sum-exp
            over the 64 positions is the cell head's: the branch then moves a keypoint inside its
            cell but leaves each cell's keypoint probability (one minus the dustbin's) unchanged.

    Shapes:
        input: (B, in_channels, H, W) float, H and W multiples of ``size_multiple``.
        ``logits``: (B, 65, H/8, W/8) raw detector logits (for the cross-entropy loss).
        ``scores``: (B, H, W) float32 keypoint probability (softmax over 65, dustbin dropped).
        ``descriptors``: (B, D, H/8, W/8) float32, unit L2 norm along D.

    Example:
        >>> from aerovis_train.models.encoders import VGGEncoder
        >>> net = KeypointNet(VGGEncoder(8), descriptor_dim=64).eval()
        >>> out = net(torch.zeros(1, 8, 16, 24))
        >>> tuple(out["logits"].shape), tuple(out["scores"].shape), tuple(out["descriptors"].shape)
        ((1, 65, 2, 3), (1, 16, 24), (1, 64, 2, 3))
    """

    cell: int = 8

    def __init__(self, encoder: Encoder, descriptor_dim: int, head_width: int = 256, *, name: str = "keypoint_net",
                 encoder_name: str | None = None, mcts: Mapping[str, Any] | None = None,
                 detector_pixel: Mapping[str, Any] | None = None):
        super().__init__()
        if encoder.stride != self.cell:
            raise ValueError(f"encoder stride must be {self.cell}, got {encoder.stride}")
        if descriptor_dim < 1 or head_width < 1:
            raise ValueError(f"descriptor_dim and head_width must be positive, got {descriptor_dim}, {head_width}")
        self.encoder = encoder
        self.detector = DetectorHead(encoder.out_channels, head_width, self.cell)
        self.descriptor = DescriptorHead(encoder.out_channels, descriptor_dim, head_width)
        if detector_pixel is not None:
            unknown = set(detector_pixel) - {"width", "depth", "within_cell"}
            if unknown:
                raise ValueError(f"detector_pixel takes width, depth and within_cell, got {sorted(unknown)}")
            within = detector_pixel.get("within_cell", False)
            if not isinstance(within, bool):
                raise ValueError(f"detector_pixel.within_cell must be true or false, got {within!r}")
            self.detector_pixel = PixelDetectorHead(encoder.in_channels, **{k: int(v) for k, v in detector_pixel.items()
                                                                            if k != "within_cell"})
            self.pixel_within_cell = within
        else:
            self.detector_pixel = None
            self.pixel_within_cell = False
        self.descriptor_dim = int(descriptor_dim)
        self.head_width = int(head_width)
        self.name = name
        self.encoder_name = encoder_name or type(encoder).__name__
        self.mcts = dict(mcts) if mcts is not None else None
        if self.mcts is not None:
            _check_mcts(self.mcts, encoder.in_channels)

    @property
    def in_channels(self) -> int:
        """Input channels (MCTS channels)."""
        return self.encoder.in_channels

    @property
    def size_multiple(self) -> int:
        """Input height and width must be multiples of this (8, or 40 for MaxViT)."""
        return self.encoder.size_multiple

    def valid_size(self, height: int, width: int) -> tuple[int, int]:
        """Largest (height, width) not above the given one that this network accepts (crop to it).

        Example:
            >>> from aerovis_train.models.encoders import MaxViTEncoder
            >>> KeypointNet(MaxViTEncoder(8), 256).valid_size(240, 424)
            (240, 400)
        """
        m = self.size_multiple
        return height // m * m, width // m * m

    def check_input(self, x: torch.Tensor) -> None:
        """Raises ValueError unless ``x`` is (B, in_channels, H, W) with H, W multiples of ``size_multiple``."""
        if x.ndim != 4:
            raise ValueError(f"{self.name} expects input (B, {self.in_channels}, H, W), got shape {tuple(x.shape)}")
        if x.shape[1] != self.in_channels:
            raise ValueError(f"{self.name} expects {self.in_channels} input channels, got {x.shape[1]} (shape {tuple(x.shape)})")
        h, w = x.shape[2], x.shape[3]
        m = self.size_multiple
        if h % m or w % m or h == 0 or w == 0:
            why = f"8 x partition size {m // 8}" if m != self.cell else "the cell size"
            hint = f"; crop to {self.valid_size(h, w)[0]}x{self.valid_size(h, w)[1]}" if h >= m and w >= m else ""
            raise ValueError(f"{self.name} ({self.encoder_name}) needs input height and width to be multiples of {m} "
                             f"({why}), got {h}x{w}{hint}")

    def forward_dense(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Unchecked forward: (logits, scores, descriptors) with the shapes of :meth:`forward`."""
        feats = self.encoder(x)
        logits = self.detector(feats)
        if self.detector_pixel is not None:
            # pixel logits regrouped into the cell channels (k = 8 * dy + dx) and added to the
            # positions; the dustbin is left to the cell head, which sees the whole cell
            pixel = space_to_depth(self.detector_pixel(x)[:, 0], self.cell)
            positions = logits[:, : self.cell * self.cell]
            moved = positions + pixel
            if self.pixel_within_cell:
                # same log-sum-exp over the cell as before: against the dustbin the cell keeps the
                # cell head's probability, so which cells hold a keypoint is the cell head's call
                moved = moved - moved.float().logsumexp(1, keepdim=True).to(moved.dtype) \
                    + positions.float().logsumexp(1, keepdim=True).to(moved.dtype)
            logits = torch.cat([moved, logits[:, self.cell * self.cell:]], 1)
        # Softmax and normalisation in float32 even under autocast/FP16: FP16 probabilities
        # below ~6e-8 flush to zero and lose weak keypoints.
        prob = logits.float().softmax(1)[:, : self.cell * self.cell]
        scores = depth_to_space(prob, self.cell)
        descriptors = F.normalize(self.descriptor(feats).float(), p=2.0, dim=1, eps=1e-12)
        return logits, scores, descriptors

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """(B, C, H, W) -> ``{"logits", "scores", "descriptors"}`` (see class docstring)."""
        self.check_input(x)
        logits, scores, descriptors = self.forward_dense(x)
        return {"logits": logits, "scores": scores, "descriptors": descriptors}

    def metadata(self) -> dict[str, Any]:
        """What a deployment needs to feed this network and read its outputs (JSON-able)."""
        from aerovis_slam.mcts import CHANNEL_ORDER

        return {
            "name": self.name,
            "encoder": self.encoder_name,
            "in_channels": self.in_channels,
            "descriptor_dim": self.descriptor_dim,
            "head_width": self.head_width,
            "cell": self.cell,
            "size_multiple": self.size_multiple,
            "cell_channel_order": "k = 8 * dy + dx, dustbin last",
            "mcts": None if self.mcts is None else {**self.mcts, "channel_order": CHANNEL_ORDER},
            "detector_pixel": None if self.detector_pixel is None else {"width": self.detector_pixel.width,
                                                                        "depth": self.detector_pixel.depth,
                                                                        "within_cell": self.pixel_within_cell},
        }


class ExportWrapper(nn.Module):
    """ONNX-facing view of a :class:`KeypointNet`: ``x -> (scores, descriptors)`` as a tuple.

    Input checks are skipped inside the graph (they would be traced as constants); check the
    example input with ``net.check_input`` before exporting.

    Shapes:
        (B, C, H, W) -> scores (B, H, W), descriptors (B, D, H/8, W/8).
    """

    input_names = ("mcts",)
    output_names = ("scores", "descriptors")

    def __init__(self, net: KeypointNet):
        super().__init__()
        self.net = net
        # Start in the net's mode: exporters restore the wrapper's mode recursively afterwards,
        # so a fresh (training-mode) wrapper would flip an eval() net back to training.
        self.train(net.training)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, C, H, W) -> (scores, descriptors)."""
        _, scores, descriptors = self.net.forward_dense(x)
        return scores, descriptors


def _check_mcts(mcts: Mapping[str, Any], in_channels: int) -> None:
    kind, params = mcts.get("kind"), mcts.get("params")
    if kind not in ("ne", "dt"):
        raise ValueError(f"mcts.kind must be 'ne' (events per pixel) or 'dt' (windows in ms), got {kind!r}")
    if not params:
        raise ValueError(f"mcts.params must list the {'events per pixel' if kind == 'ne' else 'windows in ms'}, got {params!r}")
    if 2 * len(params) != in_channels:
        raise ValueError(f"mcts {kind} with {len(params)} params gives 2 x {len(params)} = {2 * len(params)} channels, "
                         f"but in_channels is {in_channels}")
