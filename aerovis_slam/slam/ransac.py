"""Outlier rejection: 3D-2D absolute pose (OpenCV) and 2D-2D relative rotation (pure rotation).

Frames: ``T_cam_world`` maps world points into the camera (``p_cam = T_cam_world @ p_world``);
``R_1_0`` rotates camera-0 bearings into camera 1 (``b_1 ~ R_1_0 @ b_0`` for a pure rotation).

Example (PnP with known outliers):
    >>> rng = np.random.default_rng(0)
    >>> K = np.array([[200.0, 0, 160], [0, 200, 120], [0, 0, 1]])
    >>> pw = rng.uniform([-2, -1.5, 3], [2, 1.5, 6], (60, 3))
    >>> T = np.eye(4); T[:3, 3] = [0.1, -0.05, 0.2]
    >>> xy = project_points(pw, T, K)
    >>> xy[:12] += rng.uniform(20, 40, (12, 2))               # 12 gross outliers
    >>> ok, T_est, inl = pnp_ransac(pw, xy, K, reproj_px=2.0)
    >>> ok, bool(np.allclose(T_est, T, atol=1e-6)), bool(inl[:12].any()), int(inl.sum())
    (True, True, False, 48)
"""

from __future__ import annotations

import cv2
import numpy as np

from ..geometry import project, so3_log, transform_points


def project_points(points_world: np.ndarray, T_cam_world: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 3) world points -> (N, 2) pixels (NaN behind the camera)."""
    return project(transform_points(T_cam_world, np.asarray(points_world, np.float64)), K)[0]


def reprojection_error(points_world: np.ndarray, T_cam_world: np.ndarray, K: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(N,) pixel distance between world points (N, 3) projected at ``T_cam_world`` and observed
    pixels ``xy`` (N, 2); inf behind the camera or where anything is NaN, so that ``<= thr`` is the
    inlier test."""
    e = np.linalg.norm(project_points(points_world, T_cam_world, K) - xy, axis=1)
    return np.nan_to_num(e, nan=np.inf)


def rvec_tvec_to_T(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """OpenCV's (rvec, tvec) (Rodrigues vector, translation) -> the (4, 4) transform they describe."""
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3))[0]
    T[:3, 3] = np.asarray(tvec, np.float64).reshape(3)
    return T


def pnp_ransac(points_world: np.ndarray, xy: np.ndarray, K: np.ndarray, *, reproj_px: float = 2.0,
               iterations: int = 100, confidence: float = 0.999, T_guess: np.ndarray | None = None,
               min_inliers: int = 6) -> tuple[bool, np.ndarray, np.ndarray]:
    """Absolute pose of a calibrated camera from 3D-2D matches with outliers.

    ``cv2.solvePnPRansac`` (AP3P minimal samples, EPnP on the consensus set), then Levenberg-Marquardt
    refinement on the inliers (``cv2.solvePnPRefineLM``) and a final inlier re-classification with
    the refined pose.

    Args:
        points_world: (N, 3) landmarks. xy: (N, 2) their observed pixels. K: (3, 3) intrinsics.
        reproj_px: inlier threshold (pixels).
        T_guess: optional (4, 4) ``T_cam_world`` prior (e.g. the IMU prediction); when RANSAC
            fails or finds fewer inliers than the guess explains, the guess is refined instead.
        min_inliers: fewer inliers means failure.
    Returns:
        ok, ``T_cam_world`` (4, 4), inliers (N,) bool.
    """
    n = len(points_world)
    inl = np.zeros(n, bool)
    if n < 4:
        return False, np.eye(4) if T_guess is None else T_guess.copy(), inl
    obj = np.ascontiguousarray(points_world, np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(xy, np.float64).reshape(-1, 1, 2)
    best_T = None
    try:
        ok, rvec, tvec, idx = cv2.solvePnPRansac(obj, img, K, None, iterationsCount=int(iterations),
                                                 reprojectionError=float(reproj_px), confidence=float(confidence),
                                                 flags=cv2.SOLVEPNP_AP3P)
    except cv2.error:
        ok, idx = False, None
    if ok and idx is not None and len(idx) >= 4:
        best_T = rvec_tvec_to_T(rvec, tvec)
        inl[idx.ravel()] = True
    if T_guess is not None:
        guess_inl = reprojection_error(points_world, T_guess, K, xy) <= reproj_px
        if best_T is None or guess_inl.sum() > inl.sum():
            best_T, inl = T_guess.copy(), guess_inl
    if best_T is None or inl.sum() < 4:
        return False, np.eye(4) if T_guess is None else T_guess.copy(), np.zeros(n, bool)
    for _ in range(2):  # refine on the consensus set, then re-classify with the refined pose
        rvec = cv2.Rodrigues(best_T[:3, :3])[0]
        tvec = best_T[:3, 3].reshape(3, 1).copy()
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
        best_T = rvec_tvec_to_T(rvec, tvec)
        new_inl = reprojection_error(points_world, best_T, K, xy) <= reproj_px
        if new_inl.sum() < 4:
            break
        inl = new_inl
    return bool(inl.sum() >= min_inliers), best_T, inl


def bearings(xy: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 2) pixels -> (N, 3) unit bearing vectors in the camera frame."""
    b = np.concatenate([(np.asarray(xy, np.float64) - K[:2, 2]) / np.diag(K)[:2], np.ones((len(xy), 1))], axis=1)
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def kabsch_rotation(b0: np.ndarray, b1: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Rotation ``R`` minimising ``sum w |b1 - R b0|^2`` (Kabsch/Umeyama without translation), (3, 3)."""
    w = np.ones(len(b0)) if w is None else w
    H = (b0 * w[:, None]).T @ b1
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def rotation_ransac(b0: np.ndarray, b1: np.ndarray, *, threshold_rad: float, iterations: int = 200,
                    confidence: float = 0.999, rng: np.random.Generator | None = None,
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Pure-rotation model between two views: ``b1 ~ R_1_0 b0``, robust to outliers.

    Written by hand because OpenCV has no rotation-only estimator: a homography (8 DoF, 4-point
    samples) also fits planar scenes under translation, while the rotation needs 2-point samples
    and tells rotation from parallax. Hypotheses from 2 random pairs (Kabsch), scored by the angle
    between ``R b0`` and ``b1``; the best is refit on its inliers (twice).

    Args:
        b0, b1: (N, 3) unit bearings of matched keypoints in view 0 and view 1.
        threshold_rad: inlier angle.
    Returns:
        R_1_0 (3, 3) and inliers (N,) bool (all False when N < 2).
    """
    n = len(b0)
    if n < 2:
        return np.eye(3), np.zeros(n, bool)
    rng = rng or np.random.default_rng(0)
    cos_thr = np.cos(threshold_rad)
    best_inl = np.zeros(n, bool)
    best_R = np.eye(3)
    it, max_it = 0, int(iterations)
    while it < max_it:
        i, j = rng.choice(n, 2, replace=False)
        if abs(np.dot(b0[i], b0[j])) > 0.99999:  # nearly parallel bearings fix no rotation
            it += 1
            continue
        R = kabsch_rotation(b0[[i, j]], b1[[i, j]])
        inl = np.einsum("nd,nd->n", b0 @ R.T, b1) >= cos_thr
        if inl.sum() > best_inl.sum():
            best_inl, best_R = inl, R
            frac = best_inl.mean()
            # adaptive iteration count for 2-point samples
            if frac >= 1.0:
                break
            max_it = min(max_it, int(np.ceil(np.log(1 - confidence) / np.log(1 - frac ** 2))))
        it += 1
    for _ in range(2):
        if best_inl.sum() < 2:
            break
        best_R = kabsch_rotation(b0[best_inl], b1[best_inl])
        best_inl = np.einsum("nd,nd->n", b0 @ best_R.T, b1) >= cos_thr
    return best_R, best_inl


def relative_pose_ransac(xy0: np.ndarray, xy1: np.ndarray, K: np.ndarray, *, threshold_px: float = 1.0,
                         confidence: float = 0.999) -> tuple[np.ndarray | None, np.ndarray]:
    """General (translating) two-view model: ``cv2.findEssentialMat`` RANSAC, inliers (N,) bool.

    Returns:
        E (3, 3) or None, inliers.
    """
    n = len(xy0)
    if n < 5:
        return None, np.zeros(n, bool)
    E, mask = cv2.findEssentialMat(np.asarray(xy0, np.float64), np.asarray(xy1, np.float64), K,
                                   method=cv2.RANSAC, prob=confidence, threshold=threshold_px)
    if E is None or mask is None:
        return None, np.zeros(n, bool)
    return E[:3], mask.ravel().astype(bool)


def rotation_error_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle of ``R_a R_b^T`` in degrees."""
    return float(np.degrees(np.linalg.norm(so3_log(R_a @ R_b.T))))



def position_given_rotation(points_world: np.ndarray, xy: np.ndarray, cam_index: np.ndarray, Ks: list[np.ndarray],
                            T_body_cams: list[np.ndarray], R_world_body: np.ndarray, p_guess: np.ndarray, *,
                            huber_px: float = 1.5, iterations: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Body position from 3D-2D matches in any cameras of a rig when the body rotation is known.

    With the rotation fixed (e.g. integrated from the gyroscope, precise over short spans and free of
    gravity), the camera point ``p_c = A (X - p) + b`` (``A = R_bc^T R_wb^T``, ``b = -R_bc^T t_bc``) is
    linear in the body position ``p``, and ``m x p_c = 0`` for the normalised measurement ``m`` gives
    two linear equations per observation. Solved by iteratively reweighted least squares: rows are
    scaled by the focal length over the depth (so residuals are in pixels) and Huber-weighted. This
    avoids the rotation-translation ambiguity of a full single-camera PnP over a narrow field of view.

    Args:
        points_world: (N, 3). xy: (N, 2) pixels. cam_index: (N,) camera of each observation.
        Ks, T_body_cams: per camera intrinsics and camera-to-body transforms.
        R_world_body: (3, 3) known rotation. p_guess: (3,) initial position (for the depth weights).
    Returns:
        position (3,) and the final reprojection errors (N,) in pixels.
    """
    n = len(points_world)
    p = np.asarray(p_guess, np.float64).copy()
    if n < 2:
        return p, np.full(n, np.inf)
    A_list, b_list, m_list = [], [], []
    for i in range(n):
        c = int(cam_index[i])
        R_bc, t_bc = T_body_cams[c][:3, :3], T_body_cams[c][:3, 3]
        A = R_bc.T @ R_world_body.T
        b = -R_bc.T @ t_bc
        K = Ks[c]
        m = np.array([(xy[i, 0] - K[0, 2]) / K[0, 0], (xy[i, 1] - K[1, 2]) / K[1, 1], 1.0])
        A_list.append(A)
        b_list.append(b)
        m_list.append(m)
    A_all = np.stack(A_list)
    b_all = np.stack(b_list)
    m_all = np.stack(m_list)
    f_xy = np.array([[Ks[int(c)][0, 0], Ks[int(c)][1, 1]] for c in cam_index])  # (N, 2): fx, fy
    # rows of [m]x p_c: the first is the y residual (times depth), the second the x residual
    f_rows = f_xy[:, ::-1]
    S = np.zeros((n, 3, 3))  # cross-product matrices [m]x
    S[:, 0, 1], S[:, 0, 2] = -m_all[:, 2], m_all[:, 1]
    S[:, 1, 0], S[:, 1, 2] = m_all[:, 2], -m_all[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -m_all[:, 1], m_all[:, 0]
    SA = S @ A_all                                                    # (N, 3, 3): [m]x A
    rhs = np.einsum("nij,nj->ni", SA, points_world) + np.einsum("nij,nj->ni", S, b_all)  # [m]x (A X + b)
    err = np.full(n, np.inf)
    for _ in range(max(int(iterations), 1)):
        pc = np.einsum("nij,nj->ni", A_all, points_world - p) + b_all
        z = np.maximum(pc[:, 2], 1e-3)
        uv = pc[:, :2] / z[:, None]
        err = np.linalg.norm((uv - m_all[:, :2]) * f_xy, axis=1)
        w = np.where(err <= huber_px, 1.0, huber_px / np.maximum(err, 1e-12))
        scale = np.sqrt(w)[:, None] * f_rows / z[:, None]  # (N, 2): each row in pixels
        # the first two rows of [m]x are independent for m = (x, y, 1)
        M = (SA[:, :2, :] * scale[:, :, None]).reshape(-1, 3)
        y = (rhs[:, :2] * scale).reshape(-1)
        p, *_ = np.linalg.lstsq(M, y, rcond=None)
    pc = np.einsum("nij,nj->ni", A_all, points_world - p) + b_all
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm((pc[:, :2] / z[:, None] - m_all[:, :2]) * f_xy, axis=1)
    err[~(z > 0)] = np.inf
    return p, err
