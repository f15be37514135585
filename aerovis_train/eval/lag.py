"""How far behind its time stamp a time surface's keypoints show the scene (``aerovis-eval lag``).

An event edge leaves a trail in a time surface, and a keypoint detected on it need not sit at the
edge's newest position. This measures where it sits, in time: for frames with an intensity image
and a depth map (the simulator writes both), the Shi-Tomasi corners of the image at ``t`` are
lifted with the depth and moved with the ground truth to where the camera saw them at
``t - lag``; the lag whose corners lie closest to the keypoints detected on the MCTS at ``t``
(mean distance to the nearest moved corner, truncated at ``radius_px``, a parabola through the best grid point and its
neighbours) is the keypoints' lag. Expressed as events per pixel (the events each camera fired in
``(t - lag, t]`` over its pixel count, median over frames) it is the SLAM runtime's
``detector.observation_lag_events_per_px``, which holds across event rates where a lag in
milliseconds would not (a constant-event-count surface spans less time when the scene moves faster).

Only numpy and OpenCV; learned detectors come from :mod:`aerovis_train.eval.learned` (torch) or
bundles (ONNX Runtime).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from aerovis_slam.errors import DataError
from aerovis_slam.geometry import invert_T, sample_depth_nearest, warp_pixels
from aerovis_slam.io.sequence import Sequence, camera_key
from aerovis_slam.keypoints import keep_top_k
from aerovis_slam.mcts import MCTS_DT_WINDOWS_MS, MCTS_NE_EVENTS_PER_PX, TimestampBuffer

from ..labels import CornerLabeller
from .pose import _stream_surfaces, interpolate_poses, mcts_warm_up_us

#: Lags tried (ms): behind (positive) and, as a check, ahead of the time stamp.
DEFAULT_LAGS_MS = tuple(range(-30, 91, 5))


def corners_at_lags(corners_px: np.ndarray, depth_m: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray,
                    T_world_cam_lags: np.ndarray) -> np.ndarray:
    """Pixels (L, N, 2) where the scene points behind ``corners_px`` (N, 2) at z-depth ``depth_m``
    (N,), seen by the pinhole ``K`` from ``T_world_cam`` (4, 4), appear from each of the poses
    ``T_world_cam_lags`` (L, 4, 4). Points behind a camera come out as NaN (no image bounds: a
    corner just outside still counts as the nearest one to a keypoint at the border)."""
    out = np.full((len(T_world_cam_lags), len(corners_px), 2), np.nan)
    for i, T in enumerate(T_world_cam_lags):
        xy, valid = warp_pixels(corners_px, depth_m, K, K, invert_T(T) @ T_world_cam)
        out[i, valid] = xy[valid]
    return out


def nearest_distances(keypoints_px: np.ndarray, candidates_px: np.ndarray) -> np.ndarray:
    """(L, K) distance (px) of each keypoint (K, 2) to the nearest point of each candidate set
    (L, N, 2; NaN rows ignored); inf where a set is empty."""
    out = np.full((len(candidates_px), len(keypoints_px)), np.inf)
    for i, cand in enumerate(candidates_px):
        cand = cand[np.isfinite(cand[:, 0])]
        if len(cand) and len(keypoints_px):
            out[i] = np.sqrt(((keypoints_px[:, None, :] - cand[None]) ** 2).sum(-1)).min(1)
    return out


def refine_minimum(grid: np.ndarray, values: np.ndarray) -> float:
    """Argmin of ``values`` over the evenly spaced ``grid``, refined by a parabola through it and its
    two neighbours (the grid point itself at an end of the grid or on a flat stretch)."""
    j = int(np.argmin(values))
    if 0 < j < len(values) - 1:
        a, b, c = values[j - 1: j + 2]
        curvature = a - 2 * b + c
        if curvature > 0:
            return float(grid[j] + 0.5 * (a - c) / curvature * (grid[1] - grid[0]))
    return float(grid[j])


def keypoint_lag(seq_path: str | Path, detector, *, cam: str = "cam0", lags_ms=DEFAULT_LAGS_MS, top_k: int | None = None,
                 radius_px: float = 3.0, max_corners: int = 600, max_frames: int | None = None,
                 margin_s: float = 0.2) -> dict:
    """Measure the keypoint lag of ``detector`` on one sequence (see the module docstring).

    Args:
        seq_path: canonical ``.h5`` with events, ``/frames`` and ``/depth`` of ``cam``, GT and calibration.
        detector: a callable ``mcts (C, H, W) -> Keypoints`` (learned: :func:`~aerovis_train.eval.learned.load_detector`),
            or a classical baseline's name. Its ``mcts_kind`` / ``mcts_params`` choose the surface.
        lags_ms: the evenly spaced lags tried.
        top_k: keypoints per frame (default ``max(H, W) // 2``, as the pose protocol).
        radius_px: distance truncation: farther keypoints match no corner.
        max_corners: Shi-Tomasi corners per image (quality 0.01, 3 px apart, sub-pixel refined).
        max_frames: use at most this many frames (evenly spread).
        margin_s: frames this close to either end of the GT, or to the MCTS warm-up, are skipped
            (every lag's pose must be interpolated, not extrapolated).

    Returns:
        JSON-ready dict: ``sequence``, ``detector``, ``cam``, ``frames``, ``keypoints``, ``lag_ms``
        (the refined minimum), ``lag_events_per_px`` (events per pixel in ``(t - lag_ms, t]``,
        median over frames), ``mcts_windows_ms`` (median span of each MCTS_Ne window; None for
        MCTS_dt), and ``curve``: per lag, ``mean_distance_px`` and ``within_1px`` (fraction of
        keypoints within 1 px of a moved corner).

    Raises:
        DataError: no frames, depth, GT or calibration for ``cam``, or no usable frame.
    """
    path = Path(seq_path)
    cam = camera_key(cam)
    lags = np.asarray(lags_ms, np.float64)
    if len(lags) < 3 or not np.allclose(np.diff(lags), lags[1] - lags[0]) or lags[1] <= lags[0]:
        raise ValueError(f"lags_ms must be at least 3 increasing, evenly spaced values, got {list(lags_ms)}")
    kind = getattr(detector, "mcts_kind", None) or "ne"
    params = tuple(getattr(detector, "mcts_params", None) or (MCTS_NE_EVENTS_PER_PX if kind == "ne" else MCTS_DT_WINDOWS_MS))
    with Sequence(path) as seq:
        if cam not in seq.cameras:
            raise DataError(path, f"no camera {cam!r} under /events; cameras are {seq.cameras}")
        gt = seq.gt
        if gt is None or len(gt) < 2:
            raise DataError(path, "no ground truth (/gt): the keypoint lag moves corners with the GT poses")
        if not seq.has_calib or cam not in seq.calib.cameras:
            raise DataError(path, f"no calibration of {cam} in /calib")
        camcal = seq.calib.cameras[cam]
        frame_t, depth_t = seq.frame_times(cam), seq.frame_times(cam, "depth")
        if frame_t is None or depth_t is None:
            raise DataError(path, f"no /frames/{cam} or /depth/{cam}: the keypoint lag needs intensity frames and depth maps (simulated data has both)")
        if camcal.distortion_model != "none":
            raise DataError(path, f"{cam} has {camcal.distortion_model} distortion: the keypoint lag needs a pinhole camera (the simulator's)")
        W, H = seq.sensor_size(cam)
        shift = camcal.imu_clock_offset_us
        warm_t = mcts_warm_up_us(seq, cam, kind, params)
        margin = int(margin_s * 1e6)
        lag_max = int(max(abs(lags[0]), abs(lags[-1])) * 1000)
        common = np.intersect1d(frame_t, depth_t)
        ok = (common >= warm_t + margin) & (common + shift - lag_max >= gt.t[0] + margin) & \
             (common + shift + lag_max <= gt.t[-1] - margin) & (common <= seq.time_range(cam)[1])
        times = common[ok]
        if max_frames is not None and len(times) > max_frames:
            times = times[np.round(np.linspace(0, len(times) - 1, int(max_frames))).astype(int)]
        if len(times) == 0:
            raise DataError(path, f"no frame of {cam} with depth, {margin_s:g} s inside the GT and past the MCTS warm-up")
        frame_index = {int(t): i for i, t in enumerate(frame_t)}
        depth_index = {int(t): i for i, t in enumerate(depth_t)}
        top_k = int(top_k) if top_k is not None else max(W, H) // 2
        if isinstance(detector, str):
            from aerovis_slam.classical import make_detector

            name = detector
            detector = make_detector(detector, top_k=top_k)
        else:
            name = getattr(detector, "name", type(detector).__name__)
        # the training labeller's Shi-Tomasi corners, denser and weaker ones too (quality 0.01, 3 px apart)
        find_corners = CornerLabeller(max_corners=max_corners, quality=0.01, min_distance=3, block_size=3)
        buf = TimestampBuffer(W, H, events_per_px=params if kind == "ne" else (1e-9,))
        compute = (lambda tau: buf.mcts_ne(tau, params)) if kind == "ne" else (lambda tau: buf.mcts_dt(tau, params))
        K = camcal.K
        sums = np.zeros(len(lags))
        within = np.zeros(len(lags))
        n_kp = 0
        windows = []
        per_frame_t = []
        for k, mcts in _stream_surfaces(seq, cam, times, buf, compute):
            t = int(times[k])
            if kind == "ne":
                windows.append(buf.ne_windows_us(t, params))
            xy = np.asarray(keep_top_k(detector(mcts), top_k).xy, np.float64)
            img = seq.frame(cam, frame_index[t])
            corners = find_corners(img)
            if len(corners) == 0 or len(xy) == 0:
                continue
            corners = cv2.cornerSubPix(img, corners, (3, 3), (-1, -1),
                                       (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)).reshape(-1, 2)
            depth = seq.frame(cam, depth_index[t], "depth")
            z = sample_depth_nearest(depth, corners)
            good = np.isfinite(z) & (z > 0)
            if not good.any():
                continue
            poses = interpolate_poses(gt.t, gt.pose, np.concatenate([[t + shift], t + shift - np.round(lags * 1000).astype(np.int64)])) @ camcal.T_imu_cam
            moved = corners_at_lags(corners[good].astype(np.float64), z[good].astype(np.float64), K, poses[0], poses[1:])
            d = nearest_distances(xy, moved)
            sums += np.minimum(d, radius_px).sum(1)
            within += (d < 1.0).sum(1)
            n_kp += len(xy)
            per_frame_t.append(t)
        if n_kp == 0:
            raise DataError(path, f"no keypoints or no corners with depth on {len(times)} frames of {cam}")
        mean = sums / n_kp
        lag = refine_minimum(lags, mean)
        # events per pixel in (t - lag, t], per frame (the index of the ms table, no event read)
        epp = [(seq.index_at(cam, t + 1) - seq.index_at(cam, t + 1 - int(round(lag * 1000)))) / (W * H)
               for t in per_frame_t] if lag > 0 else [0.0]
    return {
        "sequence": path.stem, "detector": str(name), "cam": cam, "mcts": kind, "frames": len(per_frame_t), "keypoints": n_kp,
        "lag_ms": lag, "lag_events_per_px": float(np.median(epp)),
        "mcts_windows_ms": (np.median(np.array(windows), axis=0) / 1000).round(2).tolist() if windows else None,
        "curve": [{"lag_ms": float(L), "mean_distance_px": float(m), "within_1px": float(w / n_kp)}
                  for L, m, w in zip(lags, mean, within)],
    }



def plot_curves(results: list[dict], path: str | Path) -> Path:
    """PNG: mean distance to the moved corners against the lag, one line per sequence (colour) and
    method (line style), the refined minimum marked (matplotlib's Agg canvas; written atomically)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from aerovis_slam.fileio import atomic_write

    fig = Figure(figsize=(7.5, 4.5), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    sequences = list(dict.fromkeys(r["sequence"] for r in results))
    detectors = list(dict.fromkeys(r["detector"] for r in results))
    colours = [f"C{i % 10}" for i in range(len(sequences))]  # colour: sequence; line style: detector
    styles = ["-", "--", ":", "-."]
    for r in results:
        x = [c["lag_ms"] for c in r["curve"]]
        y = [c["mean_distance_px"] for c in r["curve"]]
        colour = colours[sequences.index(r["sequence"])]
        ax.plot(x, y, color=colour, ls=styles[detectors.index(r["detector"]) % len(styles)],
                label=f"{r['detector']} {r['sequence']}: {r['lag_ms']:.1f} ms")
        ax.axvline(r["lag_ms"], color=colour, lw=0.6, ls=":")
    ax.set_xlabel("lag: corners moved to t - lag [ms]")
    ax.set_ylabel("mean distance keypoint -> corner [px, truncated]")
    ax.set_title("Keypoint lag of time-surface detectors")
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png"))


def add_parser(sub) -> None:
    """The ``lag`` subcommand of ``aerovis-eval``."""
    from aerovis_slam.classical import DETECTORS

    p = sub.add_parser("lag", help="how far behind its time stamp a detector's keypoints show the scene (needs frames + depth: simulated data)")
    p.add_argument("--data", required=True, help="canonical sequence (.h5), a folder of them or a simulator preset (bench, tiny)")
    p.add_argument("--model", nargs="*", default=[], help="learned model(s): shipped name, model.pt, .ckpt or bundle directory")
    p.add_argument("--detector", nargs="*", default=[], choices=sorted(DETECTORS), help="classical detector(s) on MCTS_Ne")
    p.add_argument("--cam", default="cam0", help="camera (default cam0)")
    p.add_argument("--top-k", type=int, default=None, help="keypoints per frame (default max(H, W) // 2)")
    p.add_argument("--max-frames", type=int, default=None, help="at most this many frames per sequence")
    p.add_argument("--out", help="folder for lag.json (with the curves) and lag.png")


def main_lag(args) -> int:
    """Run ``aerovis-eval lag``: one JSON line per sequence and method, then one summary line per method."""
    import json
    import sys

    from aerovis_slam.fileio import atomic_write_json, prepare_out_dir

    from .cli import UsageError, load_model_arg, _sequences

    if not args.model and not args.detector:
        raise UsageError("give at least one --model or --detector")
    seqs = _sequences(args.data)
    out = prepare_out_dir(args.out) if args.out else None
    methods = [(m, load_model_arg(m)) for m in args.model] + [(d, d) for d in args.detector]
    results, summaries = [], []
    for label, detector in methods:
        mine = []
        for s in seqs:
            try:
                r = keypoint_lag(s, detector, cam=args.cam, top_k=args.top_k, max_frames=args.max_frames)
            except DataError as exc:
                print(f"skipped {s.name}: {exc}", file=sys.stderr)
                continue
            r["detector"] = label
            mine.append(r)
            print(json.dumps({k: v for k, v in r.items() if k != "curve"}))
            sys.stdout.flush()
        if not mine:
            raise DataError(Path(args.data), "no sequence has frames and depth for the keypoint lag")
        summary = {"detector": label, "sequences": len(mine),
                   "lag_ms_median": float(np.median([r["lag_ms"] for r in mine])),
                   "lag_events_per_px_median": float(np.median([r["lag_events_per_px"] for r in mine])),
                   "lag_events_per_px_range": [float(min(r["lag_events_per_px"] for r in mine)),
                                               float(max(r["lag_events_per_px"] for r in mine))]}
        print(json.dumps(summary))
        results += mine
        summaries.append(summary)
    if out is not None:
        atomic_write_json(out / "lag.json", {"data": str(args.data), "summaries": summaries, "sequences": results})
        plot_curves(results, out / "lag.png")
        print(f"wrote {out / 'lag.json'} and {out / 'lag.png'}", file=sys.stderr)
    return 0
