"""Left-right matching along epipolar lines and triangulation (OpenCV).

Frames: ``T_1_0`` maps points from camera 0 (left) to camera 1 (right), ``p_1 = T_1_0 @ p_0``; it is
``inv(T_body_cam1) @ T_body_cam0`` from the calibration's ``T_imu_cam``. Pixels are ``(x, y)`` with
integer values at pixel centres, intrinsics ``K`` (3, 3) at the MCTS resolution.

Example (an exact synthetic case):
    >>> K = np.array([[100.0, 0, 64], [0, 100, 48], [0, 0, 1]])
    >>> T_1_0 = np.eye(4); T_1_0[0, 3] = -0.1                      # right camera 10 cm to the right
    >>> p0 = np.array([[0.2, -0.1, 2.0], [-0.5, 0.3, 4.0]])
    >>> xy0 = p0[:, :2] / p0[:, 2:] * 100 + [64, 48]
    >>> p1 = p0 + T_1_0[:3, 3]
    >>> xy1 = p1[:, :2] / p1[:, 2:] * 100 + [64, 48]
    >>> pts, ok = triangulate(xy0, xy1, K, K, T_1_0)
    >>> bool(np.allclose(pts, p0)), ok.tolist()
    (True, [True, True])
"""

from __future__ import annotations

import cv2
import numpy as np

from ..geometry import epipolar_distance, invert_T, project, transform_points
from ..keypoints import Keypoints, descriptor_similarity


def best_matches(sim: np.ndarray, allowed: np.ndarray, min_similarity: float, ratio: float = 0.0) -> np.ndarray:
    """Mutual best matches among allowed pairs: (M, 2) int64 ``(row, col)``.

    Args:
        sim: (N0, N1) similarity (higher is better).
        allowed: (N0, N1) bool candidate mask (geometric gate).
        min_similarity: a match needs at least this similarity.
        ratio: distinctiveness: the best allowed candidate of a row must beat the second by
            ``ratio * (1 - best)`` (0 disables).
    """
    if sim.size == 0:
        return np.zeros((0, 2), np.int64)
    s = np.where(allowed, sim, -np.inf)
    col = s.argmax(1)
    best = s[np.arange(len(s)), col]
    ok = best >= min_similarity
    if ratio > 0 and s.shape[1] > 1:
        second = np.partition(s, -2, axis=1)[:, -2]
        ok &= (best - second) >= ratio * (1.0 - best)
    row_of_col = s.argmax(0)
    ok &= row_of_col[col] == np.arange(len(s))  # mutual: the column's best row is this row
    rows = np.flatnonzero(ok)
    return np.stack([rows, col[rows]], axis=1).astype(np.int64)


def triangulate(xy0: np.ndarray, xy1: np.ndarray, K0: np.ndarray, K1: np.ndarray, T_1_0: np.ndarray,
                *, max_reproj_px: float = 2.0, min_depth: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Linear (DLT) triangulation of pixel pairs with ``cv2.triangulatePoints``.

    Args:
        xy0, xy1: (N, 2) pixels in camera 0 and camera 1.
        K0, K1: intrinsics. T_1_0: camera-0-to-camera-1 transform.
        max_reproj_px: a point is valid when it reprojects within this in both views.
        min_depth: and lies at least this far in front of both cameras (m).
    Returns:
        points (N, 3) in camera 0's frame (m) and valid (N,) bool.
    """
    n = len(xy0)
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    P0 = K0 @ np.eye(3, 4)
    P1 = K1 @ T_1_0[:3]
    X = cv2.triangulatePoints(P0, P1, np.asarray(xy0, np.float64).T, np.asarray(xy1, np.float64).T)
    w = X[3]
    with np.errstate(divide="ignore", invalid="ignore"):
        pts = (X[:3] / w).T
    finite = np.isfinite(pts).all(axis=1) & (np.abs(w) > 1e-12)
    pts = np.where(finite[:, None], pts, 0.0)
    uv0, z0 = project(pts, K0)
    pts1 = transform_points(T_1_0, pts)
    uv1, z1 = project(pts1, K1)
    with np.errstate(invalid="ignore"):
        e0 = np.linalg.norm(uv0 - xy0, axis=1)
        e1 = np.linalg.norm(uv1 - xy1, axis=1)
        valid = finite & (z0 > min_depth) & (z1 > min_depth) & (e0 <= max_reproj_px) & (e1 <= max_reproj_px)
    return pts, valid


def is_rectified(K0: np.ndarray, K1: np.ndarray, T_1_0: np.ndarray, tol: float = 1e-6) -> bool:
    """True for a rectified horizontal pair with camera 1 on the right: equal intrinsics, no rotation,
    a baseline along +x of camera 0 only (``T_1_0`` maps camera-0 points into camera 1, so its x
    translation is ``-b < 0``). The row search looks for the right view's match left of the left
    keypoint (disparity >= 0) and gtsam's stereo factor puts the right camera at +b; a pair with
    camera 1 on the left is matched by the general epipolar search instead (see
    :func:`swapped_pair_message`)."""
    return (np.allclose(K0, K1, atol=tol * 1e3) and np.allclose(T_1_0[:3, :3], np.eye(3), atol=tol)
            and abs(T_1_0[1, 3]) < tol and abs(T_1_0[2, 3]) < tol and T_1_0[0, 3] < 0)


def swapped_pair_message(K0: np.ndarray, K1: np.ndarray, T_1_0: np.ndarray) -> str | None:
    """A warning for a rectified pair whose camera 1 is left of camera 0 (``cam0``/``cam1`` swapped in
    the calibration), else None: such a rig runs, but without the rectified row search."""
    if is_rectified(K0, K1, T_1_0) or not is_rectified(K1, K0, invert_T(T_1_0)):
        return None
    return (f"cam1 lies {T_1_0[0, 3]:.3f} m to the left of cam0 (rectified pair): the runtime expects cam0 = left, "
            "cam1 = right and matches this pair without the rectified row search; swap cam0 and cam1 for it")


def uses_row_search(K0: np.ndarray, K1: np.ndarray, T_1_0: np.ndarray, images) -> bool:
    """Whether :func:`match_stereo` finds right positions by the rectified row search (the left
    keypoint shifted by the measured disparity) rather than by matching right keypoints."""
    return images is not None and is_rectified(K0, K1, T_1_0)


def search_disparity(img0: np.ndarray, img1: np.ndarray, xy0: np.ndarray, *, min_disparity: float, max_disparity: float,
                     radius: int = 4, min_ncc: float = 0.75, uniqueness: float = 0.1,
                     min_horizontal_gradient: float = 0.1, min_support: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """Disparities of left pixels in a rectified pair by patch correlation along the row.

    Event keypoints repeat poorly between the two cameras (about half of the left keypoints have a
    right keypoint within a pixel), while the two MCTS at the same time are nearly the same image
    shifted by the disparity. So each left keypoint's patch is correlated (``cv2.matchTemplate``,
    normalised cross-correlation) with the right image along its row over the admissible
    disparities, as classical rectified stereo does; a parabola through the peak and its neighbours
    gives the sub-pixel disparity (a 0.5 px error is 7 % of depth at 7 px disparity).

    Args:
        img0, img1: (H, W) float32 images of the left and right views (e.g. the channel mean of the
            MCTS, lightly blurred: events are a sparse point process, and a 1 px Gaussian makes the two
            views' patches correlate about twice as often at the same accuracy).
        xy0: (N, 2) left pixel positions.
        min_disparity, max_disparity: search range in pixels (from the depth range).
        radius: patch half-size. min_ncc: minimum correlation of the peak.
        uniqueness: the best score must beat any other score more than 1 px away by this margin.
        min_horizontal_gradient: minimum share of the patch's gradient energy along x.
        min_support: minimum fraction of the patch's pixels with a time-surface value (> 0.02).
    Returns:
        disparity (N,) float64 (``x0 - x1``) and ok (N,) bool (False: patch outside the image,
        textureless, sparse (noise events) or only row-parallel structure, weak or ambiguous peak, the peak at the end of the search range, or a failed
        left-right check: the right patch searched along the left row must land within 1 px).
    """
    H, W = img0.shape
    n = len(xy0)
    disp = np.zeros(n)
    ok = np.zeros(n, bool)
    r = int(radius)
    d_lo = max(int(np.floor(min_disparity)), 0)
    if n == 0:
        return disp, ok
    u = np.rint(xy0[:, 0]).astype(np.int64)
    v = np.rint(xy0[:, 1]).astype(np.int64)
    inside = (v - r >= 0) & (v + r < H) & (u - r >= 0) & (u + r < W)
    # Patch statistics for all pixels at once (box filters over the (2r+1)^2 window), read at the keypoints:
    # * support: isolated noise events give patches with a few lit pixels that correlate perfectly
    #   with any other lone dot, so the patch must be covered by structure;
    # * aperture: along an edge parallel to the row every disparity fits (floor lines, shelf
    #   edges), so part of the gradient energy must lie across the row.
    win = (2 * r + 1, 2 * r + 1)
    lit = cv2.boxFilter((img0 > 0.02).astype(np.float32), -1, win, normalize=True, borderType=cv2.BORDER_CONSTANT)
    gx = cv2.Sobel(img0, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img0, cv2.CV_32F, 0, 1, ksize=3)
    ex = cv2.boxFilter(gx * gx, -1, win, normalize=False, borderType=cv2.BORDER_CONSTANT)
    ey = cv2.boxFilter(gy * gy, -1, win, normalize=False, borderType=cv2.BORDER_CONSTANT)
    uc, vc = np.clip(u, 0, W - 1), np.clip(v, 0, H - 1)
    cand = inside & (lit[vc, uc] >= min_support) & (ex[vc, uc] > 1e-8)
    cand &= ex[vc, uc] >= min_horizontal_gradient * (ex[vc, uc] + ey[vc, uc])
    for i in np.flatnonzero(cand):
        u0, v0 = int(u[i]), int(v[i])
        d_hi = min(int(np.ceil(max_disparity)), u0 - r)  # the right patch must stay inside the image
        if d_hi - d_lo < 2:
            continue
        patch = img0[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1]
        # right patch centres u0 - d for d = d_hi .. d_lo (left to right in the strip)
        strip = img1[v0 - r:v0 + r + 1, u0 - d_hi - r:u0 - d_lo + r + 1]
        score = cv2.matchTemplate(strip, patch, cv2.TM_CCOEFF_NORMED)[0]
        k = int(np.argmax(score))
        best = float(score[k])
        if not (0 < k < len(score) - 1) or best < min_ncc:
            continue
        rest = score.copy()
        rest[max(k - 1, 0):k + 2] = -1.0
        if float(rest.max()) > best - uniqueness:
            continue
        d_int = d_hi - k
        # left-right consistency: the right patch, searched along the left row, must come back
        u1 = u0 - d_int
        d_back_hi = min(d_hi, W - 1 - r - u1)
        if d_back_hi - d_lo < 2:
            continue
        patch1 = img1[v0 - r:v0 + r + 1, u1 - r:u1 + r + 1]
        strip0 = img0[v0 - r:v0 + r + 1, u1 + d_lo - r:u1 + d_back_hi + r + 1]
        back = cv2.matchTemplate(strip0, patch1, cv2.TM_CCOEFF_NORMED)[0]  # index j: left centre u1 + d_lo + j
        if abs(int(np.argmax(back)) + d_lo - d_int) > 1:
            continue
        a, b, c = score[k - 1], score[k], score[k + 1]
        den = a - 2 * b + c
        delta = 0.5 * (a - c) / den if den < 0 else 0.0
        # strip index k is the right centre u0 - d_hi + k, so d = d_hi - (k + delta). That is the
        # shift of the patch around the keypoint's pixel u0 and so the keypoint's own disparity (the
        # two views are locally one image shifted): the keypoint's fraction of a pixel does not enter
        # (adding x0 - u0 made every disparity wrong by that fraction, 0.13 px rms for SuperLitE)
        disp[i] = d_hi - (k + delta)
        ok[i] = True
    return disp, ok


def match_stereo(kp0: Keypoints, kp1: Keypoints, K0: np.ndarray, K1: np.ndarray, T_1_0: np.ndarray, *,
                 min_similarity: float, max_epipolar_px: float = 1.5, min_disparity_px: float = 1.0,
                 max_depth_m: float = 30.0, min_depth_m: float = 0.3, ratio: float = 0.0,
                 rows0: np.ndarray | None = None, images: tuple[np.ndarray, np.ndarray] | None = None,
                 min_ncc: float = 0.75) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Find the right-view position of left keypoints along their epipolar lines and triangulate.

    * Rectified pair with images (:func:`is_rectified`): patch correlation along the row
      (:func:`search_disparity`) over the disparities of depths in ``[min_depth_m, max_depth_m]``.
    * Otherwise: right keypoints near the epipolar line (``epipolar_distance``) on the near side of
      the far-depth projection, chosen by mutual best descriptor similarity (:func:`best_matches`).

    Args:
        kp0, kp1: left and right keypoints.
        rows0: optional subset of left indices to match (default all).
        images: optional (left, right) float32 images for the rectified search.
    Returns:
        left indices (M,) int64 of the valid matches, points (M, 3) in camera 0's frame, and the right
        pixel positions (M, 2) (sub-pixel for the rectified search).
    """
    idx0 = np.arange(len(kp0)) if rows0 is None else np.asarray(rows0, np.int64)
    empty = (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 2)))
    if len(idx0) == 0:
        return empty
    xy0 = kp0.xy[idx0].astype(np.float64)
    if uses_row_search(K0, K1, T_1_0, images):
        fb = K0[0, 0] * abs(T_1_0[0, 3])
        d, ok = search_disparity(images[0], images[1], xy0, min_disparity=max(fb / max_depth_m, min_disparity_px),
                                 max_disparity=fb / min_depth_m, min_ncc=min_ncc)
        sel = np.flatnonzero(ok)
        a = xy0[sel]
        b = a - np.stack([d[sel], np.zeros(len(sel))], axis=1)
    else:
        if len(kp1) == 0:
            return empty
        xy1 = kp1.xy.astype(np.float64)
        allowed = epipolar_distance(xy0, xy1, K0, K1, T_1_0) <= max_epipolar_px
        # Disparity gate: where does a point at depth z (along the left ray) land in the right view?
        # Between the projections of the ray's far end (max depth) and a near point, so the match must
        # lie on the near side of the far projection by at least min_disparity_px.
        rays = np.concatenate([(xy0 - K0[:2, 2]) / np.diag(K0)[:2], np.ones((len(xy0), 1))], axis=1)
        far, _ = project(transform_points(T_1_0, rays * max_depth_m), K1)
        near, _ = project(transform_points(T_1_0, rays * min_depth_m), K1)
        direction = near - far
        direction = direction / np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-12)
        along = np.einsum("nd,nmd->nm", direction, xy1[None, :, :] - far[:, None, :])
        allowed &= along >= min_disparity_px
        sim = descriptor_similarity(kp0.descriptors[idx0], kp1.descriptors)
        m = best_matches(sim, allowed, min_similarity, ratio)
        sel, a, b = m[:, 0], xy0[m[:, 0]], xy1[m[:, 1]]
    if len(sel) == 0:
        return empty
    pts, valid = triangulate(a, b, K0, K1, T_1_0)
    valid &= (pts[:, 2] <= max_depth_m) & (pts[:, 2] >= min_depth_m)
    return idx0[sel[valid]], pts[valid], b[valid]
