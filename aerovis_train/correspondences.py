"""Ground-truth correspondences from camera poses (and depth where available).

Used by the training losses (dense, on the 8x8-cell grid), by the detector-label consistency check
and by evaluation/visualisation (sparse keypoint matches coloured by correctness). numpy only:
computed in data-loader workers, so the same code serves CPU and GPU training.

Conventions (as glue-factory): ``matches0[i] = j`` pairs keypoint i of view 0 with j of view 1,
``-1`` = unmatched (a true negative), ``-2`` = ignore (ambiguous, or no geometry to decide).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aerovis_slam import geometry as geo

UNMATCHED, IGNORE = -1, -2


def cell_centres(height: int, width: int, cell: int = 8) -> np.ndarray:
    """Pixel centres of the (height/cell) x (width/cell) grid, row-major: (Hc*Wc, 2) float64."""
    hc, wc = height // cell, width // cell
    ys, xs = np.meshgrid(np.arange(hc), np.arange(wc), indexing="ij")
    return np.stack([xs.ravel() * cell + (cell - 1) / 2, ys.ravel() * cell + (cell - 1) / 2], axis=1)


@dataclass
class ViewGeometry:
    """What the geometry of one view needs: intrinsics, pose, optional depth.

    Attributes:
        K: (3, 3) intrinsics of the (possibly cropped) image.
        T_world_cam: (4, 4) camera pose.
        depth: optional (H, W) z-depth in metres (inf/NaN where unknown).
        size: (width, height) of the image.
    """

    K: np.ndarray
    T_world_cam: np.ndarray
    depth: np.ndarray | None
    size: tuple[int, int]


def relative_pose(view0: ViewGeometry, view1: ViewGeometry) -> np.ndarray:
    """``T_1_0``: maps points from camera 0 to camera 1."""
    return geo.invert_T(view1.T_world_cam) @ view0.T_world_cam


def warp_with_depth(xy0: np.ndarray, view0: ViewGeometry, view1: ViewGeometry, depth_rel_tol: float = 0.05):
    """Warp pixels of view 0 into view 1 with view 0's depth; visibility checked against view 1's depth.

    Returns:
        xy1 (N, 2) and visible (N,) bool; invisible points also get NaN coordinates.
    """
    if view0.depth is None:
        raise ValueError("warp_with_depth needs the depth of view 0")
    d0 = geo.sample_depth_nearest(view0.depth, xy0)
    xy1, vis = geo.warp_pixels(xy0, d0, view0.K, view1.K, relative_pose(view0, view1), view1.depth,
                               image_size1=view1.size, depth_rel_tol=depth_rel_tol)
    xy1 = xy1.copy()
    xy1[~vis] = np.nan
    return xy1, vis


def keypoint_matches_depth(
    xy0: np.ndarray, xy1: np.ndarray, view0: ViewGeometry, view1: ViewGeometry, *, pos_px: float = 3.0, neg_px: float = 5.0
) -> np.ndarray:
    """Sparse GT matches from depth and poses: (N0,) matches0 with -1 unmatched, -2 ignored.

    A pair is positive when it is the mutual nearest neighbour in the symmetric reprojection error
    (max of the 0->1 and 1->0 errors) and that error is below ``pos_px``. A keypoint is unmatched
    when every candidate is farther than ``neg_px`` (or it is visible in the other view nowhere near a
    keypoint), ignored otherwise, including when it is occluded or leaves the image (no label).
    """
    n0, n1 = len(xy0), len(xy1)
    matches0 = np.full(n0, IGNORE, np.int64)
    if n0 == 0:
        return matches0
    w01, v01 = warp_with_depth(xy0, view0, view1)
    if n1 == 0:
        matches0[v01] = UNMATCHED
        return matches0
    w10, v10 = warp_with_depth(xy1, view1, view0)
    e01 = np.linalg.norm(w01[:, None, :] - xy1[None, :, :], axis=-1)  # (N0, N1), NaN if invisible
    e10 = np.linalg.norm(xy0[:, None, :] - w10[None, :, :], axis=-1)
    err = np.fmax(e01, e10)  # both directions must agree; fmax ignores one-sided NaN
    err[~v01] = np.nan
    err_f = np.where(np.isnan(err), np.inf, err)
    nn01 = err_f.argmin(1)
    nn10 = err_f.argmin(0)
    best = err_f[np.arange(n0), nn01]
    mutual = nn10[nn01] == np.arange(n0)
    pos = mutual & (best < pos_px)
    matches0[pos] = nn01[pos]
    neg = v01 & ~pos & (np.nanmin(np.where(np.isnan(e01), np.inf, e01), axis=1) > neg_px)
    matches0[neg] = UNMATCHED
    return matches0


def keypoint_matches_epipolar(
    xy0: np.ndarray, xy1: np.ndarray, view0: ViewGeometry, view1: ViewGeometry, *, pos_px: float = 2.0, neg_px: float = 6.0
) -> np.ndarray:
    """Sparse GT from poses alone (no depth): a keypoint whose epipolar line passes within
    ``pos_px`` of exactly one keypoint of view 1 (and that keypoint's line back passes within
    ``pos_px``) is matched to it; one whose line passes no keypoint within ``neg_px`` is unmatched;
    the rest are ambiguous and ignored. Weaker than depth (points along the line are confusable),
    as CAPS-style pose-only supervision is."""
    matches0 = np.full(len(xy0), IGNORE, np.int64)
    if len(xy0) == 0 or len(xy1) == 0:
        return matches0
    T = relative_pose(view0, view1)
    d01 = geo.epipolar_distance(xy0, xy1, view0.K, view1.K, T)
    d10 = geo.epipolar_distance(xy1, xy0, view1.K, view0.K, geo.invert_T(T)).T
    d = np.maximum(d01, d10)
    close = d < pos_px
    unique = close.sum(1) == 1
    j = d.argmin(1)
    matches0[unique] = j[unique]
    matches0[(d > neg_px).all(1)] = UNMATCHED
    return matches0


def grid_targets_depth(view0: ViewGeometry, view1: ViewGeometry, cell: int = 8):
    """Dense targets for the descriptor loss: where each cell centre of view 0 lands in view 1.

    Returns:
        warped (Hc0*Wc0, 2) float32 pixel positions in view 1 (NaN where invisible) and the
        visibility mask (Hc0*Wc0,) bool.
    """
    w, h = view0.size
    xy1, vis = warp_with_depth(cell_centres(h, w, cell), view0, view1)
    return xy1.astype(np.float32), vis


def pixel_targets_depth(view0: ViewGeometry, view1: ViewGeometry) -> np.ndarray:
    """Dense targets for the detector's repeatability loss: where every pixel of view 0 lands in view 1.

    Returns:
        (H0, W0, 2) float32 pixel positions (x, y) in view 1 of the pixel centres (integer coordinates,
        the convention of :func:`cell_centres`) of view 0; NaN where invisible.
    """
    w, h = view0.size
    # the cell grid at a cell of one pixel is the pixel grid, row-major
    return grid_targets_depth(view0, view1, cell=1)[0].reshape(h, w, 2)


def epipolar_lines(view0: ViewGeometry, view1: ViewGeometry, cell: int = 8) -> np.ndarray:
    """Epipolar lines in view 1 of the cell centres of view 0: (Hc0*Wc0, 3) (a, b, c), a^2 + b^2 = 1,
    so the distance of pixel (x, y) to a line is |a x + b y + c| (used by the pose-only loss)."""
    w, h = view0.size
    T = relative_pose(view0, view1)
    F = np.linalg.inv(view1.K).T @ geo.essential_from_pose(T) @ np.linalg.inv(view0.K)
    c = cell_centres(h, w, cell)
    lines = np.concatenate([c, np.ones((len(c), 1))], axis=1) @ F.T
    return (lines / np.maximum(np.linalg.norm(lines[:, :2], axis=1, keepdims=True), 1e-12)).astype(np.float32)
