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
        subpixel_window: half-size (px) of OpenCV's ``cornerSubPix`` window that moves each corner
            to sub-pixel precision (0: the integer pixels ``goodFeaturesToTrack`` returns). With 3
            (a 7x7 window) the labels of the `train` preset land closer to where the other view's
            labels are (median cross-view distance 0.58 -> 0.22 px; docs/training.md, "Sub-pixel corner labels").
    """

    def __init__(self, max_corners: int = 300, quality: float = 0.02, min_distance: int = 4, block_size: int = 5,
                 subpixel_window: int = 0):
        if subpixel_window < 0:
            raise ValueError(f"subpixel_window must be >= 0 (0: integer corners), got {subpixel_window}")
        self.max_corners, self.quality, self.min_distance, self.block_size = max_corners, quality, min_distance, block_size
        self.subpixel_window = int(subpixel_window)

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        pts = cv2.goodFeaturesToTrack(frame, self.max_corners, self.quality, self.min_distance, blockSize=self.block_size)
        if pts is None:
            return np.zeros((0, 2), np.float32)
        pts = pts.reshape(-1, 1, 2).astype(np.float32)
        if self.subpixel_window:
            w = self.subpixel_window
            cv2.cornerSubPix(frame, pts, (w, w), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01))
        return pts.reshape(-1, 2)


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


def _one_label_per_cell(xy: np.ndarray, hc: int, wc: int, rng: np.random.Generator, cell: int) -> tuple[np.ndarray, np.ndarray]:
    """The labels that become cell targets: each label's nearest pixel must lie in the (hc x wc) cell
    grid, and of several in one cell one is kept at random (the last in a random order).

    Returns:
        (M, 2) float64 positions and (M, 2) int64 nearest pixels of the kept labels, one per cell.
    """
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    px = np.rint(xy).astype(np.int64)
    ok = (px[:, 0] >= 0) & (px[:, 0] < wc * cell) & (px[:, 1] >= 0) & (px[:, 1] < hc * cell)
    order = rng.permutation(int(ok.sum()))
    xy, px = xy[ok][order], px[ok][order]
    cells = (px[:, 1] // cell) * wc + px[:, 0] // cell
    _, last_reversed = np.unique(cells[::-1], return_index=True)
    keep = len(cells) - 1 - last_reversed
    return xy[keep], px[keep]


def cell_labels(xy: np.ndarray, height: int, width: int, rng: np.random.Generator, cell: int = 8) -> np.ndarray:
    """65-class targets per cell: (H/cell, W/cell) int64, ``(y % 8) * 8 + (x % 8)`` of one keypoint of
    the cell (chosen at random when a cell has several), 64 (dustbin) for cells without keypoints."""
    hc, wc = height // cell, width // cell
    labels = np.full((hc, wc), cell * cell, np.int64)
    if len(xy) == 0:
        return labels
    _, px = _one_label_per_cell(xy, hc, wc, rng, cell)
    labels[px[:, 1] // cell, px[:, 0] // cell] = (px[:, 1] % cell) * cell + (px[:, 0] % cell)
    return labels


def soft_cell_labels(xy: np.ndarray, height: int, width: int, rng: np.random.Generator, cell: int = 8) -> np.ndarray:
    """65-class target distributions per cell for sub-pixel keypoints: float32 (65, H/cell, W/cell).

    A keypoint belongs to the cell of its nearest pixel, as in :func:`cell_labels` (one keypoint per
    cell, chosen at random), and its unit mass is split bilinearly over the 2x2 pixels around it, so
    that the target's centroid is the keypoint's sub-pixel position: the post-processing's 3x3
    centroid (:func:`aerovis_slam.keypoints.refine_subpixel`) reads it back from probabilities trained
    towards it. Pixels of the 2x2 that fall in a neighbouring cell are dropped and the rest
    renormalised (a cell's classes are its own 64 pixels and the dustbin); a keypoint within half a
    pixel of a cell border therefore keeps up to 0.5 px of that error. Cells without a keypoint are
    the dustbin (class 64) with probability 1.
    """
    hc, wc = height // cell, width // cell
    target = np.zeros((cell * cell + 1, hc, wc), np.float32)
    target[cell * cell] = 1.0
    if len(xy) == 0:
        return target
    xy, px = _one_label_per_cell(xy, hc, wc, rng, cell)
    cy, cx = px[:, 1] // cell, px[:, 0] // cell
    base = np.floor(xy).astype(np.int64)
    frac = xy - base
    weights = np.zeros((len(xy), 4))
    corners = []
    for k, (dx, dy) in enumerate(((0, 0), (1, 0), (0, 1), (1, 1))):
        x, y = base[:, 0] + dx, base[:, 1] + dy
        w = (frac[:, 0] if dx else 1 - frac[:, 0]) * (frac[:, 1] if dy else 1 - frac[:, 1])
        same_cell = (x // cell == cx) & (y // cell == cy)  # floor division: -1 // 8 is cell -1, never cx
        weights[:, k] = np.where(same_cell, w, 0.0)
        corners.append((x, y))
    weights /= weights.sum(1, keepdims=True)  # the nearest pixel is always in the cell: the sum is > 0
    target[cell * cell, cy, cx] = 0.0
    for k, (x, y) in enumerate(corners):
        m = weights[:, k] > 0
        np.add.at(target, ((y[m] % cell) * cell + (x[m] % cell), cy[m], cx[m]), weights[m, k].astype(np.float32))
    return target
