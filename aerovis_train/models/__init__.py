"""Keypoint networks: registry, builder and size/cost counters.

``build_model(cfg)`` turns a model config (``conf/model/<name>.yaml``, or any dict/OmegaConf
node with the same keys) into a :class:`KeypointNet`::

    name: superlite            # carried into export metadata
    encoder: vgg_lite          # vgg_lite | vgg | mobilenetv3 | maxvit
    encoder_conf: {}           # overrides of conf/encoder/<encoder>.yaml
    in_channels: 8
    descriptor_dim: 64
    head_width: 256            # optional, default 256
    mcts: {kind: ne, params: [0.03, 0.1, 0.3, 1.0]}   # optional; checked against in_channels

An encoder's default hyper-parameters live only in ``conf/encoder/<encoder>.yaml`` in the
repository's ``conf/`` folder; ``encoder_conf`` may override any of its keys and nothing else
(a misspelt key is an error, not a silently ignored option). With Hydra, e.g.
``model.encoder=vgg model.descriptor_dim=128 +model.encoder_conf.width_mult=0.5``.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from aerovis_train.models.encoders import ENCODERS, Encoder
from aerovis_train.models.keypoint_net import ExportWrapper, KeypointNet, depth_to_space, space_to_depth

__all__ = [
    "CONF_DIR",
    "ENCODERS",
    "ExportWrapper",
    "KeypointNet",
    "build_encoder",
    "build_model",
    "count_flops",
    "count_parameters",
    "depth_to_space",
    "encoder_defaults",
    "space_to_depth",
]

CONF_DIR = Path(__file__).resolve().parents[2] / "conf"
"""The repository's Hydra config folder (``<repo>/conf``), home of ``encoder/*.yaml``."""


def encoder_defaults(name: str) -> dict[str, Any]:
    """Default hyper-parameters of encoder ``name`` from ``conf/encoder/<name>.yaml`` (without ``name``)."""
    if name not in ENCODERS:
        raise ValueError(f"unknown encoder {name!r}; known encoders: {sorted(ENCODERS)}")
    path = CONF_DIR / "encoder" / f"{name}.yaml"
    if not path.is_file():
        raise FileNotFoundError(f"encoder defaults {path} not found (the conf/ folder of the repository must sit "
                                f"next to the aerovis_train package; install it editable with `pip install -e .`)")
    conf = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    if not isinstance(conf, dict) or conf.get("name") != name:
        raise ValueError(f"{path}: expected a mapping with `name: {name}`, got name {conf.get('name') if isinstance(conf, dict) else conf!r}")
    conf.pop("name")
    return conf


def build_encoder(name: str, in_channels: int, overrides: Mapping[str, Any] | None = None) -> Encoder:
    """Encoder ``name`` with its YAML defaults, ``overrides`` merged on top.

    Raises:
        ValueError: Unknown encoder, or an override key the encoder's YAML does not have.
    """
    defaults = encoder_defaults(name)
    overrides = _plain(overrides) if overrides else {}
    unknown = sorted(set(overrides) - set(defaults))
    if unknown:
        raise ValueError(f"encoder_conf keys {unknown} are not options of encoder {name!r} "
                         f"(conf/encoder/{name}.yaml has: {sorted(defaults)})")
    merged = OmegaConf.to_container(OmegaConf.merge(defaults, overrides), resolve=True)
    try:
        return ENCODERS[name](in_channels=int(in_channels), **merged)
    except TypeError as exc:  # a YAML key the class does not take: the YAML and the code disagree
        raise ValueError(f"conf/encoder/{name}.yaml does not match {ENCODERS[name].__name__}: {exc}") from exc


def build_model(cfg: Mapping[str, Any] | DictConfig) -> KeypointNet:
    """A :class:`KeypointNet` from a model config (see the module docstring for the keys).

    Example:
        >>> net = build_model({"name": "superlite", "encoder": "vgg_lite", "in_channels": 8, "descriptor_dim": 64})
        >>> round(count_parameters(net) / 1e6, 2)
        0.89
    """
    cfg = _plain(cfg)
    missing = [k for k in ("name", "encoder", "in_channels", "descriptor_dim") if cfg.get(k) is None]
    if missing:
        raise ValueError(f"model config lacks {missing} (has {sorted(cfg)})")
    encoder = build_encoder(cfg["encoder"], cfg["in_channels"], cfg.get("encoder_conf") or {})
    return KeypointNet(
        encoder,
        descriptor_dim=int(cfg["descriptor_dim"]),
        head_width=int(cfg.get("head_width") or 256),
        name=str(cfg["name"]),
        encoder_name=cfg["encoder"],
        mcts=cfg.get("mcts"),
        detector_pixel=cfg.get("detector_pixel"),
    )


def count_parameters(model: torch.nn.Module, trainable_only: bool = False) -> int:
    """Number of parameters (BatchNorm affine weights included, running statistics not)."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad or not trainable_only)


def count_flops(model: torch.nn.Module, input_shape: tuple[int, ...]) -> int:
    """FLOPs of one forward pass on a zero input of ``input_shape`` (e.g. (1, 8, 240, 320)).

    Convention of ``torch.utils.flop_counter.FlopCounterMode``: 2 FLOPs per multiply-add of
    convolutions, linear layers and matrix products (attention included); normalisation,
    activations, softmax, pooling and element-wise ops are not counted. GFLOPs = result / 1e9;
    multiply-adds = result / 2.
    """
    from torch.utils.flop_counter import FlopCounterMode

    was_training = model.training
    device = next(model.parameters()).device
    model.eval()
    try:
        counter = FlopCounterMode(display=False)
        with torch.no_grad(), counter:
            model(torch.zeros(input_shape, device=device))
        return int(counter.get_total_flops())
    finally:
        model.train(was_training)


def _plain(cfg: Mapping[str, Any] | DictConfig) -> dict[str, Any]:
    if isinstance(cfg, DictConfig):
        return OmegaConf.to_container(cfg, resolve=True)
    return {k: (_plain(v) if isinstance(v, (Mapping, DictConfig)) else v) for k, v in dict(cfg).items()}
