"""Learned detectors for evaluation: a torch model (checkpoint or shipped name) as a callable
``mcts (C, H, W) -> Keypoints``, with the shared post-processing of :mod:`aerovis_slam.keypoints`."""

from __future__ import annotations

import os
import time

import numpy as np
import torch

from aerovis_slam.keypoints import Keypoints, extract_keypoints


class TorchDetector:
    """Run a :class:`~aerovis_train.models.keypoint_net.KeypointNet` on one MCTS.

    Attributes:
        name: model name (for tables).
        mcts_kind, mcts_params: the time surface the model expects (evaluation computes it).
        top_k, threshold, nms_radius: post-processing (None top_k: the evaluation's default).
    """

    def __init__(self, model: torch.nn.Module, model_cfg: dict, *, name: str | None = None, top_k: int | None = None,
                 threshold: float = 0.0, nms_radius: int = 2, device: str = "cpu"):
        self.model = model.to(device).eval()
        self.device = device
        self.name = name or model_cfg.get("name", "model")
        self.mcts_kind = model_cfg["mcts"]["kind"]
        self.mcts_params = tuple(float(p) for p in model_cfg["mcts"]["params"])
        self.size_multiple = int(getattr(model, "size_multiple", 8))
        self.top_k, self.threshold, self.nms_radius = top_k, threshold, nms_radius
        self.last_latency_ms = 0.0

    @torch.no_grad()
    def dense(self, mcts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(scores (H', W'), descriptor grid (D, H'/8, W'/8)) on the top-left crop to the size multiple."""
        c, h, w = mcts.shape
        m = self.size_multiple
        x = torch.from_numpy(np.ascontiguousarray(mcts[:, : h - h % m, : w - w % m]))[None].to(self.device)
        out = self.model(x)
        return out["scores"][0].cpu().numpy(), out["descriptors"][0].cpu().numpy()

    def __call__(self, mcts: np.ndarray, top_k: int | None = None) -> Keypoints:
        t0 = time.perf_counter()
        scores, grid = self.dense(mcts)
        k = top_k if top_k is not None else self.top_k
        kp = extract_keypoints(scores, grid, nms_radius=self.nms_radius, threshold=self.threshold, top_k=k)
        self.last_latency_ms = (time.perf_counter() - t0) * 1e3
        return kp


def load_detector(name_or_path: str | os.PathLike, **kwargs):
    """A shipped name (``superlite``...), a slim ``.pt`` or a ``train.py`` ``.ckpt`` -> :class:`TorchDetector`;
    a model bundle directory (``aerovis-export``) -> :class:`aerovis_slam.bundle.BundleDetector`.

    Both use the evaluation's post-processing (threshold 0 unless ``threshold`` is given, top-k by the
    protocol), so ``aerovis-eval pose --model superlite`` and ``--model BUNDLE_DIR`` compare alike.
    """
    if os.path.isdir(name_or_path):
        from aerovis_slam.bundle import BundleDetector

        kwargs.setdefault("threshold", 0.0)
        return BundleDetector(name_or_path, **kwargs)
    from ..checkpoints import load_model

    model, model_cfg, _ = load_model(name_or_path)
    return TorchDetector(model, model_cfg, **kwargs)
