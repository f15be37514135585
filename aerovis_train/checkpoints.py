"""Checkpoints: atomic saving, slim (weights + config) files, the shipped defaults, loading by name.

Three forms load alike through :func:`load_model`:

* a shipped name (``superlite``, ``superevent_plus``, ``superevent``): ``aerovis_train/weights/<name>.pt``;
* a slim ``.pt`` written by :func:`save_slim` (``{"format": "aerovis-weights", "model_cfg", "state_dict", "meta"}``);
* a Lightning ``.ckpt`` of ``train.py`` (its hyper-parameters hold the resolved config).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import torch
from lightning.pytorch.plugins.io import TorchCheckpointIO

from aerovis_slam.errors import DataError
from aerovis_slam.fileio import atomic_write

from .models import build_model

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
SHIPPED = ("superlite", "superevent_plus", "superevent")
SLIM_FORMAT = "aerovis-weights"


class AtomicCheckpointIO(TorchCheckpointIO):
    """Write checkpoints to a temporary name, then rename: a run killed mid-save never leaves a
    truncated ``best.ckpt`` or ``last.ckpt`` (Lightning writes the final path directly)."""

    def save_checkpoint(self, checkpoint, path, storage_options=None) -> None:
        atomic_write(path, lambda tmp: super(AtomicCheckpointIO, self).save_checkpoint(checkpoint, tmp, storage_options))


def save_slim(model_cfg: dict, state_dict: dict, out: str | os.PathLike, meta: dict | None = None) -> Path:
    """Write weights + model config (float32, no optimiser state) atomically; returns the path."""
    blob = {"format": SLIM_FORMAT, "model_cfg": model_cfg, "state_dict": {k: v.detach().cpu() for k, v in state_dict.items()},
            "meta": meta or {}}
    return atomic_write(out, lambda tmp: torch.save(blob, tmp))


def lightning_model_state(ckpt: dict) -> dict:
    """The network's weights out of a ``train.py`` Lightning checkpoint (the module's ``model.`` prefix dropped)."""
    return {k[len("model."):]: v for k, v in ckpt["state_dict"].items() if k.startswith("model.")}


def resolve(name_or_path: str | os.PathLike) -> Path:
    """A shipped model name or a file path -> existing file path."""
    s = str(name_or_path)
    if s in SHIPPED:
        path = WEIGHTS_DIR / f"{s}.pt"
        if not path.exists():
            raise DataError(path, f"the shipped {s} weights are missing from this installation")
        return path
    path = Path(s)
    if not path.exists():
        raise DataError(path, f"no such checkpoint (and not a shipped model name: {', '.join(SHIPPED)})")
    return path


def file_sha256(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def load_model(name_or_path: str | os.PathLike, map_location="cpu"):
    """Load a model for inference. Returns ``(model in eval mode, model_cfg dict, meta dict)``.

    Raises:
        DataError: missing file, unreadable file, or a file that is no aerovis checkpoint.
    """
    path = resolve(name_or_path)
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as exc:  # torch raises several types for corrupt files
        raise DataError(path, f"not a readable torch checkpoint ({type(exc).__name__}: {exc})") from None
    if isinstance(ckpt, dict) and ckpt.get("format") == SLIM_FORMAT:
        model_cfg, state, meta = ckpt["model_cfg"], ckpt["state_dict"], dict(ckpt.get("meta", {}))
    elif isinstance(ckpt, dict) and "state_dict" in ckpt and "hyper_parameters" in ckpt:
        cfg = ckpt["hyper_parameters"].get("cfg")
        if cfg is None or "model" not in cfg:
            raise DataError(path, "Lightning checkpoint without the aerovis config in its hyper-parameters")
        model_cfg = cfg["model"]
        state = lightning_model_state(ckpt)
        meta = {"global_step": ckpt.get("global_step"), "epoch": ckpt.get("epoch")}
    else:
        raise DataError(path, "not an aerovis checkpoint (expected a slim .pt from save_slim or a train.py .ckpt)")
    model = build_model(model_cfg)
    missing, unexpected = model.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise DataError(path, f"weights do not fit the {model_cfg.get('name')} model: missing {missing[:5]}, unexpected {unexpected[:5]}")
    meta["sha256"] = file_sha256(path)
    meta["path"] = str(path)
    return model.eval(), model_cfg, meta
