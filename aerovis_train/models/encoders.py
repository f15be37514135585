"""Encoders of the keypoint networks: (B, C_in, H, W) -> (B, out_channels, H/8, W/8).

Four families, the ones the AERO-VIS architecture search compared:

* :class:`VGGEncoder` as ``vgg_lite`` (SuperLitE: one 3x3 conv per scale) and ``vgg``
  (SuperPoint: two convs per scale); same class, different ``depth``.
* :class:`MobileNetV3Encoder`: inverted residuals with squeeze-excitation and hardswish.
* :class:`MaxViTEncoder`: SuperEvent's 3-stage MaxViT (MBConv + window attention + grid
  attention per block) followed by a YOLOX-style PAFPN neck back down to stride 8.

Every encoder takes its hyper-parameters as plain keyword arguments whose defaults are the
values in ``conf/encoder/<name>.yaml`` (that YAML is the source the model builder reads; the
Python defaults only keep the classes usable on their own and are checked equal in the tests).
Width (``width_mult`` and/or ``channels``), ``depth`` and ``out_channels`` are the knobs an
architecture search varies.

Every module here exports to ONNX opset 18 and runs in ONNX Runtime: attention partitions are
plain reshape/permute, no ``pixel_unshuffle`` (which exports with a wrong channel order).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

STRIDE = 8  # every encoder's output stride: the keypoint cell size of the heads


def _per_stage(value: int | float | str | bool | Sequence, n: int, what: str) -> list:
    """Expands a scalar to ``n`` per-stage values, or checks a sequence has ``n`` entries."""
    if isinstance(value, (str, bool, int, float)):
        return [value] * n
    values = list(value)
    if len(values) != n:
        raise ValueError(f"{what} needs one value per stage ({n}), got {len(values)}: {values}")
    return values


def make_divisible(channels: float, divisor: int = 8) -> int:
    """Rounds a (width-multiplied) channel count to a multiple of ``divisor`` (MobileNet rule).

    Never goes below ``divisor`` nor more than 10 % under the request, so small multipliers
    still leave every layer some capacity.

    Example:
        >>> make_divisible(64 * 0.5), make_divisible(20), make_divisible(3)
        (32, 24, 8)
    """
    rounded = max(divisor, int(channels + divisor / 2) // divisor * divisor)
    if rounded < 0.9 * channels:
        rounded += divisor
    return rounded


class ConvBNAct(nn.Sequential):
    """Conv2d (no bias: BatchNorm follows) + BatchNorm2d + activation; 'same' padding."""

    def __init__(self, c_in: int, c_out: int, kernel: int = 3, stride: int = 1, groups: int = 1, act: type[nn.Module] | None = nn.ReLU):
        layers: list[nn.Module] = [
            nn.Conv2d(c_in, c_out, kernel, stride, padding=kernel // 2, groups=groups, bias=False),
            nn.BatchNorm2d(c_out),
        ]
        if act is not None:
            layers.append(act())
        super().__init__(*layers)


_ACTIVATIONS: dict[str, type[nn.Module]] = {"relu": nn.ReLU, "hardswish": nn.Hardswish, "gelu": nn.GELU, "silu": nn.SiLU}


def _activation(name: str) -> type[nn.Module]:
    try:
        return _ACTIVATIONS[name]
    except KeyError:
        raise ValueError(f"unknown activation {name!r}; known: {sorted(_ACTIVATIONS)}") from None


class Encoder(nn.Module):
    """Common contract: ``in_channels``, ``out_channels``, ``stride`` (8), ``size_multiple``.

    ``size_multiple`` is what input height and width must be multiples of (8 for the CNNs,
    8 x partition size for MaxViT).
    """

    stride: int = STRIDE
    size_multiple: int = STRIDE

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        if in_channels < 1 or out_channels < 1:
            raise ValueError(f"in_channels and out_channels must be positive, got {in_channels} and {out_channels}")
        self.in_channels = int(in_channels)
        self.out_channels = int(out_channels)


# --------------------------------------------------------------------------------------------
# VGG (SuperPoint, SuperLitE)
# --------------------------------------------------------------------------------------------


class VGGEncoder(Encoder):
    """VGG encoder: ``depth`` 3x3 conv+BN+ReLU per scale, 2x2 max-pool between the 4 scales.

    SuperLitE (``vgg_lite``): ``depth=1``: 64 | pool | 64 | pool | 128 | pool | 128.
    SuperPoint (``vgg``): ``depth=2``: 64,64 | pool | 64,64 | pool | 128,128 | pool | 128,128.

    Args:
        in_channels: Input channels (MCTS channels: 8 for MCTS_Ne, 10 for MCTS_dt).
        channels: Widths of the first three scales (strides 1, 2, 4), before ``width_mult``.
        out_channels: Width of the last scale (stride 8), which is the encoder output; not
            scaled by ``width_mult`` since it is the interface to the heads.
        depth: Convs per scale, an int for all four or a list of four.
        width_mult: Multiplies ``channels`` (rounded to multiples of 8).

    Shapes:
        (B, in_channels, H, W) -> (B, out_channels, H/8, W/8); H, W multiples of 8.
    """

    def __init__(self, in_channels: int, channels: Sequence[int] = (64, 64, 128), out_channels: int = 128,
                 depth: int | Sequence[int] = 1, width_mult: float = 1.0):
        super().__init__(in_channels, out_channels)
        widths = [make_divisible(c * width_mult) for c in _per_stage(channels, 3, "channels")] + [int(out_channels)]
        depths = [int(d) for d in _per_stage(depth, 4, "depth")]
        if min(depths) < 1:
            raise ValueError(f"depth must be >= 1 per scale, got {depths}")
        layers: list[nn.Module] = []
        c = in_channels
        for i, (w, d) in enumerate(zip(widths, depths)):
            if i > 0:
                layers.append(nn.MaxPool2d(2, 2))
            for _ in range(d):
                layers.append(ConvBNAct(c, w, 3))
                c = w
        self.body = nn.Sequential(*layers)
        self.widths, self.depths = widths, depths

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C_in, H, W) -> (B, out_channels, H/8, W/8)."""
        return self.body(x)


# --------------------------------------------------------------------------------------------
# MobileNetV3
# --------------------------------------------------------------------------------------------


class SqueezeExcite(nn.Module):
    """Channel gating: global average -> 1x1 reduce -> ReLU -> 1x1 expand -> gate."""

    def __init__(self, channels: int, squeeze: int, gate: type[nn.Module] = nn.Hardsigmoid):
        super().__init__()
        self.reduce = nn.Conv2d(channels, squeeze, 1)
        self.expand = nn.Conv2d(squeeze, channels, 1)
        self.gate = gate()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) -> (B, C, H, W)."""
        s = x.mean((2, 3), keepdim=True)
        return x * self.gate(self.expand(F.relu(self.reduce(s))))


class InvertedResidual(nn.Module):
    """MobileNetV3 block: 1x1 expand -> kxk depthwise (stride) -> SE -> 1x1 project (linear).

    The residual is added where shape is kept (stride 1 and same width).
    """

    def __init__(self, c_in: int, c_out: int, expansion: float, kernel: int, stride: int, se: bool, act: type[nn.Module]):
        super().__init__()
        hidden = make_divisible(c_in * expansion)
        layers: list[nn.Module] = []
        if hidden != c_in:
            layers.append(ConvBNAct(c_in, hidden, 1, act=act))
        layers.append(ConvBNAct(hidden, hidden, kernel, stride, groups=hidden, act=act))
        if se:
            layers.append(SqueezeExcite(hidden, make_divisible(hidden / 4)))
        layers.append(ConvBNAct(hidden, c_out, 1, act=None))
        self.block = nn.Sequential(*layers)
        self.residual = stride == 1 and c_in == c_out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C_in, H, W) -> (B, C_out, H/stride, W/stride)."""
        y = self.block(x)
        return x + y if self.residual else y


class MobileNetV3Encoder(Encoder):
    """Small MobileNetV3 to stride 8: stem conv (stride 2, hardswish), four stages of inverted
    residuals, then a 1x1 conv+BN+hardswish to ``out_channels``.

    Args:
        in_channels: Input channels.
        stem_channels: Stem width (before ``width_mult``).
        channels: Output width of each stage (before ``width_mult``).
        depth: Blocks per stage (int or list); the first block of a stage carries its stride.
        expansion: Hidden/input width ratio of the blocks of each stage.
        kernel: Depthwise kernel size per stage.
        strides: Stride of each stage; with the stem's 2 their product must be 8.
        se: Squeeze-excitation per stage.
        act: Activation per stage, ``relu`` or ``hardswish``.
        width_mult: Multiplies stem and stage widths (rounded to multiples of 8).
        out_channels: Output width.

    Shapes:
        (B, in_channels, H, W) -> (B, out_channels, H/8, W/8); H, W multiples of 8.
    """

    def __init__(self, in_channels: int, stem_channels: int = 16, channels: Sequence[int] = (16, 24, 40, 64),
                 depth: int | Sequence[int] = (1, 2, 3, 2), expansion: float | Sequence[float] = (1, 4, 4, 6),
                 kernel: int | Sequence[int] = (3, 3, 5, 5), strides: Sequence[int] = (1, 2, 2, 1),
                 se: bool | Sequence[bool] = (True, False, True, True),
                 act: str | Sequence[str] = ("relu", "relu", "hardswish", "hardswish"),
                 width_mult: float = 1.0, out_channels: int = 128):
        super().__init__(in_channels, out_channels)
        n = len(list(channels))
        depths = [int(d) for d in _per_stage(depth, n, "depth")]
        expansions = [float(e) for e in _per_stage(expansion, n, "expansion")]
        kernels = [int(k) for k in _per_stage(kernel, n, "kernel")]
        stride_list = [int(s) for s in _per_stage(strides, n, "strides")]
        ses = [bool(s) for s in _per_stage(se, n, "se")]
        acts = [_activation(a) for a in _per_stage(act, n, "act")]
        if 2 * math.prod(stride_list) != STRIDE:
            raise ValueError(f"stem stride 2 x stage strides {stride_list} must give {STRIDE}")
        if min(depths) < 1:
            raise ValueError(f"depth must be >= 1 per stage, got {depths}")
        c = make_divisible(stem_channels * width_mult)
        layers: list[nn.Module] = [ConvBNAct(in_channels, c, 3, 2, act=nn.Hardswish)]
        for w, d, e, k, s, use_se, a in zip(channels, depths, expansions, kernels, stride_list, ses, acts):
            w = make_divisible(w * width_mult)
            for i in range(d):
                layers.append(InvertedResidual(c, w, e, k, s if i == 0 else 1, use_se, a))
                c = w
        layers.append(ConvBNAct(c, out_channels, 1, act=nn.Hardswish))
        self.body = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C_in, H, W) -> (B, out_channels, H/8, W/8)."""
        return self.body(x)


# --------------------------------------------------------------------------------------------
# MaxViT + PAFPN (SuperEvent, SuperEvent+)
# --------------------------------------------------------------------------------------------


def window_partition(x: torch.Tensor, p: int) -> torch.Tensor:
    """Non-overlapping p x p windows: (B, H, W, C) -> (B * H/p * W/p, p*p, C)."""
    _, h, w, c = x.shape
    x = x.reshape(-1, h // p, p, w // p, p, c).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(-1, p * p, c)


def window_reverse(x: torch.Tensor, p: int, h: int, w: int) -> torch.Tensor:
    """Inverse of :func:`window_partition`: (B * H/p * W/p, p*p, C) -> (B, H, W, C)."""
    c = x.shape[-1]
    x = x.reshape(-1, h // p, w // p, p, p, c).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(-1, h, w, c)


def grid_partition(x: torch.Tensor, p: int) -> torch.Tensor:
    """Sparse p x p grid (pixels H/p apart, i.e. dilated global mixing):
    (B, H, W, C) -> (B * H/p * W/p, p*p, C)."""
    _, h, w, c = x.shape
    x = x.reshape(-1, p, h // p, p, w // p, c).permute(0, 2, 4, 1, 3, 5)
    return x.reshape(-1, p * p, c)


def grid_reverse(x: torch.Tensor, p: int, h: int, w: int) -> torch.Tensor:
    """Inverse of :func:`grid_partition`: (B * H/p * W/p, p*p, C) -> (B, H, W, C)."""
    c = x.shape[-1]
    x = x.reshape(-1, h // p, w // p, p, p, c).permute(0, 3, 1, 4, 2, 5)
    return x.reshape(-1, h, w, c)


def relative_position_index(p: int) -> torch.Tensor:
    """(p*p, p*p) index into a ((2p-1)^2)-entry bias table for every (query, key) offset."""
    coords = torch.stack(torch.meshgrid(torch.arange(p), torch.arange(p), indexing="ij")).flatten(1)  # (2, p*p)
    rel = (coords[:, :, None] - coords[:, None, :]).permute(1, 2, 0) + (p - 1)  # (p*p, p*p, 2), >= 0
    return rel[..., 0] * (2 * p - 1) + rel[..., 1]


class PartitionAttention(nn.Module):
    """Multi-head self-attention inside partitions of p*p tokens, with a learned relative
    position bias (as MaxViT/Swin).

    Written with explicit matmul + softmax (no fused SDPA kernel) so the ONNX graph is the
    same on every exporter and runtime.
    """

    def __init__(self, dim: int, head_dim: int, p: int):
        super().__init__()
        if dim % head_dim:
            raise ValueError(f"attention width {dim} is not a multiple of head_dim {head_dim}")
        self.heads = dim // head_dim
        self.scale = head_dim ** -0.5
        self.p = p
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.rel_bias = nn.Parameter(torch.zeros((2 * p - 1) ** 2, self.heads))
        nn.init.trunc_normal_(self.rel_bias, std=0.02)
        self.register_buffer("rel_index", relative_position_index(p).flatten(), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B', N=p*p, C) -> (B', N, C)."""
        n, c = x.shape[1], x.shape[2]
        qkv = self.qkv(x).reshape(-1, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        q, k, v = qkv[0] * self.scale, qkv[1], qkv[2]  # (B', heads, N, head_dim)
        bias = self.rel_bias[self.rel_index].reshape(n, n, self.heads).permute(2, 0, 1)
        attn = (q @ k.transpose(-2, -1) + bias).softmax(-1)
        return self.proj((attn @ v).transpose(1, 2).reshape(-1, n, c))


class PartitionAttentionBlock(nn.Module):
    """Pre-norm transformer block over window or grid partitions (channels-last).

    x = x + Attn(LN(x)) over partitions; x = x + MLP(LN(x)).
    """

    def __init__(self, dim: int, head_dim: int, p: int, mlp_ratio: float, mode: str):
        super().__init__()
        if mode not in ("window", "grid"):
            raise ValueError(f"mode must be 'window' or 'grid', got {mode!r}")
        self.mode, self.p = mode, p
        self.norm1 = nn.LayerNorm(dim)
        self.attn = PartitionAttention(dim, head_dim, p)
        self.norm2 = nn.LayerNorm(dim)
        hidden = int(dim * mlp_ratio)
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, H, W, C) -> (B, H, W, C); H and W multiples of p."""
        h, w = x.shape[1], x.shape[2]
        if self.mode == "window":
            y = window_reverse(self.attn(window_partition(self.norm1(x), self.p)), self.p, h, w)
        else:
            y = grid_reverse(self.attn(grid_partition(self.norm1(x), self.p)), self.p, h, w)
        x = x + y
        return x + self.mlp(self.norm2(x))


class MBConv(nn.Module):
    """MaxViT's MBConv (channels-first): BN -> 1x1 expand -> BN GELU -> 3x3 depthwise -> BN GELU
    -> squeeze-excitation -> 1x1 project, plus the identity."""

    def __init__(self, dim: int, expansion: float, se_ratio: float):
        super().__init__()
        hidden = make_divisible(dim * expansion)
        layers: list[nn.Module] = [
            nn.BatchNorm2d(dim),
            ConvBNAct(dim, hidden, 1, act=nn.GELU),
            ConvBNAct(hidden, hidden, 3, groups=hidden, act=nn.GELU),
        ]
        if se_ratio > 0:
            # MaxViT sizes the squeeze from the block's input width, gates with a sigmoid.
            layers.append(SqueezeExcite(hidden, max(1, int(dim * se_ratio)), gate=nn.Sigmoid))
        layers.append(nn.Conv2d(hidden, dim, 1))
        self.block = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) -> (B, C, H, W)."""
        return x + self.block(x)


class MaxViTBlock(nn.Module):
    """One MaxViT block: [MBConv] -> window attention -> grid attention. NCHW in and out."""

    def __init__(self, dim: int, head_dim: int, p: int, mlp_ratio: float, mbconv: bool, mbconv_expansion: float, se_ratio: float):
        super().__init__()
        self.mbconv = MBConv(dim, mbconv_expansion, se_ratio) if mbconv else nn.Identity()
        self.window = PartitionAttentionBlock(dim, head_dim, p, mlp_ratio, "window")
        self.grid = PartitionAttentionBlock(dim, head_dim, p, mlp_ratio, "grid")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) -> (B, C, H, W)."""
        x = self.mbconv(x).permute(0, 2, 3, 1)  # attention and LayerNorm work channels-last
        return self.grid(self.window(x)).permute(0, 3, 1, 2)


class CSPLayer(nn.Module):
    """YOLOX CSP layer: two 1x1 branches, bottlenecks on one, concat, 1x1 fuse (SiLU, no
    shortcut inside the bottlenecks as in YOLOX's neck)."""

    def __init__(self, c_in: int, c_out: int, depth: int, expansion: float = 0.5):
        super().__init__()
        hidden = max(1, int(c_out * expansion))
        self.main = ConvBNAct(c_in, hidden, 1, act=nn.SiLU)
        self.side = ConvBNAct(c_in, hidden, 1, act=nn.SiLU)
        self.bottlenecks = nn.Sequential(*[
            nn.Sequential(ConvBNAct(hidden, hidden, 1, act=nn.SiLU), ConvBNAct(hidden, hidden, 3, act=nn.SiLU))
            for _ in range(depth)
        ])
        self.fuse = ConvBNAct(2 * hidden, c_out, 1, act=nn.SiLU)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C_in, H, W) -> (B, C_out, H, W)."""
        return self.fuse(torch.cat([self.bottlenecks(self.main(x)), self.side(x)], 1))


class PAFPNNeck(nn.Module):
    """YOLOX-style PAFPN over three levels (strides 2, 4, 8), reduced to its stride-8 output.

    Top-down: stride-8 features (1x1 lateral) are upsampled and fused into stride 4, then into
    stride 2; bottom-up: strided 3x3 convs carry the fine result back to stride 4 and 8, each
    time concatenated with the top-down lateral of that level. So the stride-8 output sees
    the stride-2 details that keypoint localisation inside a cell needs.
    """

    def __init__(self, widths: Sequence[int], out_channels: int, depth: int, expansion: float):
        super().__init__()
        c2, c4, c8 = widths
        self.lateral8 = ConvBNAct(c8, c4, 1, act=nn.SiLU)
        self.td4 = CSPLayer(2 * c4, c4, depth, expansion)
        self.lateral4 = ConvBNAct(c4, c2, 1, act=nn.SiLU)
        self.td2 = CSPLayer(2 * c2, c2, depth, expansion)
        self.down2 = ConvBNAct(c2, c2, 3, 2, act=nn.SiLU)
        self.bu4 = CSPLayer(2 * c2, c4, depth, expansion)
        self.down4 = ConvBNAct(c4, c4, 3, 2, act=nn.SiLU)
        self.bu8 = CSPLayer(2 * c4, out_channels, depth, expansion)

    def forward(self, f2: torch.Tensor, f4: torch.Tensor, f8: torch.Tensor) -> torch.Tensor:
        """Features at strides 2, 4, 8 -> (B, out_channels, H/8, W/8)."""
        lat8 = self.lateral8(f8)
        td4 = self.td4(torch.cat([F.interpolate(lat8, scale_factor=2.0, mode="nearest"), f4], 1))
        lat4 = self.lateral4(td4)
        p2 = self.td2(torch.cat([F.interpolate(lat4, scale_factor=2.0, mode="nearest"), f2], 1))
        p4 = self.bu4(torch.cat([self.down2(p2), lat4], 1))
        return self.bu8(torch.cat([self.down4(p4), lat8], 1))


class MaxViTEncoder(Encoder):
    """SuperEvent backbone: 3-stage MaxViT (strides 2/4/8) + PAFPN neck to stride 8.

    Each stage: overlapping patch embedding (3x3 conv, stride 2, kernel > stride so patches
    overlap) then ``depth`` MaxViT blocks. The patch embedding has no norm of its own since
    the MBConv (BatchNorm) or attention (LayerNorm) after it normalises its input first.

    Args:
        in_channels: Input channels.
        channels: Widths of the three stages (before ``width_mult``; rounded to multiples of
            ``head_dim`` so every stage has whole heads).
        depth: MaxViT blocks per stage (int or list of 3).
        width_mult: Multiplies ``channels``.
        partition_size: Side p of attention windows and grids; every stage's map must be a
            multiple of p, hence input sides multiples of 8p.
        head_dim: Channels per attention head (heads = width / head_dim).
        mlp_ratio: Hidden/width ratio of the transformer MLPs.
        mbconv: Whether each block starts with an MBConv.
        mbconv_expansion: MBConv hidden/width ratio.
        se_ratio: MBConv squeeze width / block width (0 disables squeeze-excitation).
        neck_depth: Bottlenecks per PAFPN CSP layer.
        neck_expansion: CSP hidden/output width ratio.
        out_channels: Output width.

    Shapes:
        (B, in_channels, H, W) -> (B, out_channels, H/8, W/8); H, W multiples of 8p (40).
    """

    def __init__(self, in_channels: int, channels: Sequence[int] = (32, 64, 128), depth: int | Sequence[int] = 1,
                 width_mult: float = 1.0, partition_size: int = 5, head_dim: int = 8, mlp_ratio: float = 4.0,
                 mbconv: bool = True, mbconv_expansion: float = 4.0, se_ratio: float = 0.25,
                 neck_depth: int = 1, neck_expansion: float = 0.5, out_channels: int = 128):
        super().__init__(in_channels, out_channels)
        if partition_size < 1 or head_dim < 1:
            raise ValueError(f"partition_size and head_dim must be positive, got {partition_size}, {head_dim}")
        widths = [make_divisible(c * width_mult, head_dim) for c in _per_stage(channels, 3, "channels")]
        depths = [int(d) for d in _per_stage(depth, 3, "depth")]
        if min(depths) < 1:
            raise ValueError(f"depth must be >= 1 per stage, got {depths}")
        self.partition_size = int(partition_size)
        self.size_multiple = STRIDE * self.partition_size
        self.widths, self.depths = widths, depths
        self.stages = nn.ModuleList()
        c = in_channels
        for w, d in zip(widths, depths):
            self.stages.append(nn.Sequential(
                nn.Conv2d(c, w, 3, 2, padding=1),  # overlapping patch embedding
                *[MaxViTBlock(w, head_dim, partition_size, mlp_ratio, mbconv, mbconv_expansion, se_ratio) for _ in range(d)],
            ))
            c = w
        self.neck = PAFPNNeck(widths, out_channels, neck_depth, neck_expansion)
        self.apply(_init_transformer_linear)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C_in, H, W) -> (B, out_channels, H/8, W/8)."""
        feats = []
        for stage in self.stages:
            x = stage(x)
            feats.append(x)
        return self.neck(*feats)


def _init_transformer_linear(m: nn.Module) -> None:
    # ViT/MaxViT convention: small truncated-normal linear weights keep early attention
    # logits near zero (uniform attention) instead of PyTorch's fan-in uniform default.
    if isinstance(m, nn.Linear):
        nn.init.trunc_normal_(m.weight, std=0.02)
        nn.init.zeros_(m.bias)


ENCODERS: dict[str, type[Encoder]] = {
    "vgg_lite": VGGEncoder,
    "vgg": VGGEncoder,
    "mobilenetv3": MobileNetV3Encoder,
    "maxvit": MaxViTEncoder,
}
"""Encoder name (the file stem of ``conf/encoder/<name>.yaml``) -> class."""
