"""Trajectories: TUM files, association and error metrics (ATE, RPE) with ``evo`` as the library.

A trajectory is a :class:`~aerovis_slam.measurements.PoseSamples`: ``t`` int64 µs and ``pose``
(N, 7) ``tx ty tz qx qy qz qw`` of ``T_world_body`` in metres.

TUM format (one pose per line, ``#`` starts a comment)::

    t tx ty tz qx qy qz qw        # t in seconds

Errors:

* ATE (absolute trajectory error): associate estimate and reference poses by time, align the
  estimate to the reference (SE(3) for stereo/inertial systems, whose scale is observable; Sim(3)
  for monocular ones), then the RMSE of the translation differences (evo's APE on the translation
  part, Umeyama alignment). ``ate_pct`` divides it by the reference's path length over the
  evaluated time span.
* RPE (relative pose error): the error of the motion over a fixed time ``delta_s`` (evo's RPE on
  pose pairs ``delta_s`` apart), translation in metres and rotation in degrees.

Example:
    >>> import numpy as np
    >>> t = np.arange(0, 2_000_000, 10_000)                   # 2 s at 100 Hz on a unit circle
    >>> a = np.pi * t / 1e6
    >>> pose = np.zeros((len(t), 7)); pose[:, 0], pose[:, 1], pose[:, 6] = np.cos(a), np.sin(a), 1.0
    >>> ref = PoseSamples(t, pose)
    >>> est = PoseSamples(t, pose + [0.0, 0.0, 0.05, 0, 0, 0, 0])  # 5 cm offset: removed by alignment
    >>> r = ate(ref, est, align="se3")
    >>> r["pairs"], r["ate_rmse_m"] < 1e-9, round(r["path_length_m"], 2)
    (200, True, 6.25)
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..fileio import atomic_write_text
from ..geometry import interpolate_poses, invert_T, pose7_to_matrix, pose_difference
from ..measurements import PoseSamples

ALIGNMENTS = ("se3", "sim3", "none")
PARTIAL_MARKER = "partial trajectory"  # written in the header of a trajectory that stopped early
DEFAULT_MAX_DIFF_S = 0.02  # association tolerance (REFERENCE.md: ~10-20 ms is customary)

# evo logs every metric at INFO level through the root logger configuration of its CLI; as a library
# it should stay quiet unless the caller asks for its logs.
logging.getLogger("evo").setLevel(logging.WARNING)


# -- TUM files ---------------------------------------------------------------------------------
def _parse_time_us(token: str) -> int:
    """Seconds as text -> int µs, exactly for plain decimals (float64 loses µs at epoch-scale times)."""
    if "e" in token.lower() or token.lower() in ("nan", "inf", "-inf", "+inf"):
        value = float(token)
        if not math.isfinite(value):
            raise ValueError(f"time {token!r} is not finite")
        return int(round(value * 1e6))
    sign = -1 if token.startswith("-") else 1
    whole, _, frac = token.lstrip("+-").partition(".")
    if not (whole or frac) or not (whole.isdigit() or whole == "") or not (frac.isdigit() or frac == ""):
        raise ValueError(f"time {token!r} is not a number")
    frac = (frac + "0000000")[:7]  # µs plus one digit to round on
    us = int(whole or "0") * 1_000_000 + int(frac[:6]) + (1 if int(frac[6]) >= 5 else 0)
    return sign * us


def read_tum(path: str | os.PathLike) -> PoseSamples:
    """Read a TUM trajectory file.

    Blank lines and lines starting with ``#`` are skipped. Quaternions are normalised (files written
    with few decimals are off by ~1e-4); one further than 1 % from unit length is an error.

    Returns:
        PoseSamples with ``t`` int64 µs and ``pose`` (N, 7).

    Raises:
        DataError: missing or unreadable file, a line without 8 numbers, a non-finite value, a
            quaternion far from unit length, times not strictly increasing, no pose at all. The
            message names the file and the line.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise DataError(path, "no such file (expected a TUM trajectory: 't tx ty tz qx qy qz qw' per line)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(path, f"cannot read as a text TUM trajectory ({exc})") from None
    times: list[int] = []
    poses: list[list[float]] = []
    lines: list[int] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        tokens = s.replace(",", " ").split()
        if len(tokens) != 8:
            raise DataError(path, f"line {lineno}: expected 8 values 't tx ty tz qx qy qz qw', found {len(tokens)}: {s[:80]!r}")
        try:
            t = _parse_time_us(tokens[0])
            values = [float(v) for v in tokens[1:]]
        except ValueError:
            raise DataError(path, f"line {lineno}: values must be numbers ('t tx ty tz qx qy qz qw'), got {s[:80]!r}") from None
        if not all(math.isfinite(v) for v in values):
            raise DataError(path, f"line {lineno}: non-finite value in {s[:80]!r}")
        norm = math.sqrt(sum(v * v for v in values[3:]))
        if abs(norm - 1.0) > 0.01:
            raise DataError(path, f"line {lineno}: quaternion (qx qy qz qw) has norm {norm:.4f}, expected 1")
        if times and t <= times[-1]:
            raise DataError(path, f"line {lineno}: time {tokens[0]} s does not increase (line {lines[-1]} has {times[-1] / 1e6:.6f} s)")
        times.append(t)
        poses.append(values[:3] + [v / norm for v in values[3:]])
        lines.append(lineno)
    if not times:
        raise DataError(path, "no poses (expected lines 't tx ty tz qx qy qz qw')")
    return PoseSamples(np.array(times, np.int64), np.array(poses, np.float64))


def read_tum_comments(path: str | os.PathLike) -> list[str]:
    """The comment lines (without the leading ``#``) of a TUM file, e.g. to see a partial flag."""
    out = []
    with open(path) as f:
        for line in f:
            if line.lstrip().startswith("#"):
                out.append(line.lstrip()[1:].strip())
    return out


def is_partial(path: str | os.PathLike) -> bool:
    """True when the TUM file's header says it holds a partial trajectory (see :func:`write_tum`)."""
    return any(PARTIAL_MARKER in c for c in read_tum_comments(path))

def format_tum(t_us: np.ndarray, pose7: np.ndarray, comments: list[str] | None = None) -> str:
    """TUM text: ``t`` (N,) int64 µs, ``pose7`` (N, 7); times with exact µs, positions to 0.1 µm."""
    t_us = np.asarray(t_us, np.int64)
    pose7 = np.asarray(pose7, np.float64)
    if pose7.ndim != 2 or pose7.shape[1] != 7 or len(pose7) != len(t_us):
        raise ValueError(f"expected t (N,) and pose7 (N, 7), got {t_us.shape} and {pose7.shape}")
    out = [f"# {c}\n" for c in (comments or [])]
    for t, p in zip(t_us.tolist(), pose7.tolist()):
        sign = "-" if t < 0 else ""
        s, us = divmod(abs(t), 1_000_000)
        out.append(f"{sign}{s}.{us:06d} {p[0]:.7f} {p[1]:.7f} {p[2]:.7f} {p[3]:.9f} {p[4]:.9f} {p[5]:.9f} {p[6]:.9f}\n")
    return "".join(out)


def write_tum(path: str | os.PathLike, t_us: np.ndarray, pose7: np.ndarray, *, comments: list[str] | None = None,
              partial: bool = False) -> Path:
    """Write a TUM file atomically (nothing half-written ever appears under ``path``).

    Args:
        t_us: (N,) int64 µs. pose7: (N, 7) ``T_world_body``.
        comments: header lines (written as ``# ...``).
        partial: flag the trajectory as partial in the header (:func:`is_partial` reads it back).
    """
    comments = list(comments or [])
    if partial:
        comments.insert(0, f"{PARTIAL_MARKER}: the run stopped before the end of the sequence")
    return atomic_write_text(path, format_tum(t_us, pose7, comments))


# -- association -------------------------------------------------------------------------------
def _evo(traj: PoseSamples, t_us: np.ndarray | None = None):
    from evo.core.trajectory import PoseTrajectory3D

    t = traj.t if t_us is None else t_us
    p = traj.pose
    return PoseTrajectory3D(positions_xyz=p[:, :3].copy(), orientations_quat_wxyz=p[:, [6, 3, 4, 5]].copy(),
                            timestamps=np.asarray(t, np.float64) / 1e6)


def interpolate_trajectory(traj: PoseSamples, t_query_us: np.ndarray, max_gap_s: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Poses of ``traj`` at ``t_query_us`` (N,) where two samples bracket the query within ``max_gap_s``.

    Returns:
        pose7 (M, 7) at the valid queries and the bool mask (N,) of valid queries. Linear
        translation and slerp (:func:`aerovis_slam.geometry.interpolate_poses`); no extrapolation and
        no bridging of gaps longer than ``max_gap_s`` (a lost-tracking hole must not be filled in).
    """
    tq = np.asarray(t_query_us, np.int64)
    inside = (tq >= traj.t[0]) & (tq <= traj.t[-1])
    i1 = np.clip(np.searchsorted(traj.t, tq, side="left"), 0, len(traj.t) - 1)
    i0 = np.clip(i1 - 1, 0, None)
    exact = traj.t[i1] == tq
    gap = traj.t[i1] - traj.t[i0]
    valid = inside & (exact | (gap <= max_gap_s * 1e6))
    return interpolate_poses(tq[valid], traj.t, traj.pose), valid


def associate(ref: PoseSamples, est: PoseSamples, *, max_diff_s: float = DEFAULT_MAX_DIFF_S,
              interpolate: bool = False, max_gap_s: float = 0.1) -> tuple[PoseSamples, PoseSamples]:
    """Pairs of reference and estimated poses at (nearly) the same time.

    Args:
        max_diff_s: nearest-timestamp association tolerance (evo ``associate_trajectories``).
        interpolate: instead, interpolate the reference at every estimate time (exact pairs; the
            right choice for a dense ground truth: nearest-neighbour pairing at 200 Hz GT already
            costs up to speed x 2.5 ms of error, as large as a good estimate's ATE).
        max_gap_s: with ``interpolate``, do not interpolate across reference gaps longer than this.

    Returns:
        (ref, est) with equal length, paired row by row, on the estimate's times.

    Raises:
        DataError: no pair within the tolerance.
    """
    if interpolate:
        pose, valid = interpolate_trajectory(ref, est.t, max_gap_s)
        if not valid.any():
            raise DataError(None, f"no estimate time lies within the reference's time span [{ref.t[0] / 1e6:.3f}, {ref.t[-1] / 1e6:.3f}] s")
        return PoseSamples(est.t[valid], pose), PoseSamples(est.t[valid], est.pose[valid])
    from evo.core import sync
    from evo.core.sync import SyncException

    try:
        r, e = sync.associate_trajectories(_evo(ref), _evo(est), max_diff=max_diff_s)
    except SyncException as exc:
        raise DataError(None, f"no pose pairs within {max_diff_s} s ({exc})") from None
    t = np.rint(e.timestamps * 1e6).astype(np.int64)
    return PoseSamples(t, _pose7(r)), PoseSamples(t, _pose7(e))


def _pose7(traj) -> np.ndarray:
    return np.concatenate([traj.positions_xyz, traj.orientations_quat_wxyz[:, [1, 2, 3, 0]]], axis=1)


def path_length(traj: PoseSamples, t_start_us: int | None = None, t_end_us: int | None = None) -> float:
    """Length in metres of the polyline through the positions with ``t_start_us <= t <= t_end_us``."""
    m = np.ones(len(traj.t), bool)
    if t_start_us is not None:
        m &= traj.t >= t_start_us
    if t_end_us is not None:
        m &= traj.t <= t_end_us
    p = traj.pose[m, :3]
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0


# -- ATE -----------------------------------------------------------------------------------------
def ate(ref: PoseSamples, est: PoseSamples, *, align: str = "se3", max_diff_s: float = DEFAULT_MAX_DIFF_S,
        interpolate: bool = False, max_gap_s: float = 0.1) -> dict:
    """Absolute trajectory error of ``est`` against ``ref`` (evo APE, translation part).

    Args:
        align: ``se3`` (rotation + translation), ``sim3`` (+ scale) or ``none``.
        max_diff_s, interpolate, max_gap_s: association, see :func:`associate`.

    Returns:
        JSON-ready dict: ``ate_rmse_m``, ``ate_mean_m``, ``ate_median_m``, ``ate_max_m``, ``pairs``,
        ``align``, ``scale`` (Sim(3) scale applied to the estimate, 1 otherwise), ``path_length_m``
        (reference path over the paired time span, all reference samples), ``ate_pct`` (RMSE as %
        of that length; None for a zero-length path), ``duration_s`` of the paired span, and arrays
        ``t_us`` (M,), ``error_m`` (M,), ``est_aligned`` (M, 7), ``ref_pose`` (M, 7) for plots (not
        JSON: pop them before dumping).
    """
    from evo.core.metrics import PoseRelation
    from evo.main_ape import ape

    if align not in ALIGNMENTS:
        raise ValueError(f"align must be one of {ALIGNMENTS}, not {align!r}")
    r, e = associate(ref, est, max_diff_s=max_diff_s, interpolate=interpolate, max_gap_s=max_gap_s)
    n = len(r.t)
    need = {"se3": 3, "sim3": 3, "none": 1}[align]  # Umeyama needs >= 3 points for a unique rotation
    if n < need:
        raise DataError(None, f"{n} pose pair(s): {align} alignment needs at least {need}")
    ev_ref, ev_aligned = _evo(r), _evo(e)
    scale = 1.0
    if align != "none":
        scale = _align(ev_aligned, ev_ref, align == "sim3")
    res = ape(ev_ref, ev_aligned, PoseRelation.translation_part, align=False)
    err = np.asarray(res.np_arrays["error_array"], np.float64)
    aligned = _pose7(ev_aligned)
    length = path_length(ref, int(r.t[0]), int(r.t[-1]))
    rmse = float(np.sqrt(np.mean(err**2)))
    return {
        "ate_rmse_m": rmse,
        "ate_mean_m": float(err.mean()),
        "ate_median_m": float(np.median(err)),
        "ate_max_m": float(err.max()),
        "pairs": int(n),
        "align": align,
        "scale": scale,
        "path_length_m": length,
        "ate_pct": 100.0 * rmse / length if length > 0 else None,
        "duration_s": float(r.t[-1] - r.t[0]) / 1e6,
        "t_us": r.t,
        "error_m": err,
        "est_aligned": aligned,
        "ref_pose": r.pose,
    }


def _align(est, ref, with_scale: bool, n: int = -1) -> float:
    """Umeyama-align evo trajectory ``est`` onto ``ref`` in place; returns the scale applied.

    ``n``: the alignment is found from the first ``n`` pose pairs only (-1: all), and applied to
    every pose (evo's ``align(n=...)``).

    evo's Umeyama alignment refuses exactly collinear (or coincident) positions: rotation about the
    line is then undetermined by positions alone (a slider run, a static camera). There the
    orientations decide: each pose also contributes three virtual points one spread-length along
    its body axes (the estimate's scaled by the positions' spread ratio, so that they pull the
    Sim(3) scale toward the positions' own), and Umeyama runs on those (still evo's).
    """
    from evo.core import lie_algebra as lie
    from evo.core.geometry import GeometryException, umeyama_alignment

    try:
        _, _, s = est.align(ref, correct_scale=with_scale, n=n)
        return float(s) if with_scale else 1.0
    except GeometryException:
        pass
    k = est.num_poses if n < 0 else n
    pe, pr = est.positions_xyz[:k], ref.positions_xyz[:k]
    spread_e = float(np.sqrt(np.mean(np.sum((pe - pe.mean(0)) ** 2, axis=1))))
    spread_r = float(np.sqrt(np.mean(np.sum((pr - pr.mean(0)) ** 2, axis=1))))
    d = max(spread_r, 1.0)
    ratio = spread_r / spread_e if (with_scale and spread_e > 1e-12 and spread_r > 1e-12) else 1.0
    Re = np.stack([T[:3, :3] for T in est.poses_se3[:k]])
    Rr = np.stack([T[:3, :3] for T in ref.poses_se3[:k]])
    x = np.concatenate([pe] + [pe + Re[:, :, i] * (d / ratio) for i in range(3)])
    y = np.concatenate([pr] + [pr + Rr[:, :, i] * d for i in range(3)])
    r_a, t_a, s = umeyama_alignment(x.T, y.T, with_scale)
    if with_scale:
        est.scale(s)
    est.transform(lie.se3(r_a, t_a))
    return float(s) if with_scale else 1.0


ATE_ARRAYS = ("t_us", "error_m", "est_aligned", "ref_pose")

#: seconds of a run's start that :func:`end_error` aligns on (the stretch before drift accumulates)
END_ERROR_ALIGN_S = 1.5


def end_error(ref: PoseSamples, est: PoseSamples, *, align_s: float = END_ERROR_ALIGN_S, max_gap_s: float = 0.1) -> dict:
    """Drift at the end of a run: the position error (m) of ``est``'s last pose after an SE(3)
    alignment of its first ``align_s`` seconds onto ``ref`` (the reference interpolated at the
    estimate's times).

    On a sequence that returns to its start this is the drift loop closure exists to remove; run
    with and without loop closure, it compares the corrected end with the open-loop drift. Unlike
    the ATE's alignment over the whole run, which spreads the drift over both ends, aligning the
    start shows all of it at the end.

    Returns:
        ``{"end_error_m", "end_error_align_s", "end_error_t_s"}``: the error, the aligned span and
        the time of the last pose after the first (s).

    Raises:
        DataError: fewer than 3 pose pairs within the first ``align_s`` seconds.
    """
    r, e = associate(ref, est, interpolate=True, max_gap_s=max_gap_s)
    k = int(np.searchsorted(r.t, r.t[0] + align_s * 1e6, side="right"))
    if k < 3:
        raise DataError(None, f"{k} pose pair(s) in the first {align_s} s: the end error's SE(3) alignment needs at least 3")
    ev_ref, ev_est = _evo(r), _evo(e)
    _align(ev_est, ev_ref, False, n=k)
    err = float(np.linalg.norm(ev_est.positions_xyz[-1] - ev_ref.positions_xyz[-1]))
    return {"end_error_m": err, "end_error_align_s": float(align_s), "end_error_t_s": float(r.t[-1] - r.t[0]) / 1e6}


def json_ready(result: dict) -> dict:
    """A metric dict without its array entries (:data:`ATE_ARRAYS`)."""
    return {k: v for k, v in result.items() if k not in ATE_ARRAYS}


# -- RPE -----------------------------------------------------------------------------------------
def rpe(ref: PoseSamples, est: PoseSamples, *, delta_s: float = 1.0, step_s: float = 0.05, max_gap_s: float = 0.1) -> dict:
    """Relative pose error over ``delta_s`` (evo RPE, all pairs ``delta_s`` apart).

    Both trajectories are resampled on a common grid of ``step_s`` inside their overlap (evo's RPE
    counts its ``delta`` in poses or metres, not seconds; a time grid makes the interval the same
    for a fixed-rate and an asynchronous estimate), without bridging gaps over ``max_gap_s``.

    Returns:
        ``rpe_trans_rmse_m``, ``rpe_rot_rmse_deg``, ``rpe_pairs`` and ``rpe_delta_s``; the errors are
        None when the overlap is shorter than ``delta_s``.
    """
    from evo.core.metrics import PoseRelation, Unit
    from evo.main_rpe import rpe as evo_rpe

    k = max(1, int(round(delta_s / step_s)))
    t0, t1 = max(ref.t[0], est.t[0]), min(ref.t[-1], est.t[-1])
    grid = np.arange(t0, t1 + 1, int(round(step_s * 1e6)), dtype=np.int64)
    out = {"rpe_delta_s": float(k * step_s), "rpe_trans_rmse_m": None, "rpe_rot_rmse_deg": None, "rpe_pairs": 0}
    if len(grid) <= k:
        return out
    pr, vr = interpolate_trajectory(ref, grid, max_gap_s)
    pe, ve = interpolate_trajectory(est, grid, max_gap_s)
    keep = vr & ve
    pr, pe, tk = pr[keep[vr]], pe[keep[ve]], grid[keep]
    # Pairs must be exactly delta apart in time: evaluate each run of consecutive grid points alone.
    trans, rot = [], []
    for run in _runs(tk, int(round(step_s * 1e6))):
        if len(run) <= k:
            continue
        for rel, sink in ((PoseRelation.translation_part, trans), (PoseRelation.rotation_angle_deg, rot)):
            # fresh trajectories for each call: evo's RPE leaves its inputs changed (seen in evo 1.38)
            a, b = _evo(PoseSamples(tk[run], pr[run])), _evo(PoseSamples(tk[run], pe[run]))
            res = evo_rpe(a, b, rel, delta=k, delta_unit=Unit.frames, all_pairs=True)
            sink.append(np.asarray(res.np_arrays["error_array"], np.float64))
    if trans:
        t_err, r_err = np.concatenate(trans), np.concatenate(rot)
        out.update(rpe_trans_rmse_m=float(np.sqrt(np.mean(t_err**2))), rpe_rot_rmse_deg=float(np.sqrt(np.mean(r_err**2))),
                   rpe_pairs=int(len(t_err)))
    return out


def loop_errors(ref: PoseSamples, t_match_us: int, t_query_us: int, T_loop: np.ndarray, T_odometry: np.ndarray) -> dict | None:
    """How good a loop closure was, by the ground truth: the error of the loop's measured relative
    pose and that of the odometry's estimate it corrected.

    Args:
        ref: ground-truth ``T_world_body`` samples. t_match_us, t_query_us: the two keyframes' times.
        T_loop, T_odometry: (4, 4) the query body pose in the match body frame, measured by the loop
            and as the odometry had it.
    Returns:
        ``{"error_m", "error_deg", "true_drift_m", "true_drift_deg"}`` (the loop's error; the
        odometry's, i.e. the drift the loop should have removed), or None outside the GT's time span.
    """
    t = np.array([t_match_us, t_query_us], np.int64)
    if t.min() < ref.t[0] or t.max() > ref.t[-1]:
        return None
    T_w_m, T_w_q = pose7_to_matrix(interpolate_poses(t, ref.t, ref.pose))
    T_gt = invert_T(T_w_m) @ T_w_q
    out = {}
    for name, T in (("error", T_loop), ("true_drift", T_odometry)):
        metres, degrees = pose_difference(T_gt, T)
        out[f"{name}_m"], out[f"{name}_deg"] = round(metres, 4), round(degrees, 3)
    return out


def final_trajectory(T_live: np.ndarray, anchor_kf: np.ndarray, T_kf_body: np.ndarray, T_corr_live: np.ndarray,
                     kf_poses: dict[int, np.ndarray], kf_corrections: dict[int, np.ndarray] | None = None) -> np.ndarray:
    """The final trajectory: every output re-anchored to its keyframe's last estimate.

    A live output is the frame's tracked pose against the newest keyframe as the smoother saw that
    keyframe then; later smoother updates (until the keyframe leaves the window) and later loop
    closures move the keyframe, and the frame should move with it. OKVIS2 writes such a "final"
    trajectory beside the real-time one; the live outputs stay the measure of what a robot gets.

    Args:
        T_live: (N, 4, 4) live ``T_world_body`` outputs (loop correction of their time applied).
        anchor_kf: (N,) keyframe id each output was tracked against; -1: none, the output is kept
            as it is (the pipeline anchors the vision-only outputs before the initialisation to
            their keyframes in the initialisation's window, or to its oldest keyframe).
        T_kf_body: (N, 4, 4) each output's pose in its keyframe's body frame, at output time.
        T_corr_live: (N, 4, 4) the loop correction (world <- odometry world) applied at output time.
        kf_poses: keyframe id -> its last smoother estimate ``T_world_body`` (odometry world).
        kf_corrections: keyframe id -> its correction from the final pose graph (world <- odometry
            world, exact at that keyframe); keyframes without one keep the live correction.

    Returns:
        (N, 4, 4) final ``T_world_body``; outputs whose keyframe is unknown are the live ones.
    """
    T_live = np.asarray(T_live, np.float64)
    out = T_live.copy()
    kf_corrections = kf_corrections or {}
    for i, k in enumerate(np.asarray(anchor_kf, np.int64)):
        k = int(k)
        if k < 0 or k not in kf_poses:
            continue
        C = kf_corrections.get(k, T_corr_live[i])
        out[i] = C @ kf_poses[k] @ T_kf_body[i]
    return out


def _runs(t: np.ndarray, step: int) -> list[np.ndarray]:
    """Index runs of consecutive grid times (a missing grid point splits a run)."""
    if len(t) == 0:
        return []
    breaks = np.flatnonzero(np.diff(t) != step) + 1
    return np.split(np.arange(len(t)), breaks)
