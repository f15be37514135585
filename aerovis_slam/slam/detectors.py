"""Stereo detector contract of the SLAM runtime, and the classical implementation of it.

A detector for :func:`~aerovis_slam.slam.pipeline.run_slam` has

* ``detect(batch) -> [Keypoints, Keypoints]`` for a float32 MCTS batch (2, C, H, W) (left, right);
* ``mcts_kind`` (``"ne"`` | ``"dt"``) and ``mcts_params`` (events per pixel, or windows in ms): the
  time surface it expects;
* ``size_multiple``: H and W are cropped (top-left) to multiples of it before ``detect``;
* ``name``.

:class:`~aerovis_slam.bundle.BundleDetector` (ONNX Runtime, learned) is one; :class:`StereoClassicalDetector`
runs :mod:`aerovis_slam.classical` (ORB, SIFT, Shi-Tomasi + rBRIEF) on the same MCTS, the baseline
of the benchmark.

Example:
    >>> import numpy as np
    >>> det = StereoClassicalDetector("sift", top_k=20)
    >>> batch = np.zeros((2, 8, 64, 96), np.float32)
    >>> batch[:, :, 20:40, 30:60] = 0.8
    >>> left, right = det.detect(batch)
    >>> det.mcts_kind, len(left) > 0, left.descriptors.dtype
    ('ne', True, dtype('float32'))
"""

from __future__ import annotations

import time

import numpy as np

from ..classical import make_detector
from ..keypoints import Keypoints
from ..mcts import MCTS_NE_EVENTS_PER_PX


class StereoClassicalDetector:
    """A classical detector applied to each image of a stereo MCTS batch.

    Args:
        kind: ``orb``, ``sift`` or ``gftt_brief`` (see :mod:`aerovis_slam.classical`).
        top_k: keypoints per image.
        mcts_kind, mcts_params: the time surface computed for it (default MCTS_Ne with the paper's
            0.03/0.1/0.3/1 events per pixel, the same surfaces the learned models see).
        **options: passed to :class:`~aerovis_slam.classical.ClassicalDetector`.

    Attributes:
        name: ``classical-<kind>``. size_multiple: 1 (no crop needed).
        last_latency_ms: duration of the last :meth:`detect` call.
    """

    def __init__(self, kind: str = "orb", top_k: int = 300, *, mcts_kind: str = "ne",
                 mcts_params: tuple[float, ...] = MCTS_NE_EVENTS_PER_PX, **options):
        self.kind = kind
        self.name = f"classical-{kind}"
        self.top_k = int(top_k)
        self.mcts_kind = mcts_kind
        self.mcts_params = tuple(float(p) for p in mcts_params)
        self.size_multiple = 1
        self._det = make_detector(kind, top_k=self.top_k, **options)
        self.last_latency_ms = 0.0

    def detect(self, batch: np.ndarray, *, top_k: int | None = None) -> list[Keypoints]:
        """(B, C, H, W) float32 MCTS -> one :class:`Keypoints` per image (at most ``top_k``)."""
        batch = np.asarray(batch)
        if batch.ndim != 4:
            raise ValueError(f"batch must be (B, C, H, W), got shape {batch.shape}")
        t0 = time.perf_counter()
        out = []
        for mcts in batch:
            kp = self._det(mcts)
            if top_k is not None and len(kp) > top_k:
                order = np.argsort(-kp.scores, kind="stable")[:top_k]
                kp = Keypoints(kp.xy[order], kp.scores[order], kp.descriptors[order])
            out.append(kp)
        self.last_latency_ms = (time.perf_counter() - t0) * 1e3
        return out
