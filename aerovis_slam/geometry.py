"""Rigid-body and pinhole geometry (numpy): the one implementation used by training labels,
evaluation, the simulator's checks and the SLAM runtime.

Conventions: ``T_a_b`` (4, 4) maps points from frame b to frame a (``p_a = T_a_b @ p_b``);
quaternions are ``(qx, qy, qz, qw)`` (Hamilton, as in the TUM format and the canonical ``/gt/pose``);
``pose7`` is ``tx ty tz qx qy qz qw``; pixels are ``(x = column, y = row)`` with integer values at
pixel centres; depth is z along the optical axis in metres.
"""

from __future__ import annotations

import numpy as np


# -- rotations ---------------------------------------------------------------------------------
def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions (x, y, z, w) -> (..., 3, 3) rotation matrices."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def rot_to_quat(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions (x, y, z, w) with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    m = R.reshape(-1, 3, 3)
    q = np.empty((len(m), 4))
    tr = np.trace(m, axis1=1, axis2=2)
    # Shepperd's method: pick the largest of (w, x, y, z) to divide by, for numerical stability
    cand = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    k = np.argmax(cand, axis=1)
    for i in range(len(m)):
        r = m[i]
        if k[i] == 0:
            s = 2 * np.sqrt(1 + tr[i])
            q[i] = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4]
        elif k[i] == 1:
            s = 2 * np.sqrt(1 + r[0, 0] - r[1, 1] - r[2, 2])
            q[i] = [s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
        elif k[i] == 2:
            s = 2 * np.sqrt(1 + r[1, 1] - r[0, 0] - r[2, 2])
            q[i] = [(r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
        else:
            s = 2 * np.sqrt(1 + r[2, 2] - r[0, 0] - r[1, 1])
            q[i] = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4, (r[1, 0] - r[0, 1]) / s]
    q *= np.where(q[:, 3:4] < 0, -1.0, 1.0)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q.reshape(R.shape[:-2] + (4,))


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angle in degrees of rotation matrices (..., 3, 3), in [0, 180].

    Uses ``atan2(|axis * sin|, cos)`` rather than ``arccos((trace - 1) / 2)``: the arccos loses
    all precision below ~0.1 deg, where the small rotation errors of a good estimate live.
    """
    R = np.asarray(R, np.float64)
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    return np.degrees(np.arctan2(np.linalg.norm(w, axis=-1) / 2.0, cos))


def pose_difference(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """How far apart two poses (4, 4) in one frame are: the translation norm (in the poses' units) and
    the rotation angle (degrees) of ``inv(T_a) @ T_b``, the motion from ``a`` to ``b`` in ``a``'s frame
    (a loop's correction, a relative pose's error against the ground truth)."""
    E = invert_T(np.asarray(T_a, np.float64)) @ np.asarray(T_b, np.float64)
    return float(np.linalg.norm(E[:3, 3])), float(rotation_angle_deg(E[:3, :3]))


def so3_exp(omega: np.ndarray) -> np.ndarray:
    """Rotation vector(s) (..., 3) in radians -> rotation matrices (..., 3, 3) (Rodrigues)."""
    omega = np.asarray(omega, dtype=np.float64)
    theta = np.linalg.norm(omega, axis=-1)[..., None, None]
    K = skew(omega)
    small = theta < 1e-8
    th = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(th) / th)
    b = np.where(small, 0.5, (1 - np.cos(th)) / th**2)
    return np.eye(3) + a * K + b * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> rotation vectors (..., 3) (angles below 180 degrees)."""
    q = rot_to_quat(R)
    v, w = q[..., :3], q[..., 3]
    n = np.linalg.norm(v, axis=-1)
    angle = 2 * np.arctan2(n, w)
    scale = np.where(n < 1e-12, 2.0, angle / np.maximum(n, 1e-300))
    return v * scale[..., None]


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices ``[v]x``."""
    v = np.asarray(v, dtype=np.float64)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


# -- poses -------------------------------------------------------------------------------------
def pose7_to_matrix(pose7: np.ndarray) -> np.ndarray:
    """(..., 7) ``tx ty tz qx qy qz qw`` -> (..., 4, 4) transforms."""
    pose7 = np.asarray(pose7, dtype=np.float64)
    T = np.zeros(pose7.shape[:-1] + (4, 4))
    T[..., :3, :3] = quat_to_rot(pose7[..., 3:])
    T[..., :3, 3] = pose7[..., :3]
    T[..., 3, 3] = 1.0
    return T


def matrix_to_pose7(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) transforms -> (..., 7) ``tx ty tz qx qy qz qw``."""
    T = np.asarray(T, dtype=np.float64)
    return np.concatenate([T[..., :3, 3], rot_to_quat(T[..., :3, :3])], axis=-1)


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4)."""
    T = np.asarray(T, dtype=np.float64)
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -(Rt @ T[..., :3, 3:4])[..., 0]
    Ti[..., 3, 3] = 1.0
    return Ti


def slerp(q0: np.ndarray, q1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Spherical interpolation of unit quaternions (N, 4) at fractions s (N,)."""
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)  # shortest arc
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin = np.sin(theta)
    near = sin < 1e-9
    w0 = np.where(near, 1 - s, np.sin((1 - s) * theta) / np.where(near, 1, sin))
    w1 = np.where(near, s, np.sin(s * theta) / np.where(near, 1, sin))
    q = w0[:, None] * q0 + w1[:, None] * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def interpolate_poses(t_query_us: np.ndarray, t_us: np.ndarray, pose7: np.ndarray) -> np.ndarray:
    """Poses at ``t_query_us`` (N,) from samples (M,), (M, 7): linear translation, slerp rotation.

    Raises:
        ValueError: a query lies outside ``[t_us[0], t_us[-1]]`` (no extrapolation).
    """
    t_query_us = np.atleast_1d(np.asarray(t_query_us, dtype=np.int64))
    if len(t_query_us) and (t_query_us.min() < t_us[0] or t_query_us.max() > t_us[-1]):
        raise ValueError(f"pose query times [{t_query_us.min()}, {t_query_us.max()}] µs outside the samples [{t_us[0]}, {t_us[-1]}] µs")
    if len(t_us) == 1:
        return np.repeat(pose7[:1], len(t_query_us), axis=0)
    i1 = np.clip(np.searchsorted(t_us, t_query_us, side="right"), 1, len(t_us) - 1)
    i0 = i1 - 1
    span = (t_us[i1] - t_us[i0]).astype(np.float64)
    s = np.where(span > 0, (t_query_us - t_us[i0]) / np.where(span > 0, span, 1), 0.0)
    s = np.clip(s, 0.0, 1.0)
    trans = pose7[i0, :3] * (1 - s[:, None]) + pose7[i1, :3] * s[:, None]
    return np.concatenate([trans, slerp(pose7[i0, 3:], pose7[i1, 3:], s)], axis=1)


# -- pinhole -----------------------------------------------------------------------------------
def project(points_cam: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (N, 3) -> pixels (N, 2) and depth z (N,). Points behind get NaN pixels."""
    p = np.asarray(points_cam, dtype=np.float64)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([K[0, 0] * p[:, 0] / z + K[0, 2], K[1, 1] * p[:, 1] / z + K[1, 2]], axis=1)
    uv[z <= 0] = np.nan
    return uv, z


def unproject(xy: np.ndarray, depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) with z-depth (N,) -> camera-frame points (N, 3)."""
    xy = np.asarray(xy, dtype=np.float64)
    depth = np.asarray(depth, dtype=np.float64)
    x = (xy[:, 0] - K[0, 2]) / K[0, 0] * depth
    y = (xy[:, 1] - K[1, 2]) / K[1, 1] * depth
    return np.stack([x, y, depth], axis=1)


def transform_points(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to points (N, 3)."""
    return points_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def sample_depth_nearest(depth: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Depth map (H, W) at pixels (N, 2), nearest pixel; NaN outside the image."""
    H, W = depth.shape
    finite = np.isfinite(xy).all(axis=1)
    safe = np.where(finite[:, None], xy, -1.0)  # NaN/inf would overflow the integer cast
    u = np.rint(safe[:, 0]).astype(np.int64)
    v = np.rint(safe[:, 1]).astype(np.int64)
    inside = finite & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    out = np.full(len(xy), np.nan)
    out[inside] = depth[v[inside], u[inside]]
    return out


def warp_pixels(
    xy0: np.ndarray,
    depth0: np.ndarray,
    K0: np.ndarray,
    K1: np.ndarray,
    T_1_0: np.ndarray,
    depth1: np.ndarray | None = None,
    *,
    image_size1: tuple[int, int] | None = None,
    depth_rel_tol: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """Where pixels of view 0 appear in view 1.

    Args:
        xy0: (N, 2) pixels of view 0. depth0: (N,) their z-depth (m).
        K0, K1: intrinsics. T_1_0: camera-0-to-camera-1 transform.
        depth1: optional (H1, W1) depth map of view 1 for the occlusion check.
        image_size1: (W1, H1) for the inside check (taken from depth1 when given).
        depth_rel_tol: a point is visible when its depth in view 1 agrees with depth1 within this
            relative tolerance (5 %: interpolation at depth edges is off by more, occluders by far more).
    Returns:
        xy1 (N, 2) warped pixels and visible (N,) bool (finite depth, in front, inside, not occluded).
    """
    with np.errstate(invalid="ignore", over="ignore"):  # no-surface pixels have infinite depth
        pts1 = transform_points(T_1_0, unproject(xy0, depth0, K0))
        xy1, z1 = project(pts1, K1)
    valid = np.isfinite(depth0) & (depth0 > 0) & (z1 > 0) & np.isfinite(xy1).all(axis=1)
    if depth1 is not None:
        image_size1 = (depth1.shape[1], depth1.shape[0])
    if image_size1 is not None:
        W1, H1 = image_size1
        valid &= (xy1[:, 0] > -0.5) & (xy1[:, 0] < W1 - 0.5) & (xy1[:, 1] > -0.5) & (xy1[:, 1] < H1 - 0.5)
    if depth1 is not None:
        d1 = sample_depth_nearest(depth1, xy1)
        with np.errstate(invalid="ignore"):
            valid &= np.abs(z1 - d1) <= depth_rel_tol * d1
    return xy1, valid


def essential_from_pose(T_1_0: np.ndarray) -> np.ndarray:
    """Essential matrix ``E = [t]x R`` with ``x1^T E x0 = 0`` for normalised coordinates."""
    return skew(T_1_0[:3, 3]) @ T_1_0[:3, :3]


def epipolar_distance(xy0: np.ndarray, xy1: np.ndarray, K0: np.ndarray, K1: np.ndarray, T_1_0: np.ndarray) -> np.ndarray:
    """Pixel distance of each xy1 (M, 2) to the epipolar line of each xy0 (N, 2) in view 1: (N, M)."""
    F = np.linalg.inv(K1).T @ essential_from_pose(T_1_0) @ np.linalg.inv(K0)
    h0 = np.concatenate([xy0, np.ones((len(xy0), 1))], axis=1)
    h1 = np.concatenate([xy1, np.ones((len(xy1), 1))], axis=1)
    lines = h0 @ F.T  # (N, 3) lines a x + b y + c = 0 in view 1
    num = np.abs(lines @ h1.T)
    return num / np.maximum(np.linalg.norm(lines[:, :2], axis=1, keepdims=True), 1e-12)


def symmetric_epipolar_distance(F: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """Symmetric epipolar distance in pixels of correspondences ``x0[i] <-> x1[i]`` under ``F``.

    With ``l1 = F x0`` (the epipolar line of ``x0`` in image 1) and ``l0 = F^T x1``, the distances of
    each point to the other's line are ``d1 = |x1^T F x0| / |l1[:2]|`` and ``d0 = |x1^T F x0| / |l0[:2]|``;
    the symmetric distance is ``sqrt(d0^2 + d1^2)`` (Hartley & Zisserman, eq. 11.10, the square root of
    the quantity SuperGlue thresholds).

    Args:
        F: (3, 3) with ``x1^T F x0 = 0`` in homogeneous pixels.
        x0, x1: (N, 2) pixels (x = column, y = row).
    Returns:
        (N,) float64 pixels (inf where a line is undefined, i.e. at an epipole).
    """
    x0 = np.asarray(x0, np.float64).reshape(-1, 2)
    x1 = np.asarray(x1, np.float64).reshape(-1, 2)
    h0 = np.hstack([x0, np.ones((len(x0), 1))])
    h1 = np.hstack([x1, np.ones((len(x1), 1))])
    l1 = h0 @ F.T   # F x0 per row
    l0 = h1 @ F     # F^T x1 per row
    algebraic = np.abs(np.sum(h1 * l1, axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        d1 = algebraic / np.hypot(l1[:, 0], l1[:, 1])
        d0 = algebraic / np.hypot(l0[:, 0], l0[:, 1])
    d = np.hypot(d0, d1)
    return np.where(np.isfinite(d), d, np.inf)
