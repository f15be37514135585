"""Reports of a SLAM run: ``metrics.json`` (accuracy, speed, latency, robustness) and ``traj.png``.

:func:`compute_metrics` turns a :class:`~aerovis_slam.slam.pipeline.SlamResult` (or anything with its
fields) and the sequence's ground truth into one JSON-ready dict:

* accuracy: ``ate_rmse_m`` after SE(3) alignment (the ground truth interpolated at every estimate
  time, see :func:`aerovis_slam.slam.trajectory.associate`), ``ate_pct`` of the ground-truth path
  length, mean/median/max, ``ate_sim3_rmse_m`` and ``sim3_scale`` (scale drift shows as a scale
  far from 1), and the RPE over 1 s (a quarter of the run when it is shorter than 2 s);
* speed: ``rate_hz`` (poses per second of processing), ``pose_rate_hz`` (poses per second of
  data after the warm-up's first frame), ``real_time_factor`` (processing seconds per second of data: at most 1 keeps up);
* latency from event time to pose output: ``latency_ms_p50`` / ``p90`` / ``max``;
* ``stages``: per-stage timings (count, mean, p50, p90, max in ms, total in s);
* robustness: ``loop_closures``, ``tracking_losses``, ``warnings``, ``status``, ``complete``.

:func:`plot_trajectory` draws the estimate against the ground truth (top view) and the error over
time with matplotlib's Agg canvas (no pyplot state, no display needed).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..measurements import PoseSamples
from ..fileio import atomic_write, atomic_write_text
from .trajectory import ate, end_error, json_ready, rpe

METRICS_VERSION = 1


def _percentiles(x, qs=(50, 90)) -> list[float | None]:
    x = np.asarray(x, np.float64)
    x = x[np.isfinite(x)]
    return [float(np.percentile(x, q)) if len(x) else None for q in qs]


def stage_summary(stage_ms: dict[str, list[float]]) -> dict[str, dict]:
    """Per-stage timing statistics: ``{stage: {count, mean_ms, p50_ms, p90_ms, max_ms, total_s}}``."""
    out = {}
    for name, values in stage_ms.items():
        v = np.asarray(values, np.float64)
        if len(v) == 0:
            out[name] = {"count": 0, "mean_ms": None, "p50_ms": None, "p90_ms": None, "max_ms": None, "total_s": 0.0}
            continue
        p50, p90 = _percentiles(v)
        out[name] = {"count": int(len(v)), "mean_ms": float(v.mean()), "p50_ms": p50, "p90_ms": p90,
                     "max_ms": float(v.max()), "total_s": float(v.sum() / 1e3)}
    return out


def compute_metrics(result, gt: PoseSamples | None, *, sequence: str | os.PathLike | None = None, detector: str | None = None,
                    mode: str | None = None, config: str | None = None, extra: dict | None = None,
                    rpe_delta_s: float = 1.0) -> tuple[dict, dict | None, dict | None]:
    """Metrics of one run.

    Args:
        result: a ``SlamResult`` (fields ``t_us``, ``pose7``, ``latency_ms``, ``stage_ms``, ``wall_s``,
            ``sequence_duration_s``, ``loop_closures``, ``tracking_losses``, ``warnings``, ``status``,
            ``complete``; optional ``pose7_final``).
        gt: ground truth ``T_world_body`` (None: accuracy fields are None and a warning says why).
        sequence, detector, mode, config: recorded as given.
        extra: merged in last (e.g. the loop closer's summary).

    Returns:
        (metrics dict ready for JSON, the SE(3) ATE result with its arrays for plotting or None, the
        same for the final trajectory or None).
    """
    t_us = np.asarray(result.t_us, np.int64)
    pose7 = np.asarray(result.pose7, np.float64).reshape(-1, 7)
    n = len(t_us)
    wall = float(result.wall_s)
    duration = float(result.sequence_duration_s)
    info = getattr(result, "info", None) or {}
    warm_up_s = 0.0
    if info.get("t_first_frame_us") is not None and info.get("t_begin_us") is not None:
        warm_up_s = max(float(info["t_first_frame_us"] - info["t_begin_us"]) * 1e-6, 0.0)
    output_span = duration - warm_up_s
    warnings = list(result.warnings)
    p50, p90 = _percentiles(result.latency_ms)
    lat = np.asarray(result.latency_ms, np.float64)
    m: dict = {
        "metrics_version": METRICS_VERSION,
        "sequence": None if sequence is None else str(sequence),
        "detector": detector,
        "mode": mode,
        "config": config,
        "status": result.status,
        "complete": bool(result.complete),
        "poses": n,
        "t_first_s": float(t_us[0]) / 1e6 if n else None,
        "t_last_s": float(t_us[-1]) / 1e6 if n else None,
        "sequence_duration_s": duration,
        "wall_s": wall,
        "rate_hz": n / wall if wall > 0 else None,
        # over the data after the warm-up (the first frame waits for complete time surfaces, and no
        # pose is due before it); the real-time factor keeps the whole span, whose events were ingested
        "pose_rate_hz": n / output_span if output_span > 0 else None,
        "real_time_factor": wall / duration if duration > 0 else None,
        "latency_ms_p50": p50,
        "latency_ms_p90": p90,
        "latency_ms_max": float(lat[np.isfinite(lat)].max()) if np.isfinite(lat).any() else None,
        "ate_rmse_m": None, "ate_pct": None, "path_length_m": None, "ate_pairs": 0, "ate_align": "se3",
        "ate_mean_m": None, "ate_median_m": None, "ate_max_m": None,
        "ate_sim3_rmse_m": None, "sim3_scale": None,
        "rpe_delta_s": rpe_delta_s, "rpe_trans_rmse_m": None, "rpe_rot_rmse_deg": None, "rpe_pairs": 0,
        # the last output's error after aligning the first seconds (trajectory.end_error): the drift
        # a loop closure removes on a sequence that returns to its start
        "end_error_m": None, "end_error_align_s": None,
        "loop_closures": int(result.loop_closures),
        "tracking_losses": int(result.tracking_losses),
        "stages": stage_summary(result.stage_ms),
        "warnings": warnings,
        "final": None,  # the final trajectory's accuracy (pipeline.SlamResult.pose7_final), when the run completed
    }
    ate_se3 = ate_final = None
    if gt is None or len(gt) == 0:
        warnings.append("no ground truth in the sequence: accuracy not evaluated")
    elif n < 3:
        warnings.append(f"{n} pose(s) estimated: too few to align (ATE needs 3)")
    else:
        est = PoseSamples(t_us, pose7)
        try:
            ate_se3 = ate(gt, est, align="se3", interpolate=True)
            ate_sim3 = ate(gt, est, align="sim3", interpolate=True)
        except DataError as exc:
            warnings.append(f"ATE not evaluated: {exc.problem}")
            ate_se3 = None
        if ate_se3 is not None:
            r = json_ready(ate_se3)
            m.update(ate_rmse_m=r["ate_rmse_m"], ate_pct=r["ate_pct"], path_length_m=r["path_length_m"], ate_pairs=r["pairs"],
                     ate_mean_m=r["ate_mean_m"], ate_median_m=r["ate_median_m"], ate_max_m=r["ate_max_m"],
                     ate_sim3_rmse_m=ate_sim3["ate_rmse_m"], sim3_scale=ate_sim3["scale"])
            if r["pairs"] < n:
                warnings.append(f"{n - r['pairs']} of {n} poses lie outside the ground truth's time span or gaps: not evaluated")
            # a run shorter than two intervals gets a quarter of its span (recorded in rpe_delta_s)
            span_s = ate_se3["duration_s"]
            delta = rpe_delta_s if span_s >= 2 * rpe_delta_s else max(0.05, round(span_s / 4 / 0.05) * 0.05)
            m.update(rpe(gt, est, delta_s=delta))
            m.update(_end_error(gt, est, warnings))
            final = getattr(result, "pose7_final", None)
            if final is not None:
                # the same alignment and RPE of the final trajectory (same times as the live outputs)
                est_f = PoseSamples(t_us, np.asarray(final, np.float64).reshape(-1, 7))
                ate_final = ate(gt, est_f, align="se3", interpolate=True)
                rf = json_ready(ate_final)
                rpe_f = rpe(gt, est_f, delta_s=delta)
                m["final"] = {"ate_rmse_m": rf["ate_rmse_m"], "ate_pct": rf["ate_pct"], "ate_max_m": rf["ate_max_m"],
                              "rpe_trans_rmse_m": rpe_f["rpe_trans_rmse_m"], "rpe_rot_rmse_deg": rpe_f["rpe_rot_rmse_deg"],
                              "end_error_m": _end_error(gt, est_f, [])["end_error_m"]}
    if extra:
        m.update(extra)
    return m, ate_se3, ate_final


def _end_error(gt: PoseSamples, est: PoseSamples, warnings: list[str]) -> dict:
    """:func:`~aerovis_slam.slam.trajectory.end_error` as metrics entries (None, with a warning, when the
    run's first seconds hold too few outputs to align)."""
    try:
        r = end_error(gt, est)
    except DataError as exc:
        warnings.append(f"end error not evaluated: {exc.problem}")
        return {"end_error_m": None, "end_error_align_s": None}
    return {"end_error_m": r["end_error_m"], "end_error_align_s": r["end_error_align_s"]}


def write_metrics(path: str | os.PathLike, metrics: dict) -> Path:
    """Write ``metrics.json`` atomically (indented, NaN-free: non-finite numbers become null)."""
    return atomic_write_text(path, json.dumps(_finite(metrics), indent=2) + "\n")


def _finite(x):
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def plot_trajectory(path: str | os.PathLike, gt: PoseSamples | None, ate_result: dict | None, *,
                    est: PoseSamples | None = None, title: str = "", loop_times_s: list[float] | None = None,
                    init_time_s: float | None = None, final_result: dict | None = None) -> Path:
    """``traj.png``: top view (x-y) of the aligned estimate against the ground truth, and the
    translation error over time. Written atomically.

    Args:
        gt: ground truth (drawn over the estimate's time span).
        ate_result: :func:`~aerovis_slam.slam.trajectory.ate` output with its arrays (None: the raw
            estimate ``est`` is drawn without errors).
        loop_times_s: times of loop closures (vertical lines on the error plot).
        init_time_s: time of the visual-inertial initialisation; the error plot shades what comes
            before it (vision-only outputs, no gravity yet).
        final_result: the same for the final trajectory (``traj_final.txt``), drawn dashed.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4.5), dpi=100)
    FigureCanvasAgg(fig)
    ax0, ax1 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    if ate_result is not None:
        t = np.asarray(ate_result["t_us"]) / 1e6
        if gt is not None:
            sel = (gt.t >= ate_result["t_us"][0]) & (gt.t <= ate_result["t_us"][-1])
            ax0.plot(gt.pose[sel, 0], gt.pose[sel, 1], "k-", lw=1.5, label="ground truth")
        e = ate_result["est_aligned"]
        ax0.plot(e[:, 0], e[:, 1], "-", color="tab:red", lw=1.0, label="estimate (SE(3)-aligned)")
        ax0.plot(e[:1, 0], e[:1, 1], "o", color="tab:green", label="start")
        ax1.plot(t - t[0], np.asarray(ate_result["error_m"]) * 100, "-", color="tab:red", lw=1.0, label="live")
        if final_result is not None:
            f = final_result["est_aligned"]
            ax0.plot(f[:, 0], f[:, 1], "--", color="tab:purple", lw=1.0, label="final trajectory (SE(3)-aligned)")
            tf = np.asarray(final_result["t_us"]) / 1e6
            ax1.plot(tf - t[0], np.asarray(final_result["error_m"]) * 100, "--", color="tab:purple", lw=1.0, label="final")
        ax1.set_title(f"ATE RMSE {ate_result['ate_rmse_m'] * 100:.2f} cm"
                      + (f" ({ate_result['ate_pct']:.2f} % of {ate_result['path_length_m']:.2f} m)" if ate_result.get("ate_pct") is not None else "")
                      + (f", final {final_result['ate_rmse_m'] * 100:.2f} cm" if final_result is not None else ""))
        for i, tl in enumerate(loop_times_s or []):
            ax1.axvline(tl - t[0], color="tab:blue", lw=0.8, ls="--", label="loop closure" if i == 0 else None)
        shade_init = init_time_s is not None and init_time_s > t[0]
        if shade_init:
            ax1.axvspan(0.0, init_time_s - t[0], color="0.85", label="before initialisation")
        if loop_times_s or shade_init or final_result is not None:
            ax1.legend(loc="upper right", fontsize=8)
    else:
        if gt is not None and len(gt):
            ax0.plot(gt.pose[:, 0], gt.pose[:, 1], "k-", lw=1.5, label="ground truth")
        if est is not None and len(est):
            ax0.plot(est.pose[:, 0], est.pose[:, 1], "-", color="tab:red", lw=1.0, label="estimate (not aligned)")
        ax1.text(0.5, 0.5, "no error: ground truth missing\nor too few poses", ha="center", va="center", transform=ax1.transAxes)
    ax0.set_xlabel("x [m]")
    ax0.set_ylabel("y [m]")
    ax0.set_aspect("equal", adjustable="datalim")
    ax0.grid(True, alpha=0.3)
    ax0.legend(loc="best", fontsize=8)
    ax0.set_title("top view")
    ax1.set_xlabel("time [s]")
    ax1.set_ylabel("translation error [cm]")
    ax1.grid(True, alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png"))
