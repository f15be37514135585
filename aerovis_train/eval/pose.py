"""Relative-pose evaluation of event keypoint detectors (the SuperEvent protocol).

Protocol (REFERENCE.md section 4, as implemented here):

1. Frames: an MCTS is computed at timestamps sampled at ``rate_hz`` along the ground truth (or at
   the GT timestamps themselves with ``rate_hz=None``, SuperEvent's choice), from one streaming
   pass of a :class:`~aerovis_slam.mcts.TimestampBuffer` through the events. The GT pose
   ``T_world_body`` is interpolated at those times (linear translation, quaternion slerp) and
   turned into the camera pose ``T_world_cam = T_world_body @ T_imu_cam``.
2. Pairs (:func:`select_pairs`): see there; within 2 s of each start frame, the first frame past
   each GT rotation of 1, 2, ..., 45 deg, then the next start is the frame after the one that passed
   45 deg.
3. Each frame: ``detector(mcts) -> Keypoints`` (at most ``top_k = max(H, W) // 2``, the highest
   scores). Each pair: mutual nearest neighbours (cosine for float/int8 descriptors, Hamming for
   binary uint8 ones), keypoints undistorted to ideal pinhole pixels, essential matrix with RANSAC
   (threshold in pixels: 1 px on 240x180-class sensors, 3 px on larger ones) and pose recovery.
   OpenCV's plain RANSAC (the protocol's, unrefined) is the default; ``estimator="usac_accurate"``
   refines the model (lower errors, not comparable with published numbers).
4. Errors (:func:`relative_pose_error`): rotation error = angle of ``R_est R_gt^T``; translation
   error = angle between the translation directions, folded to [0, 90] deg; failure = 180 deg.
5. AUC (:func:`pose_auc`) at 5/10/20 deg by the trapezoid rule over the recall curve, in percent,
   of the rotation error (SuperEvent's metric) and of max(rotation, translation) error (the
   common SuperGlue/LoFTR metric, ``auc*_max``).

Frames: ``T_a_b`` (4x4) maps points from frame ``b`` to frame ``a``; ``T_1_0`` maps points from
camera 0 (the earlier frame of a pair) to camera 1. Pixel convention as in
:mod:`aerovis_slam.keypoints` (x = column, y = row, integers at pixel centres).

This module needs only numpy and OpenCV; importing it never imports torch.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import cv2
import numpy as np
from tqdm.auto import tqdm

from aerovis_slam.calib import CameraCalibration
from aerovis_slam.geometry import invert_T as invert_transform
from aerovis_slam.geometry import pose7_to_matrix, rotation_angle_deg
from aerovis_slam.geometry import interpolate_poses as _interpolate_pose7
from aerovis_slam.errors import DataError
from aerovis_slam.io.sequence import Sequence, camera_key
from aerovis_slam.keypoints import Keypoints, keep_top_k, match_keypoints
from aerovis_slam.mcts import MCTS_DT_WINDOWS_MS, MCTS_NE_EVENTS_PER_PX, TimestampBuffer, warm_up_requirement

AUC_THRESHOLDS_DEG: tuple[float, ...] = (5.0, 10.0, 20.0)
FAILURE_DEG = 180.0
MIN_MATCHES = 5  # the five-point solver's minimum
# Robust estimators of the essential matrix. "ransac" is the protocol's (SuperEvent and SuperGlue
# call OpenCV's plain RANSAC): the pose comes from the best minimal 5-point sample, unrefined, so
# its error is several times the noise floor. "usac_accurate" adds local optimisation and a final
# least-squares polish on the inliers (closer to the noise floor; not comparable with published AUCs).
ESTIMATORS: dict[str, int] = {"ransac": cv2.RANSAC, "usac_accurate": cv2.USAC_ACCURATE, "magsac": cv2.USAC_MAGSAC}


@runtime_checkable
class Detector(Protocol):
    """A keypoint detector + descriptor on time surfaces.

    Attributes:
        name: reported as ``"model"`` in results.

    ``__call__(mcts)`` takes a float32 (C, H, W) MCTS (values in [0, 1], channel order of
    :mod:`aerovis_slam.mcts`) and returns :class:`~aerovis_slam.keypoints.Keypoints` in the pixel
    coordinates of the full (C, H, W) input; a detector that crops (e.g. to multiples of 8) maps
    its keypoints back. Descriptors: float (cosine matching), int8 (cosine) or uint8 bit strings
    (Hamming matching).
    """

    name: str

    def __call__(self, mcts: np.ndarray) -> Keypoints: ...


def interpolate_poses(t_gt_us: np.ndarray, pose7: np.ndarray, t_query_us: np.ndarray) -> np.ndarray:
    """GT poses ``T_world_body`` (M, 4, 4) at query times (linear translation, slerp rotation)."""
    return pose7_to_matrix(_interpolate_pose7(t_query_us, np.asarray(t_gt_us, np.int64), np.asarray(pose7, np.float64).reshape(-1, 7)))


# --------------------------------------------------------------------------------------------
# pair selection
# --------------------------------------------------------------------------------------------
def select_pairs(
    gt_times_us: np.ndarray,
    gt_rotations: np.ndarray,
    max_dt_s: float = 2.0,
    max_angle_deg: float = 45.0,
    *,
    step_deg: float = 1.0,
    superevent_code_compat: bool = False,
) -> np.ndarray:
    """Frame pairs of the SuperEvent relative-pose protocol.

    With ``a_j`` the angle of the rotation between the camera orientations of start frame ``i``
    and frame ``j > i`` (``angle(R_i^T R_j)``), and the window of ``i`` the frames with
    ``0 < t_j - t_i <= max_dt_s``:

    * if no frame of the window has ``a_j >= max_angle_deg``, start ``i`` yields no pair and the
      next frame ``i + 1`` is tried as a start (a slow segment is skipped, not paired);
    * otherwise, for each threshold ``a`` in ``step_deg, 2 step_deg, ..., max_angle_deg`` (1, 2, ...,
      45 deg) the first frame ``j_a`` of the window with ``a_j >= a`` is paired with ``i``. A frame that
      passes several thresholds at once (fast rotation, low frame rate) forms one pair, so a
      pair is never counted twice; the next start is ``j_45 + 1``, the frame after the one that
      passed ``max_angle_deg`` (the window is not reused).

    ``superevent_code_compat=True`` reproduces the public SuperEvent script instead, which moves
    to the next threshold only once per frame: after a frame passing several thresholds, the
    following frames are paired too until the thresholds catch up (more pairs at large angles
    under fast motion), and it closes the window at the first frame strictly past 45 deg.

    Args:
        gt_times_us: (N,) int64 frame times in µs, increasing.
        gt_rotations: (N, 3, 3) camera orientations ``R_world_cam`` at those frames (any fixed
            frame in place of world; the body orientation gives the same angles).
        max_dt_s: window length in seconds.
        max_angle_deg: largest threshold in degrees.
        step_deg: threshold spacing in degrees.
        superevent_code_compat: see above.
    Returns:
        (M, 2) int64 frame index pairs ``(i, j)``, ``i < j``, sorted by ``i`` then ``j``.

    Example:
        >>> t = np.arange(6) * 100_000  # 10 Hz
        >>> yaw = np.radians([0, 10, 30, 50, 55, 60])
        >>> R = np.stack([[[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]] for a in yaw])
        >>> select_pairs(t, R).tolist()  # 10 deg passes 1..10, 30 passes 11..30, 50 passes 31..45
        [[0, 1], [0, 2], [0, 3]]
    """
    t = np.asarray(gt_times_us, np.int64)
    R = np.asarray(gt_rotations, np.float64)
    if R.shape != (len(t), 3, 3):
        raise ValueError(f"gt_rotations must be ({len(t)}, 3, 3) to match gt_times_us, got {R.shape}")
    if len(t) > 1 and np.any(np.diff(t) <= 0):
        raise ValueError("gt_times_us must be strictly increasing")
    n_thr = int(np.floor(max_angle_deg / step_deg + 1e-9))
    if n_thr < 1:
        raise ValueError(f"max_angle_deg ({max_angle_deg}) must be at least step_deg ({step_deg})")
    thresholds = step_deg * np.arange(1, n_thr + 1)
    top = thresholds[-1]
    max_dt_us = int(round(max_dt_s * 1e6))
    pairs: list[tuple[int, int]] = []
    i = 0
    n = len(t)
    while i < n - 1:
        j_end = int(np.searchsorted(t, t[i] + max_dt_us, side="right"))
        js = np.arange(i + 1, j_end)
        if len(js) == 0:
            i += 1
            continue
        angles = rotation_angle_deg(np.swapaxes(R[i], -1, -2)[None] @ R[js])
        closing = angles > top if superevent_code_compat else angles >= top
        if not closing.any():
            i += 1
            continue
        last = int(np.argmax(closing))  # position in the window of the frame past the largest threshold
        if superevent_code_compat:
            k = 0
            for pos in range(last + 1):
                if k < n_thr and angles[pos] >= thresholds[k]:
                    pairs.append((i, int(js[pos])))
                    k += 1
        else:
            passed = angles[: last + 1, None] >= thresholds[None, :]  # (frames, thresholds)
            first = np.argmax(passed, axis=0)  # every threshold is passed by frame `last` at the latest
            pairs.extend((i, int(js[pos])) for pos in np.unique(first))
        i = int(js[last]) + 1
    return np.array(pairs, np.int64).reshape(-1, 2)


# --------------------------------------------------------------------------------------------
# matching and two-view geometry
# --------------------------------------------------------------------------------------------
@dataclass
class PoseError:
    """Outcome of one relative-pose estimate.

    Attributes:
        rot_err_deg: angle of ``R_est R_gt^T`` in degrees (180 on failure).
        t_err_deg: angle between estimated and GT translation directions, folded to [0, 90]
            (180 on failure; 0 when the GT translation is below the baseline threshold, where
            the direction is undefined).
        max_err_deg: ``max(rot_err_deg, t_err_deg)``.
        matches: number of putative matches.
        inliers: RANSAC inliers that also pass the cheirality check of pose recovery.
        inlier_ratio: ``inliers / matches`` (0 without matches).
        success: whether a pose was recovered.
        R_1_0, t_1_0: (3, 3) estimated rotation and (3,) unit translation direction (camera 0 ->
            camera 1), None on failure.
    """

    rot_err_deg: float
    t_err_deg: float
    max_err_deg: float
    matches: int
    inliers: int
    inlier_ratio: float
    success: bool
    R_1_0: np.ndarray | None = None
    t_1_0: np.ndarray | None = None

    def to_dict(self) -> dict:
        """JSON-ready scalars (the estimated pose is left out)."""
        d = asdict(self)
        d.pop("R_1_0"), d.pop("t_1_0")
        return d


def _normalise(xy: np.ndarray, K: np.ndarray) -> np.ndarray:
    K = np.asarray(K, np.float64)
    return np.stack([(xy[:, 0] - K[0, 2]) / K[0, 0], (xy[:, 1] - K[1, 2]) / K[1, 1]], axis=1)


def relative_pose_error(
    kpts0: np.ndarray | Keypoints,
    kpts1: np.ndarray | Keypoints,
    matches: np.ndarray,
    K0: np.ndarray,
    K1: np.ndarray,
    T_1_0_gt: np.ndarray,
    ransac_px: float,
    *,
    confidence: float = 0.99999,
    min_baseline_m: float = 0.0,
    estimator: str = "ransac",
    seed: int | None = 0,
) -> PoseError:
    """Estimate the relative pose of a matched pair and compare it with the ground truth.

    Matched keypoints are normalised with their own intrinsics (so ``K0 != K1`` is handled), the
    essential matrix is found by OpenCV's RANSAC with the pixel threshold converted to normalised
    units (``ransac_px / mean(fx0, fy0, fx1, fy1)``, as SuperGlue), and each returned candidate is
    decomposed by ``cv2.recoverPose`` (cheirality check on the RANSAC inliers, with no far-point
    cut-off); the candidate with the most inliers wins.

    The translation direction of an essential matrix is defined only up to sign (``E`` and
    ``-E`` are the same constraint, and cheirality can pick the wrong sign on near-degenerate
    pairs), so the translation error is folded: ``min(angle, 180 - angle)`` in [0, 90] deg, the
    SuperGlue/LoFTR convention (equal to the angle of ``|cos|``). Failure (fewer than 5 matches, no
    essential matrix, no inlier passing cheirality) gives 180 deg for both errors.

    Args:
        kpts0, kpts1: (N0, 2) and (N1, 2) pixel coordinates, or :class:`Keypoints`. They must be
            ideal pinhole pixels (undistort first when the camera has distortion).
        matches: (M, 2) int index pairs into ``kpts0`` and ``kpts1``.
        K0, K1: (3, 3) intrinsics of the two images.
        T_1_0_gt: (4, 4) GT transform mapping points from camera 0 to camera 1.
        ransac_px: RANSAC threshold in pixels (distance to the epipolar line).
        confidence: RANSAC confidence.
        min_baseline_m: GT translations shorter than this have no defined direction: their
            translation error is 0 (the rotation still counts).
        estimator: key of :data:`ESTIMATORS` (default ``"ransac"``, the protocol's).
        seed: seeds OpenCV's RNG before RANSAC so results are reproducible (None: leave it).
    Returns:
        :class:`PoseError`.
    """
    xy0 = np.asarray(kpts0.xy if isinstance(kpts0, Keypoints) else kpts0, np.float64).reshape(-1, 2)
    xy1 = np.asarray(kpts1.xy if isinstance(kpts1, Keypoints) else kpts1, np.float64).reshape(-1, 2)
    matches = np.asarray(matches, np.int64).reshape(-1, 2)
    T = np.asarray(T_1_0_gt, np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"T_1_0_gt must be (4, 4), got {T.shape}")
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator must be one of {sorted(ESTIMATORS)}, not {estimator!r}")
    m = len(matches)
    fail = PoseError(FAILURE_DEG, FAILURE_DEG, FAILURE_DEG, m, 0, 0.0, False)
    if m < MIN_MATCHES:
        return fail
    p0 = _normalise(xy0[matches[:, 0]], K0)
    p1 = _normalise(xy1[matches[:, 1]], K1)
    f_mean = np.mean([K0[0][0], K0[1][1], K1[0][0], K1[1][1]])
    thr = float(ransac_px) / float(f_mean)
    if seed is not None:
        cv2.setRNGSeed(int(seed))
    try:
        E, mask = cv2.findEssentialMat(p0, p1, np.eye(3), method=ESTIMATORS[estimator], prob=confidence, threshold=thr)
    except cv2.error:
        return fail
    if E is None or mask is None or E.ndim != 2 or E.shape[1] != 3 or E.shape[0] % 3 != 0:
        return fail
    best = (0, None, None)
    for k in range(E.shape[0] // 3):
        try:
            # distanceThresh 1e9 (as SuperGlue): the default 50 (in units of the baseline) discards
            # every point of a small-baseline pair as "at infinity", failing near-pure rotations
            n_in, R, t, _, _ = cv2.recoverPose(E[3 * k:3 * k + 3], p0, p1, np.eye(3), distanceThresh=1e9, mask=mask.copy())
        except cv2.error:
            continue
        if n_in > best[0]:
            best = (int(n_in), R, t.ravel())
    n_in, R, t = best
    if n_in == 0:
        return fail
    rot_err = float(rotation_angle_deg(R @ T[:3, :3].T))
    t_gt = T[:3, 3]
    norm_gt = np.linalg.norm(t_gt)
    if norm_gt <= min_baseline_m or norm_gt == 0.0:
        t_err = 0.0
    else:
        cos = float(np.clip(np.dot(t, t_gt) / (np.linalg.norm(t) * norm_gt), -1.0, 1.0))
        t_err = float(np.degrees(np.arccos(cos)))
        t_err = min(t_err, 180.0 - t_err)
    return PoseError(rot_err, t_err, max(rot_err, t_err), m, n_in, n_in / m, True, R, t)


# --------------------------------------------------------------------------------------------
# AUC and summaries
# --------------------------------------------------------------------------------------------
def pose_auc(errors_deg, thresholds: tuple[float, ...] = AUC_THRESHOLDS_DEG) -> list[float]:
    """Area under the recall curve of an error, up to each threshold, in percent.

    The recall curve is the fraction of pairs with error below ``e``, as a function of ``e``;
    sorted errors ``e_1 <= ... <= e_N`` with recalls ``1/N, ..., 1`` and the point ``(0, 0)`` are
    joined by straight lines (trapezoid rule), the curve is held flat from the last error below
    the threshold up to the threshold, and the area is divided by the threshold (SuperGlue's
    ``pose_auc``; the SuperEvent/LoFTR code computes the same). An error equal to the threshold
    does not count as below it.

    Args:
        errors_deg: (N,) errors in degrees (failures as 180).
        thresholds: thresholds in degrees.
    Returns:
        AUC in percent per threshold (NaN for an empty error list).

    Example:
        >>> [round(a, 2) for a in pose_auc([0, 5, 10, 180])]
        [25.0, 43.75, 62.5]
    """
    e = np.sort(np.asarray(errors_deg, np.float64).ravel())
    if len(e) == 0:
        return [float("nan")] * len(thresholds)
    if np.any(np.isnan(e)):
        raise ValueError("errors contain NaN (use 180 deg for failures)")
    recall = np.r_[0.0, np.arange(1, len(e) + 1) / len(e)]
    e = np.r_[0.0, e]
    aucs = []
    for thr in thresholds:
        last = int(np.searchsorted(e, thr, side="left"))  # e[:last] < thr; last >= 1 since e[0] = 0 < thr
        r = np.r_[recall[:last], recall[last - 1]]
        x = np.r_[e[:last], thr]
        area = float(np.sum((x[1:] - x[:-1]) * (r[1:] + r[:-1]) / 2.0))
        aucs.append(100.0 * area / thr)
    return aucs


def summarize(per_pair: list[dict], thresholds: tuple[float, ...] = AUC_THRESHOLDS_DEG) -> dict:
    """Summary of per-pair results (dicts with ``rot_err_deg``, ``max_err_deg``, ``matches``, ``inlier_ratio``).

    Returns:
        ``auc{T}`` (rotation) and ``auc{T}_max`` (max(rotation, translation)) in percent for each
        threshold ``T``, ``pairs``, mean ``matches`` and mean ``inlier_ratio`` per pair. Pairs scored
        with the simulator's truth (``oracle_noise_px``) add ``correct_matches_{r}px`` (mean per pair for
        each radius of :func:`match_truth`), ``correct_error_px`` (median over pairs of the median
        distance to the truth of their matches correct within the largest radius) and ``oracle``
        (:func:`summarize_oracle`).
    """
    rot = [p["rot_err_deg"] for p in per_pair]
    mx = [p["max_err_deg"] for p in per_pair]
    out: dict = {}
    for thr, a in zip(thresholds, pose_auc(rot, thresholds)):
        out[f"auc{thr:g}"] = a
    for thr, a in zip(thresholds, pose_auc(mx, thresholds)):
        out[f"auc{thr:g}_max"] = a
    out["pairs"] = len(per_pair)
    out["matches"] = float(np.mean([p["matches"] for p in per_pair])) if per_pair else float("nan")
    out["inlier_ratio"] = float(np.mean([p["inlier_ratio"] for p in per_pair])) if per_pair else float("nan")
    if per_pair and "truth" in per_pair[0]:
        for r in per_pair[0]["truth"]["correct"]:
            out[f"correct_matches_{r}px"] = float(np.mean([p["truth"]["correct"][r] for p in per_pair]))
        out["keypoints_in_view"] = float(np.mean([p["truth"]["keypoints_in_view"] for p in per_pair]))
        for r in per_pair[0]["truth"]["repeatable"]:
            out[f"repeatable_{r}px"] = float(np.mean([p["truth"]["repeatable"][r] for p in per_pair]))
        errors = [p["truth"]["error_px"] for p in per_pair if p["truth"]["error_px"] is not None]
        out["correct_error_px"] = float(np.median(errors)) if errors else None  # median over pairs of each pair's median
    if per_pair and "oracle" in per_pair[0]:
        out["oracle"] = summarize_oracle(per_pair, thresholds)
    return out


def summarize_oracle(per_pair: list[dict], thresholds: tuple[float, ...] = AUC_THRESHOLDS_DEG) -> list[dict]:
    """The perfect-matches rows of pairs evaluated with ``oracle_noise_px`` (see :func:`oracle_pair_errors`):
    one dict per noise level with ``noise_px``, ``auc{T}`` and ``auc{T}_max`` of all visible keypoints
    matched perfectly, ``auc{T}_at_inliers`` of as many as the method's own RANSAC inliers, and the
    mean ``matches`` (visible keypoints) per pair."""
    rows = []
    for k, first in enumerate(per_pair[0]["oracle"]):
        entries = [p["oracle"][k] for p in per_pair]
        row = {"noise_px": first["noise_px"]}
        for key, suffix in (("rot_err_deg", ""), ("max_err_deg", "_max"), ("rot_err_deg_at_inliers", "_at_inliers")):
            for thr, a in zip(thresholds, pose_auc([e[key] for e in entries], thresholds)):
                row[f"auc{thr:g}{suffix}"] = a
        row["matches"] = float(np.mean([e["matches"] for e in entries]))
        rows.append(row)
    return rows


def default_ransac_px(width: int, height: int) -> float:
    """RANSAC threshold of the protocol: 1 px up to DAVIS346 size (ECD's 240x180), 3 px above (EDS's 640x480)."""
    return 1.0 if max(width, height) <= 346 else 3.0


# --------------------------------------------------------------------------------------------
# the protocol's ceiling: perfect matches of a detector's keypoints
# --------------------------------------------------------------------------------------------
def true_projections(truth, sensor: str, camera: CameraCalibration, xy0: np.ndarray, t0_us: int, t1_us: int) -> np.ndarray:
    """Where one frame's keypoints truly appear in a later frame, from the simulator's scene.

    Each keypoint ``xy0`` of the frame at ``t0_us`` is back-projected with the rendered depth, and
    that scene point is projected into the camera at ``t1_us``.

    Args:
        truth: :class:`~aerovis_slam.slam.oracle.SceneTruth` of the sequence.
        sensor: the camera's name in the simulator's rig.
        camera: its calibration (pixels of ``xy0``: ideal pinhole, as the simulator renders).
        xy0: (N, 2) keypoints of the first frame (px).
        t0_us, t1_us: the frames' times on the camera clock (µs; the truth is read at
            ``t + camera.imu_clock_offset_us``, the GT's clock).
    Returns:
        (N, 2) pixels in the second frame; NaN rows where the keypoint hits no surface, or its point
        is behind the camera, outside the image or hidden by a nearer surface at ``t1_us``.
    """
    shift = camera.imu_clock_offset_us
    K, T_bc, size = camera.K, camera.T_imu_cam, (camera.width, camera.height)
    pts = truth.back_project(int(t0_us) + shift, sensor, K, T_bc, np.asarray(xy0, np.float64).reshape(-1, 2))
    return truth.project(int(t1_us) + shift, K, T_bc, size, pts, occluded_by=sensor)


#: distances (px) at which a method's own match counts as correct (:func:`match_truth`): 1 px, and 3 px,
#: SuperPoint's correctness distance (event keypoints trail the motion by about a pixel, "Evaluation" in the README)
CORRECT_RADII_PX: tuple[float, ...] = (1.0, 3.0)


def match_truth(xy1: np.ndarray, matches: np.ndarray, uv_true: np.ndarray, radii_px: tuple[float, ...] = CORRECT_RADII_PX) -> dict:
    """How a method's own matches compare with the truth: a match is correct within ``r`` when its
    second keypoint lies within ``r`` px of where its first keypoint's scene point truly appears.

    Args:
        xy1: (N1, 2) keypoints of the second frame.
        matches: (M, 2) the method's index pairs.
        uv_true: (N0, 2) :func:`true_projections` of the first frame's keypoints (NaN: not in view).
        radii_px: the distances (px).
    Returns:
        ``in_view`` (matches whose first keypoint is in view in the second frame), ``correct`` (count
        per radius, keyed by the radius as text, e.g. ``"3"``), ``error_px`` (median distance to
        the truth of the matches correct within the largest radius; None without any),
        ``keypoints_in_view`` (first-frame keypoints in view in the second frame) and ``repeatable``
        (per radius: those of them with a second-frame keypoint within ``r`` px of their true
        projection, the detector's repeatability count; what a perfect descriptor could match at most).
    """
    xy1 = np.asarray(xy1, np.float64).reshape(-1, 2)
    matches = np.asarray(matches, np.int64).reshape(-1, 2)
    d = np.linalg.norm(xy1[matches[:, 1]] - uv_true[matches[:, 0]], axis=1)
    in_view = np.isfinite(d)
    d = np.where(in_view, d, np.inf)
    within = d <= max(radii_px)
    seen = np.isfinite(uv_true).all(axis=1)
    nearest = np.full(len(uv_true), np.inf)
    if seen.any() and len(xy1):
        # a few hundred keypoints a frame: the full distance matrix is cheaper than building a tree
        nearest[seen] = np.linalg.norm(uv_true[seen][:, None] - xy1[None], axis=2).min(axis=1)
    return {"in_view": int(in_view.sum()), "correct": {f"{r:g}": int(np.sum(d <= r)) for r in radii_px},
            "error_px": float(np.median(d[within])) if within.any() else None,
            "keypoints_in_view": int(seen.sum()), "repeatable": {f"{r:g}": int(np.sum(nearest <= r)) for r in radii_px}}


def oracle_pair_errors(a: np.ndarray, b: np.ndarray, K: np.ndarray, T_1_0_gt: np.ndarray, ransac_px: float, noise_px,
                       own_inliers: int, *, estimator: str = "ransac", rng: np.random.Generator) -> list[dict]:
    """What the protocol scores for perfect matches at each noise level: ``a`` and their true
    projections ``b`` (:func:`true_projections`, the rows in view).

    Gaussian noise of ``noise_px`` per axis is added to both keypoints of every match, and the
    matches go through :func:`relative_pose_error` exactly as a method's do. So detector and
    descriptor are taken out: what remains is what the keypoints' positions, their number in view and
    the protocol's unrefined RANSAC allow. A second draw keeps only as many of those matches as the
    method's own RANSAC inliers (``own_inliers``): the ceiling for the number of correct matches the
    method found.

    Args:
        a, b: (M, 2) matched pixels of the two frames.
        K: (3, 3) intrinsics of both.
        T_1_0_gt: (4, 4) the pair's GT transform, as the method is scored against.
        ransac_px: as for the method.
        noise_px: noise levels (px, per axis).
        own_inliers: the method's inlier count on this pair.
        estimator: as for the method.
        rng: noise and subsampling draws.
    Returns:
        One dict per noise level: ``noise_px``, ``matches`` (M), ``rot_err_deg``, ``max_err_deg``,
        and ``rot_err_deg_at_inliers``, ``max_err_deg_at_inliers``.
    """
    a, b = np.asarray(a, np.float64).reshape(-1, 2), np.asarray(b, np.float64).reshape(-1, 2)
    every = np.repeat(np.arange(len(a))[:, None], 2, axis=1)
    out = []
    for sigma in noise_px:
        na = a + rng.normal(0.0, float(sigma), a.shape)
        nb = b + rng.normal(0.0, float(sigma), b.shape)
        e_all = relative_pose_error(na, nb, every, K, K, T_1_0_gt, ransac_px, estimator=estimator)
        few = every[rng.permutation(len(a))[: max(int(own_inliers), 0)]]
        e_few = relative_pose_error(na, nb, few, K, K, T_1_0_gt, ransac_px, estimator=estimator)
        out.append({"noise_px": float(sigma), "matches": int(len(a)), "rot_err_deg": e_all.rot_err_deg,
                    "max_err_deg": e_all.max_err_deg, "rot_err_deg_at_inliers": e_few.rot_err_deg,
                    "max_err_deg_at_inliers": e_few.max_err_deg})
    return out


# --------------------------------------------------------------------------------------------
# whole sequences
# --------------------------------------------------------------------------------------------
def _stream_surfaces(seq: Sequence, cam: str, taus: np.ndarray, buf: TimestampBuffer, compute: Callable[[int], np.ndarray],
                     chunk_events: int = 1 << 18):
    """Yield ``(k, mcts)`` for each ``taus[k]`` (increasing), ingesting every event exactly once.

    A frame is emitted as soon as the current chunk holds an event newer than its ``tau`` (then
    no event at or before ``tau`` can follow); the frames after the last event come at the end.
    """
    k, n = 0, len(taus)
    for chunk in seq.iter_events(cam, chunk_events=chunk_events, t_end_us=int(taus[-1]) + 1):
        pos = 0
        while k < n:
            cut = int(np.searchsorted(chunk.t, taus[k], side="right"))
            if cut >= len(chunk):
                break
            if cut > pos:
                buf.ingest(chunk[pos:cut])
                pos = cut
            yield k, compute(int(taus[k]))
            k += 1
        if pos < len(chunk):
            buf.ingest(chunk[pos:])
    while k < n:
        yield k, compute(int(taus[k]))
        k += 1


def mcts_warm_up_us(seq: Sequence, cam: str, mcts_kind: str, params) -> int:
    """First time (µs, camera clock) at which ``cam``'s MCTS is complete: the event that fills the
    longest MCTS_Ne window (the last event if there are fewer), or the first event plus the longest
    MCTS_dt window. ``cam`` must hold events."""
    events, span_us = warm_up_requirement(mcts_kind, params, *seq.sensor_size(cam))
    i = min(events, seq.num_events(cam)) - 1  # the event that completes it
    return max(int(seq.events_by_index(cam, i, i + 1).t[0]), seq.time_range(cam)[0] + int(round(span_us)))


@dataclass
class FramePlan:
    """Frames and pairs of one sequence (what :func:`evaluate_sequence` will detect and match).

    Attributes:
        times_us: (F,) int64 frame times (µs).
        T_world_cam: (F, 4, 4) interpolated camera poses at those times.
        pairs: (M, 2) int64 frame-index pairs from :func:`select_pairs` (cut to ``max_pairs``).
        camera: calibration of the evaluated camera.
        width, height: sensor (= MCTS) size in pixels.
        mcts_kind, mcts_params: the time surface.
    """

    times_us: np.ndarray
    T_world_cam: np.ndarray
    pairs: np.ndarray
    camera: CameraCalibration
    width: int
    height: int
    mcts_kind: str
    mcts_params: tuple

    @property
    def needed(self) -> np.ndarray:
        """Sorted indices of the frames that occur in a pair (the only ones detected)."""
        return np.unique(self.pairs.ravel())


def plan_frames(
    seq: Sequence,
    cam: str = "cam0",
    *,
    mcts_kind: str = "ne",
    mcts_params=None,
    rate_hz: float | None = 20.0,
    max_dt_s: float = 2.0,
    max_angle_deg: float = 45.0,
    max_gt_gap_s: float = 0.1,
    superevent_code_compat: bool = False,
    max_pairs: int | None = None,
    t_start_us: int | None = None,
) -> FramePlan:
    """Frame times, camera poses and pairs of an open sequence (arguments as :func:`evaluate_sequence`).

    Frames start once the MCTS is warmed up (the longest MCTS_Ne window holds ``max(N_k)``
    events, or the longest MCTS_dt window has elapsed since the first event) and the GT has
    begun, and end at the last event or GT sample, whichever comes first. ``t_start_us`` moves
    the first frame later (never earlier): methods on different time surfaces (whose warm-ups
    differ) then share one frame grid and so the same pairs (``aerovis-eval compare``).

    Raises:
        DataError: no GT, no calibration, unknown camera, sizes that disagree, no events, no overlap
            of GT and events, or no pair.
    """
    path = seq.path
    if mcts_kind not in ("ne", "dt"):
        raise ValueError(f"mcts_kind must be 'ne' or 'dt', not {mcts_kind!r}")
    cam = camera_key(cam)
    if cam not in seq.cameras:
        raise DataError(path, f"no camera {cam!r} under /events; cameras are {seq.cameras}")
    gt = seq.gt
    if gt is None or len(gt) < 2:
        raise DataError(path, "no ground truth (/gt/t and /gt/pose with at least 2 poses): the relative-pose evaluation needs GT poses")
    if not seq.has_calib:
        raise DataError(path, "no calibration (/calib attribute 'json'): the relative-pose evaluation needs the camera intrinsics and T_imu_cam")
    calib = seq.calib
    if cam not in calib.cameras:
        raise DataError(path, f"/calib has no camera {cam!r} (it has {sorted(calib.cameras)})")
    camcal = calib.cameras[cam]
    W, H = seq.sensor_size(cam)
    if (camcal.width, camcal.height) != (W, H):
        raise DataError(path, f"/calib {cam} is {camcal.width}x{camcal.height} but /events/{cam} is {W}x{H}")
    tr = seq.time_range(cam)
    if tr is None:
        raise DataError(path, f"/events/{cam} holds no events")
    params = tuple(float(v) for v in (mcts_params or (MCTS_NE_EVENTS_PER_PX if mcts_kind == "ne" else MCTS_DT_WINDOWS_MS)))
    warm_t = mcts_warm_up_us(seq, cam, mcts_kind, params)
    # frames are on the camera's clock; the GT (like the IMU) is at t_cam + timeshift_cam_imu
    shift = camcal.imu_clock_offset_us
    t_lo = max(int(gt.t[0]) - shift, warm_t, warm_t if t_start_us is None else int(t_start_us))
    t_hi = min(int(gt.t[-1]) - shift, tr[1])
    if t_hi <= t_lo:
        raise DataError(path, f"GT [{gt.t[0]}, {gt.t[-1]}] µs and the events of {cam} after MCTS warm-up [{warm_t}, {tr[1]}] µs do not overlap")
    if rate_hz is None:
        t_gt = gt.t.astype(np.int64) - shift
        times = t_gt[(t_gt >= t_lo) & (t_gt <= t_hi)]
    else:
        times = np.unique(np.round(np.arange(t_lo, t_hi + 1, 1e6 / float(rate_hz))).astype(np.int64))
    times_gt = times + shift
    i1 = np.clip(np.searchsorted(gt.t, times_gt, side="left"), 1, len(gt.t) - 1)
    on_sample = (gt.t[i1] == times_gt) | (gt.t[i1 - 1] == times_gt)
    keep = ((gt.t[i1] - gt.t[i1 - 1]) * 1e-6 <= max_gt_gap_s) | on_sample
    times, times_gt = times[keep], times_gt[keep]
    T_w_c = interpolate_poses(gt.t, gt.pose, times_gt) @ camcal.T_imu_cam
    pairs = select_pairs(times, T_w_c[:, :3, :3], max_dt_s, max_angle_deg, superevent_code_compat=superevent_code_compat)
    if max_pairs is not None:
        pairs = pairs[: int(max_pairs)]
    if len(pairs) == 0:
        raise DataError(path, f"no frame pairs: among {len(times)} frames at {rate_hz or 'GT'} Hz the camera never rotates "
                              f"{max_angle_deg:g} deg within {max_dt_s:g} s (see select_pairs)")
    return FramePlan(times, T_w_c, pairs, camcal, W, H, mcts_kind, params)


def evaluate_sequence(
    seq_path: str | Path,
    detector: Detector | str,
    *,
    cam: str = "cam0",
    mcts_kind: str | None = None,
    mcts_params=None,
    rate_hz: float | None = 20.0,
    ransac_px: float | None = None,
    top_k: int | None = None,
    max_pairs: int | None = None,
    max_dt_s: float = 2.0,
    max_angle_deg: float = 45.0,
    max_gt_gap_s: float = 0.1,
    superevent_code_compat: bool = False,
    estimator: str = "ransac",
    progress: bool = False,
    t_start_us: int | None = None,
    oracle_noise_px=(),
    oracle_seed: int = 0,
) -> dict:
    """Relative-pose evaluation of one detector on one canonical sequence.

    Args:
        seq_path: canonical ``.h5`` with events of ``cam``, ``/gt`` and ``/calib``.
        detector: a :class:`Detector`, or a classical baseline's name (``orb``, ``sift``,
            ``gftt_brief``), built with the ``top_k`` budget.
        cam: camera key.
        mcts_kind: ``"ne"`` (MCTS_Ne, 8 channels by default) or ``"dt"`` (MCTS_dt, 10 channels).
            None: the detector's own ``mcts_kind`` attribute when it has one (a learned model
            expects the surface it was trained on), else ``"ne"``.
        mcts_params: events per pixel (``ne``) or windows in ms (``dt``). None: the detector's
            ``mcts_params`` when it has them and its kind is used, else the defaults of
            :mod:`aerovis_slam.mcts`.
        rate_hz: frame rate along the GT; None: one frame per GT timestamp (SuperEvent's protocol).
        ransac_px: RANSAC threshold in px; default :func:`default_ransac_px` of the sensor size.
        top_k: keypoint budget per frame; default ``max(H, W) // 2``. A detector's output is cut
            to its ``top_k`` highest scores.
        max_pairs: evaluate only the first pairs (in time order).
        max_dt_s, max_angle_deg, superevent_code_compat: pair selection, see :func:`select_pairs`.
        max_gt_gap_s: frames whose bracketing GT samples lie further apart are dropped (motion
            capture dropouts; interpolating across them would invent poses).
        estimator: essential-matrix estimator, see :data:`ESTIMATORS`.
        progress: tqdm bar on stderr.
        t_start_us: no frame before this time (µs); see :func:`plan_frames`.
        oracle_noise_px: noise levels (px) at which each pair is scored again with perfect matches
            of the detector's keypoints (:func:`oracle_pair_errors`: the protocol's ceiling for
            these keypoints); needs a sequence written by ``aerovis-sim``. Empty: not done.
        oracle_seed: seed of the oracle's noise (each pair draws from ``(seed, i, j)``).
    Returns:
        A JSON-ready dict: ``model``, ``sequence``, ``cam``, ``resolution`` [W, H], ``mcts``,
        ``mcts_params``, ``rate_hz``, ``ransac_px``, ``top_k``, ``frames`` (frames detected),
        the summary of :func:`summarize` (``auc5, auc10, auc20`` rotation, ``auc5_max, ...``,
        ``pairs``, ``matches``, ``inlier_ratio``), ``latency_ms`` (mean detector time per frame,
        the first call excluded as warm-up when there are several), ``mcts_ms`` (mean MCTS
        time), and ``per_pair``: one dict per pair (frame indices, times, GT angle and
        translation, errors, matches, inliers; with ``oracle_noise_px`` ``truth`` and ``oracle``). With
        ``oracle_noise_px`` the summary has ``correct_matches_1px``, ``correct_matches_3px``, ``correct_error_px`` and ``oracle`` (:func:`summarize`).
    Raises:
        DataError: no GT, no calibration, unknown camera, sizes that disagree, no events, or no pair;
            with ``oracle_noise_px``, a negative level or a sequence not written by ``aerovis-sim``.
        ValueError: ``mcts_kind`` contradicts the detector's declared time surface.
    """
    path = Path(seq_path)
    noise_levels = [float(x) for x in oracle_noise_px]
    truth = None
    if noise_levels:
        # the simulator (and gtsam with the SLAM package) only when asked for
        from aerovis_slam.slam.oracle import SceneTruth, _check_noise

        for x in noise_levels:
            _check_noise(x)
        truth = SceneTruth(path)
        if camera_key(cam) not in truth.sim.rig.cameras:
            raise DataError(path, f"camera {camera_key(cam)!r} is not in the simulator's rig {sorted(truth.sim.rig.cameras)}")
    own_kind = getattr(detector, "mcts_kind", None)
    if mcts_kind is None:
        mcts_kind = own_kind or "ne"
    elif own_kind is not None and own_kind != mcts_kind:
        raise ValueError(f"detector {getattr(detector, 'name', detector)!r} expects MCTS kind {own_kind!r}, not {mcts_kind!r}")
    if mcts_params is None and own_kind == mcts_kind and getattr(detector, "mcts_params", None) is not None:
        mcts_params = tuple(detector.mcts_params)
    with Sequence(path) as seq:
        plan = plan_frames(seq, cam, mcts_kind=mcts_kind, mcts_params=mcts_params, rate_hz=rate_hz, max_dt_s=max_dt_s,
                           max_angle_deg=max_angle_deg, max_gt_gap_s=max_gt_gap_s,
                           superevent_code_compat=superevent_code_compat, max_pairs=max_pairs,
                           t_start_us=t_start_us)
        cam, camcal, W, H, params = camera_key(cam), plan.camera, plan.width, plan.height, plan.mcts_params
        times, T_w_c, pairs = plan.times_us, plan.T_world_cam, plan.pairs
        if mcts_kind == "ne":
            buf = TimestampBuffer(W, H, events_per_px=params)
        else:
            buf = TimestampBuffer(W, H, events_per_px=(1e-9,))  # fixed windows need no ring of past timestamps

        # -- detector ---------------------------------------------------------------------
        top_k = int(top_k) if top_k is not None else max(W, H) // 2
        if isinstance(detector, str):
            from aerovis_slam.classical import make_detector

            detector = make_detector(detector, top_k=top_k)
        name = getattr(detector, "name", type(detector).__name__)
        if ransac_px is None:
            ransac_px = default_ransac_px(W, H)
        K = camcal.K
        distorted = camcal.distortion_model != "none" and any(c != 0 for c in camcal.distortion_coeffs)

        # -- one streaming pass: MCTS and keypoints at the paired frames ---------------------
        needed = plan.needed
        if mcts_kind == "ne":
            compute = lambda tau: buf.mcts_ne(tau, params)  # noqa: E731
        else:
            compute = lambda tau: buf.mcts_dt(tau, params)  # noqa: E731
        mcts_s: list[float] = []

        def timed_compute(tau: int) -> np.ndarray:
            t0 = time.perf_counter()
            out = compute(tau)
            mcts_s.append(time.perf_counter() - t0)
            return out

        kps: dict[int, tuple[Keypoints, np.ndarray]] = {}
        det_s: list[float] = []
        bar = tqdm(total=len(needed), desc=f"{name} {path.name}", unit="frame", file=sys.stderr, disable=not progress, leave=False)
        for k, mcts in _stream_surfaces(seq, cam, times[needed], buf, timed_compute):
            t0 = time.perf_counter()
            kp = detector(mcts)
            det_s.append(time.perf_counter() - t0)
            kp = keep_top_k(kp, top_k)
            xy = camcal.undistort_points(kp.xy) if (distorted and len(kp)) else np.asarray(kp.xy, np.float64)
            kps[int(needed[k])] = (kp, xy)
            bar.update(1)
        bar.close()

    # -- pairs ----------------------------------------------------------------------------
    per_pair = []
    # RANSAC dominates when matches are mostly wrong (up to ~0.3 s a pair): a bar of its own
    for i, j in tqdm(pairs, desc=f"{name} {path.name} pairs", unit="pair", file=sys.stderr, disable=not progress, leave=False):
        (kp0, xy0), (kp1, xy1) = kps[int(i)], kps[int(j)]
        T_1_0 = invert_transform(T_w_c[j]) @ T_w_c[i]
        m = match_keypoints(kp0, kp1)
        err = relative_pose_error(xy0, xy1, m, K, K, T_1_0, ransac_px, estimator=estimator)
        per_pair.append({"i": int(i), "j": int(j), "t0_us": int(times[i]), "t1_us": int(times[j]),
                         "gt_angle_deg": float(rotation_angle_deg(T_1_0[:3, :3])),
                         "gt_translation_m": float(np.linalg.norm(T_1_0[:3, 3])),
                         "keypoints0": len(kp0), "keypoints1": len(kp1), **err.to_dict()})
        if truth is not None:
            uv_true = true_projections(truth, cam, camcal, xy0, int(times[i]), int(times[j]))
            per_pair[-1]["truth"] = match_truth(xy1, m, uv_true)
            seen = np.isfinite(uv_true).all(axis=1)
            a, b = xy0[seen], uv_true[seen]
            per_pair[-1]["oracle"] = oracle_pair_errors(a, b, K, T_1_0, ransac_px, noise_levels, err.inliers, estimator=estimator,
                                                        rng=np.random.default_rng([int(oracle_seed), int(i), int(j)]))
    timed = det_s[1:] if len(det_s) > 1 else det_s
    result = {"model": name, "sequence": str(path), "cam": cam, "resolution": [W, H], "mcts": mcts_kind,
              "mcts_params": list(params), "rate_hz": rate_hz, "ransac_px": float(ransac_px), "estimator": estimator, "top_k": top_k,
              "frames": len(needed), **summarize(per_pair),
              "latency_ms": 1000.0 * float(np.mean(timed)), "mcts_ms": 1000.0 * float(np.mean(mcts_s)),
              "per_pair": per_pair}
    return result
