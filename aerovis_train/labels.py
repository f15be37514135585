"""Detector labels, cross-modal: corners of the synchronised intensity frame (no pretrained network
can be downloaded here), kept where the corner is re-detected in the paired view.

The labeller is pluggable: any callable ``frame uint8 (H, W) -> xy (N, 2)`` works, e.g. a user's
frame-based SuperPoint run offline (``PrecomputedLabeller`` reads such keypoints from a file).
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from .correspondences import ViewGeometry, warp_with_depth

Labeller = Callable[[np.ndarray], np.ndarray]


class CornerLabeller:
    """Shi-Tomasi corners (OpenCV ``goodFeaturesToTrack``) as keypoint labels.

    Args:
        max_corners: at most this many per image.
        quality: relative corner-strength threshold (fraction of the strongest).
        min_distance: minimum spacing in pixels (about the NMS radius of the network's outputs).
    """

    def __init__(self, max_corners: int = 300, quality: float = 0.02, min_distance: int = 4, block_size: int = 5):
        self.max_corners, self.quality, self.min_distance, self.block_size = max_corners, quality, min_distance, block_size

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        pts = cv2.goodFeaturesToTrack(frame, self.max_corners, self.quality, self.min_distance, blockSize=self.block_size)
        return np.zeros((0, 2), np.float32) if pts is None else pts.reshape(-1, 2).astype(np.float32)


def cross_view_consistent(xy0: np.ndarray, xy1: np.ndarray, view0: ViewGeometry, view1: ViewGeometry, radius_px: float = 2.0) -> np.ndarray:
    """Mask (N0,) of view-0 labels that land within ``radius_px`` of a view-1 label (via depth and pose).

    Labels that leave view 1 or are occluded cannot be verified and are dropped too.
    """
    if len(xy0) == 0 or len(xy1) == 0:
        return np.zeros(len(xy0), bool)
    w, vis = warp_with_depth(xy0, view0, view1)
    # squared distances, no sqrt: a loader computes this for every pair (N0 x N1 ~ 300 x 300)
    d2 = ((w[:, None, :] - xy1[None, :, :]) ** 2).sum(-1).min(1)
    return vis & (d2 <= radius_px**2)  # NaN (not visible) compares False


def cell_labels(xy: np.ndarray, height: int, width: int, rng: np.random.Generator, cell: int = 8) -> np.ndarray:
    """65-class targets per cell: (H/cell, W/cell) int64, ``(y % 8) * 8 + (x % 8)`` of one keypoint of
    the cell (chosen at random when a cell has several), 64 (dustbin) for cells without keypoints."""
    hc, wc = height // cell, width // cell
    labels = np.full((hc, wc), cell * cell, np.int64)
    if len(xy) == 0:
        return labels
    px = np.rint(xy).astype(np.int64)
    ok = (px[:, 0] >= 0) & (px[:, 0] < wc * cell) & (px[:, 1] >= 0) & (px[:, 1] < hc * cell)
    px = px[ok][rng.permutation(int(ok.sum()))]  # random order: the last write per cell wins at random
    labels[px[:, 1] // cell, px[:, 0] // cell] = (px[:, 1] % cell) * cell + (px[:, 0] % cell)
    return labels
