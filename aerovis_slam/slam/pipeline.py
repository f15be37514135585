"""Run the SLAM pipeline on a canonical sequence: :func:`run_slam` -> :class:`SlamResult`.

Modes (paper Sec. III-C):

* ``sync``: frames at a fixed rate (``config.rate_hz``, e.g. 50 Hz); every step is processed however
  long it takes (the accuracy setting, the paper's OKVIS2-SE+ column). The reported latency is what
  a live system would see with a frame queue: a frame waits until the previous one is done.
* ``async``: the frontend always takes the newest state when it is free (the real-time setting).
  Offline, the recording is replayed on a simulated clock that advances by the measured processing
  time of each iteration, so the frames chosen and the latencies are what this machine would have
  produced live, deterministic given the timings. The state at clock ``c`` holds every event up to
  the newest IMU sample at or before ``c`` (events wait for IMU coverage).
* ``live``: wall-clock replay: a preprocessing thread ingests events at sensor speed while the
  frontend snapshots the buffers whenever it is free.

Preprocessing (reading, ingesting events) runs beside the frontend in the paper's design; it is
timed (``stage_ms["preprocess"]``) but, in ``async`` mode, not charged to the simulated clock.

Threads: the event reader (and in ``live`` mode the preprocessor) end when the run ends, on an
error, on ``stop_event`` and on KeyboardInterrupt; a stopped run returns its partial trajectory with
``complete=False`` (and says so in ``status``).

Example (a sketch; see ``aerovis-slam run``)::

    from aerovis_slam.slam.pipeline import load_config, run_slam
    from aerovis_slam.slam.detectors import StereoClassicalDetector
    res = run_slam("seq.h5", StereoClassicalDetector("orb"), load_config("accurate"), mode="sync")
    res.t_us, res.pose7      # T_world_body outputs (world: gravity-aligned, origin at the first pose)
"""

from __future__ import annotations

import sys
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ..environment import blas_thread_limit
from ..errors import DataError
from ..geometry import invert_T, matrix_to_pose7
from ..io.sequence import Sequence
from .cameras import StereoCameras
from .config import MODES, SlamConfig, load_config
from .imu import ImuStream
from .odometry import StereoInertialOdometry, WarningLog
from .preprocessing import EventFeeder, EventReader, LivePreprocessor, observation_time
from .stereo import is_rectified, swapped_pair_message
from .trajectory import final_trajectory

__all__ = ["SlamResult", "load_config", "run_slam"]

STAGES = ("preprocess", "mcts", "detector", "matching", "refine", "tracking", "keyframe", "backend", "loop", "total")


@dataclass
class SlamResult:
    """Outcome of :func:`run_slam`.

    Attributes:
        t_us: (N,) int64 times of the pose outputs (µs, sequence clock).
        pose7: (N, 7) ``T_world_body`` as ``tx ty tz qx qy qz qw`` (world: gravity-aligned, z up,
            origin and yaw at the first estimated body pose; loop-closure corrections applied from
            the moment they arrive, as a live system would output them).
        latency_ms: (N,) event time (the frame's ``tau``) -> pose output.
        stage_ms: per-stage durations per iteration (``preprocess``, ``mcts``, ``detector``,
            ``matching``, ``refine``, ``tracking``, ``keyframe``, ``backend``, ``loop``, ``total``).
        wall_s: wall time of the run. sequence_duration_s: replayed span of the recording.
        loop_closures: closures reported by the loop closer. tracking_losses: map re-initialisations.
        warnings: distinct warnings with repeat counts. status: ``ok`` | ``failed: ...`` | ``stopped: ...``.
        complete: False when stopped early or failed (the trajectory is partial).
        mode, detector, config: what ran. keyframes: keyframes created. tracked: (N,) bool visual tracking.
        info: counters (events, dropped by the rate cap, IMU gaps, landmarks, loop corrections applied),
            ``initialized`` and ``t_initialized_us`` (when the visual-inertial initialisation succeeded).
        pose7_final: (N, 7) the final trajectory at the same times (every output moved with its
            keyframe's last smoother estimate and the last pose graph, see
            :func:`~aerovis_slam.slam.trajectory.final_trajectory`); None when the run did not complete.
        slot_us: (N,) int64 the frame slot of each output: the time up to which its frame holds the
            events (µs; ``t_us`` is at or before it, see ``detector.observation_lag_events_per_px``).
            Passed back as ``frame_slots`` it replays the same frames.
        iteration_caps: per output, the LM iteration caps of the backend updates its frame made
            (``backend.time_budget_ms`` lowers them on a slow machine); ``frame_caps`` of a replay.
    """

    t_us: np.ndarray
    pose7: np.ndarray
    latency_ms: np.ndarray
    stage_ms: dict[str, list[float]]
    wall_s: float
    sequence_duration_s: float
    loop_closures: int
    tracking_losses: int
    warnings: list[str]
    status: str
    complete: bool
    mode: str = "sync"
    detector: str = ""
    config: str = ""
    keyframes: int = 0
    tracked: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    info: dict = field(default_factory=dict)
    pose7_final: np.ndarray | None = None
    slot_us: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    iteration_caps: list[list[int]] = field(default_factory=list)

    @property
    def rate_hz(self) -> float:
        """Pose outputs per second of recording."""
        return len(self.t_us) / self.sequence_duration_s if self.sequence_duration_s > 0 else 0.0


def final_poses(odo, loop_closer, T_out: list[np.ndarray], anchors: list[tuple]) -> np.ndarray:
    """(N, 4, 4) final trajectory of a finished run (see ``SlamResult.pose7_final``): waits (up to
    10 s) for a pose-graph optimisation still running, so that a loop found at the end counts too."""
    corrections = None
    if loop_closer is not None:
        loop_closer.wait_idle(timeout=10.0)
        loop_closer.poll()
        corrections = loop_closer.corrections()
    eye = np.eye(4)
    return final_trajectory(np.stack(T_out), np.array([a[0] for a in anchors], np.int64),
                            np.stack([eye if a[1] is None else a[1] for a in anchors]),
                            np.stack([eye if a[2] is None else a[2] for a in anchors]), odo.kf_smoothed, corrections)


def _open_inputs(path: Path):
    with Sequence(path) as seq:
        if not seq.has_calib:
            raise DataError(path, "no /calib: the SLAM runtime needs the stereo calibration (cam0, cam1 with T_imu_cam)")
        calib = seq.calib
        imu = seq.imu
        if imu is None or len(imu) < 2:
            raise DataError(path, "no /imu samples: stereo event-inertial SLAM needs the IMU")
        for cam in ("cam0", "cam1"):
            if cam not in seq.cameras:
                raise DataError(path, f"no /events/{cam}: stereo SLAM needs cam0 (left) and cam1 (right); found {seq.cameras}")
        ranges = [seq.time_range(c) for c in ("cam0", "cam1")]
    # events move onto the IMU clock (Kalibr's t_imu = t_cam + timeshift_cam_imu); all times after
    # this point, frames and outputs included, are IMU-clock times
    shifts = {c: calib.cameras[c].imu_clock_offset_us for c in ("cam0", "cam1")}
    ranges = [None if r is None else (r[0] + shifts[c], r[1] + shifts[c]) for r, c in zip(ranges, ("cam0", "cam1"))]
    return calib, imu, ranges, shifts


def check_frame_slots(frame_slots: np.ndarray, stream, t_begin: int, t_end: int, path=None) -> None:
    """Refuse replay slots (µs) that an async run of this recording could not have taken.

    Async takes the newest IMU sample at or before its clock (``stream.covered_until``), and the
    clock starts at ``t_begin``: its first slot can precede ``t_begin`` by up to one IMU period
    (spin_hdr_window of the bench preset: slot 20000 µs for ``t_begin`` 20029 µs).

    Raises:
        DataError: a slot before ``stream.covered_until(t_begin)`` or after ``t_end``.
    """
    first_slot = stream.covered_until(t_begin)
    if frame_slots[0] < first_slot or frame_slots[-1] > t_end:
        raise DataError(path, f"frame_slots span {frame_slots[0]}..{frame_slots[-1]} µs, outside this recording's "
                              f"frames {first_slot}..{t_end} µs (slots of another sequence?)")


def run_slam(sequence: str | Path, detector, config: SlamConfig, *, mode: str | None = "sync", loop_closer=None,
             progress: bool = True, stop_event: threading.Event | None = None,
             frame_slots: np.ndarray | None = None, frame_caps: list[list[int]] | None = None) -> SlamResult:
    """Estimate the body trajectory of a stereo event + IMU sequence.

    Args:
        sequence: canonical ``.h5`` sequence (events cam0/cam1, IMU, calibration).
        detector: stereo detector (``detect``, ``mcts_kind``, ``mcts_params``, ``size_multiple``; see
            :mod:`aerovis_slam.slam.detectors`).
        config: settings (:func:`load_config`).
        mode: ``sync`` | ``async`` | ``live`` (None: ``config.mode``).
        loop_closer: optional ``LoopCloser`` (closed at the end of the run).
        progress: tqdm bar on stderr over sequence time.
        stop_event: set it (from another thread) to stop early.
        frame_slots: ``async`` only: (M,) increasing frame slots (µs, IMU clock), e.g. an earlier run's
            ``slot_us``. The frames are these instead of those the simulated clock picks, so an async
            run (whose frames depend on this machine's timing) is reproduced; the latencies are
            still this run's (its clock waits for each slot).
        frame_caps: with ``frame_slots``: per slot, the backend's iteration caps of that frame in
            the run replayed (its ``iteration_caps``), imposed instead of what
            ``backend.time_budget_ms`` allows on this machine now. With both the replay is exact
            (``info["replay_cap_mismatches"]`` counts frames whose updates did not match).

    Raises:
        DataError: the sequence lacks what SLAM needs (calibration, IMU, a camera), bad mode, or
            frame slots that are not increasing or outside the recording.
    """
    # process-wide while the run lasts (every thread's numpy), restored afterwards
    with blas_thread_limit(config.blas_threads):
        return _run_slam(sequence, detector, config, mode=mode, loop_closer=loop_closer, progress=progress,
                         stop_event=stop_event, frame_slots=frame_slots, frame_caps=frame_caps)


def _run_slam(sequence: str | Path, detector, config: SlamConfig, *, mode: str | None, loop_closer,
              progress: bool, stop_event: threading.Event | None, frame_slots: np.ndarray | None,
              frame_caps: list[list[int]] | None) -> SlamResult:
    """:func:`run_slam` without the BLAS thread limit."""
    path = Path(sequence)
    mode = mode or config.mode
    if mode not in MODES:
        raise DataError(None, f"mode must be one of {MODES}, got {mode!r}")
    if frame_slots is not None:
        frame_slots = np.asarray(frame_slots, np.int64).reshape(-1)
        if mode != "async":
            raise DataError(None, f"frame_slots replay an async run's frames; mode is {mode!r}")
        if len(frame_slots) == 0 or np.any(np.diff(frame_slots) <= 0):
            raise DataError(None, "frame_slots must be a non-empty, strictly increasing list of times (µs)")
    if frame_caps is not None and (frame_slots is None or len(frame_caps) != len(frame_slots)):
        raise DataError(None, f"frame_caps need frame_slots of the same length (got {len(frame_caps)} caps for "
                              f"{0 if frame_slots is None else len(frame_slots)} slots)")
    windows = len(getattr(detector, "mcts_params", ()))
    if config.detector.min_event_support > 0 and not config.detector.support_window < windows:
        raise DataError(None, f"detector.support_window {config.detector.support_window}: the detector's MCTS has "
                              f"{windows} windows (0..{windows - 1})")
    calib, imu, ranges, shifts = _open_inputs(path)
    cams = StereoCameras.from_rig(calib, max_width=config.input.max_width, max_height=config.input.max_height,
                                  size_multiple=int(getattr(detector, "size_multiple", 1)), path=path)
    stream = ImuStream(imu, max_gap_us=int(config.tracking.max_imu_gap_ms * 1000))
    log = WarningLog()
    # which stereo path runs: the rectified row search (cam1 right of cam0, equal intrinsics) and, with
    # backend.disparity_sigma_px, its pairs as single stereo factors; else the general epipolar search
    row_search = bool(is_rectified(cams.left.K, cams.right.K, cams.T_right_left))
    swapped = None if row_search else swapped_pair_message(cams.left.K, cams.right.K, cams.T_right_left)
    if swapped:
        log.warn("stereo-layout", f"{path}: {swapped}")
    gaps = stream.gaps(stream.t_first, stream.t_last)
    if gaps:
        longest = max(b - a for a, b in gaps)
        log.warn("imu-gaps", f"{len(gaps)} IMU gap(s) longer than {config.tracking.max_imu_gap_ms:g} ms "
                             f"(longest {longest / 1000:.1f} ms): integration bridges them with interpolated samples")
    ev_first = min(r[0] for r in ranges if r is not None) if any(ranges) else stream.t_first
    ev_last = max(r[1] for r in ranges if r is not None) if any(ranges) else stream.t_last
    frame_us = int(round(1e6 / config.rate_hz))
    t_begin = max(stream.t_first, ev_first) + frame_us
    t_end = min(stream.t_last, max(ev_last, stream.t_first))
    if t_end <= t_begin:
        raise DataError(path, f"events ({ev_first}..{ev_last} µs) and IMU ({stream.t_first}..{stream.t_last} µs) "
                              "do not overlap by more than one frame")
    if frame_slots is not None:
        check_frame_slots(frame_slots, stream, t_begin, t_end, path)
    # OpenCV's RANSAC draws from its global generator: seed it so that a run is reproducible
    cv2.setRNGSeed(0)
    oracle = None
    if config.detector.oracle_noise_px is not None or config.detector.measure_keypoint_errors:
        # diagnostics on simulated sequences (oracle.py): perfect tracks, or the keypoints' distance to them
        from .oracle import ObservationOracle

        from .oracle import check_diagnostics

        check_diagnostics(config.detector.oracle_noise_px, config.detector.measure_keypoint_errors)
        oracle = ObservationOracle(path, cams, float(config.detector.oracle_noise_px or 0.0),
                                   seed=config.detector.keypoint_noise_seed, replace=not config.detector.measure_keypoint_errors)
    odo = StereoInertialOdometry(cams, stream, calib.imu, config, loop_closer=loop_closer, log=log, oracle=oracle)
    # the setting's detection threshold for learned detectors (restored after the run)
    old_threshold = getattr(detector, "threshold", None)
    if config.detector.threshold is not None and old_threshold is not None:
        detector.threshold = float(config.detector.threshold)
    rate_cap = config.input.rate_cap_mev_s * 1e6 if config.input.rate_cap_mev_s else None
    stop_event = stop_event or threading.Event()

    t_out: list[int] = []
    slots: list[int] = []
    caps: list[list[int]] = []  # per output: the backend's iteration caps of its frame
    cap_mismatches = [0]  # replayed frames whose backend updates did not use exactly the caps given
    T_out: list[np.ndarray] = []
    lat: list[float] = []
    tracked: list[bool] = []
    stages: dict[str, list[float]] = {s: [] for s in STAGES}
    status, complete = "ok", True
    failure_trace = None
    reader = live = feeder = None
    T_final = None
    bar = tqdm(total=round((t_end - t_begin) * 1e-6, 3), unit="s", desc=f"slam {path.stem} ({mode})", disable=not progress,
               leave=False, file=sys.stderr, bar_format="{l_bar}{bar}| {n:.2f}/{total:.2f} s [{elapsed}<{remaining}]")
    wall0 = time.perf_counter()
    shown = t_begin

    anchors: list[tuple] = []  # per output: its keyframe, its pose in that keyframe, the live loop correction

    def record(res, slot: int, tau: int, latency_us: float, pre_ms: float, mcts_ms: float, proc_ms: float):
        nonlocal shown
        if odo.rotate_outputs is not None:  # gravity became known: earlier outputs into the world frame
            # ... and anchored to a keyframe the smoother estimates: their own keyframe where the
            # initialisation's window took it in, else the oldest keyframe of that window (the
            # keyframe of the initialisation when it started alone). The alignment's gravity is off
            # by degrees (1.7-17 deg on the bench preset's starts, up to 3.5x its own sigma); the
            # final trajectory carries the smoother's correction back over the vision-only stretch,
            # as it does for later outputs
            k0, T_k0 = odo.init_anchor
            to_k0 = invert_T(T_k0)
            for i in range(len(T_out)):
                T_out[i] = odo.rotate_outputs @ T_out[i]
                if anchors[i][0] not in odo.kf_smoothed:
                    anchors[i] = (k0, to_k0 @ T_out[i], res.T_corr)
            odo.rotate_outputs = None
        t_out.append(int(tau))
        slots.append(int(slot))
        T_out.append(res.T_world_body)
        anchors.append((res.anchor_kf, res.T_kf_body, res.T_corr))
        lat.append(latency_us / 1000.0)
        tracked.append(bool(res.tracked))
        stages["preprocess"].append(pre_ms)
        stages["mcts"].append(mcts_ms)
        for k in ("detector", "matching", "refine", "tracking", "keyframe", "backend", "loop"):
            stages[k].append(float(res.timings_ms.get(k, 0.0)))
        stages["total"].append(proc_ms)
        bar.update(max(0.0, (slot - shown) * 1e-6))
        shown = max(shown, slot)

    warm_until = t_begin + (int(config.input.max_warm_up_s * 1e6) if config.input.max_warm_up_s is not None else 2**62)
    t_warm = [None if config.input.warm_up else t_begin]  # first processed frame slot (µs)

    def warm(buffers, tau: int) -> bool:
        """input.warm_up: whether frames are processed from tau on (both cameras' MCTS complete)."""
        if t_warm[0] is None and (tau >= warm_until or all(b.is_complete(tau, detector.mcts_kind, detector.mcts_params)
                                                             for b in buffers)):
            t_warm[0] = int(tau)
        return t_warm[0] is not None

    counted = [0]  # events in the buffers at the previous frame
    last_obs = [-(2**62)]  # time of the previous frame's estimate
    obs_lag: list[int] = []  # tau - time of the estimate, per frame (µs)

    def iterate(tau: int, pre_ms: float, buffers=None, forced_caps: list[int] | None = None):
        """MCTS + odometry at tau. Returns (result, time of the estimate (µs), mcts_ms, processing_ms).
        forced_caps: the backend's iteration caps for this frame's updates (a replay)."""
        n_caps = len(odo.smoother.iteration_caps)
        missing = odo.smoother.forced_caps_missing
        odo.smoother.forced_caps = None if forced_caps is None else list(forced_caps)
        t0 = time.perf_counter()
        if buffers is None:
            buffers, _ = feeder.snapshot()
        n_events = sum(b.count for b in buffers)
        batch = feeder.mcts_batch(buffers, tau)
        t1 = time.perf_counter()
        # the frame is estimated (and output) at the time its keypoints show: strictly after the
        # previous frame's, not before the first frame's slot, never after tau (frames come in time
        # order, so with no lag this is tau)
        t_obs = min(int(tau), max(observation_time(buffers, tau, feeder.observation_lag_events_per_px), t_begin, last_obs[0] + 1))
        last_obs[0] = t_obs
        obs_lag.append(int(tau) - t_obs)
        res = odo.process(t_obs, batch, detector, new_events=n_events - counted[0])
        counted[0] = n_events
        t2 = time.perf_counter()
        caps.append(odo.smoother.iteration_caps[n_caps:])
        if forced_caps is not None:
            cap_mismatches[0] += int(bool(odo.smoother.forced_caps) or odo.smoother.forced_caps_missing > missing)
            odo.smoother.forced_caps = None
        return res, t_obs, (t1 - t0) * 1e3, (t2 - t0) * 1e3

    try:
        reader = EventReader(path, chunk_events=config.input.chunk_events, prefetch=config.input.prefetch_chunks,
                             stop_event=stop_event, time_shift_us=shifts)
        feeder = EventFeeder(reader, cams, mcts_kind=detector.mcts_kind, mcts_params=detector.mcts_params,
                             rate_cap_ev_s=rate_cap,
                             observation_lag_events_per_px=config.detector.observation_lag_events_per_px,
                             noise_filter_us=(None if config.input.noise_filter_ms is None
                                              else int(round(config.input.noise_filter_ms * 1000))))
        min_dt_us = int(round(1e6 / config.max_rate_hz))
        if mode == "sync":
            finish = float(t_begin)
            tau = t_begin
            while tau <= t_end and not stop_event.is_set():
                tp = time.perf_counter()
                feeder.advance_to(tau)
                pre_ms = (time.perf_counter() - tp) * 1e3
                if not warm(feeder.buffers, tau):
                    tau += frame_us
                    continue
                res, t_obs, mcts_ms, proc_ms = iterate(tau, pre_ms)
                finish = max(finish, float(tau)) + proc_ms * 1e3  # live frame queue: wait for the previous frame
                record(res, tau, t_obs, finish - tau, pre_ms, mcts_ms, proc_ms)
                tau += frame_us
        elif mode == "async" and frame_slots is not None:
            clock = float(t_begin)
            for i, tau in enumerate(frame_slots.tolist()):
                if stop_event.is_set():
                    break
                clock = max(clock, float(tau))  # this run's clock waits for the slot the earlier run took
                tp = time.perf_counter()
                feeder.advance_to(tau)
                pre_ms = (time.perf_counter() - tp) * 1e3
                if not warm(feeder.buffers, tau):
                    continue
                res, t_obs, mcts_ms, proc_ms = iterate(tau, pre_ms, forced_caps=None if frame_caps is None else frame_caps[i])
                clock += proc_ms * 1e3
                record(res, tau, t_obs, clock - tau, pre_ms, mcts_ms, proc_ms)
        elif mode == "async":
            clock = float(t_begin)
            last_tau = None
            while clock <= t_end and not stop_event.is_set():
                tau = stream.covered_until(int(clock))
                if last_tau is not None and tau < last_tau + min_dt_us:
                    # nothing new enough: the frontend idles until the next IMU sample after the rate cap
                    nxt = int(np.searchsorted(stream.t, last_tau + min_dt_us, side="left"))
                    if nxt >= len(stream.t):
                        break
                    clock = max(clock, float(stream.t[nxt]))
                    continue
                tp = time.perf_counter()
                feeder.advance_to(tau)
                pre_ms = (time.perf_counter() - tp) * 1e3
                if not warm(feeder.buffers, tau):  # the frontend waits for the next IMU-covered slot
                    last_tau = tau
                    clock = max(clock, float(tau)) + 1.0
                    continue
                res, t_obs, mcts_ms, proc_ms = iterate(tau, pre_ms)
                clock += proc_ms * 1e3
                record(res, tau, t_obs, clock - tau, pre_ms, mcts_ms, proc_ms)
                last_tau = tau
        else:  # live
            live = LivePreprocessor(feeder, stream.covered_until, t_begin - frame_us, t_end, stop_event=stop_event)
            last_tau = None
            while not stop_event.is_set():
                if live.error is not None:
                    raise live.error
                now = live.now_us()
                if now > t_end or (live.done.is_set() and last_tau is not None and last_tau >= feeder.ingested_until):
                    break
                buffers, tau = feeder.snapshot()
                if tau < t_begin or (last_tau is not None and tau < last_tau + min_dt_us) or not warm(buffers, tau):
                    time.sleep(0.0005)
                    continue
                res, t_obs, mcts_ms, proc_ms = iterate(tau, 0.0, buffers)
                record(res, tau, t_obs, live.now_us() - tau, 0.0, mcts_ms, proc_ms)
                last_tau = tau
            if live.busy_s:
                stages["preprocess"] = [live.busy_s * 1e3 / max(len(t_out), 1)] * len(t_out)
        if stop_event.is_set():
            status, complete = "stopped: stop_event set", False
        elif T_out:
            T_final = final_poses(odo, loop_closer, T_out, anchors)
    except KeyboardInterrupt:
        status, complete = "stopped: interrupted (KeyboardInterrupt)", False
    except Exception as exc:  # the run ends cleanly and reports; input errors were raised before
        status, complete = f"failed: {type(exc).__name__}: {exc}", False
        failure_trace = traceback.format_exc()
    finally:
        if live is not None:
            live.close()
        if reader is not None:
            reader.close()
        if loop_closer is not None:
            loop_closer.close()
        if old_threshold is not None:
            detector.threshold = old_threshold
        bar.close()
    wall = time.perf_counter() - wall0
    # a run that failed before its feeder existed (bad detector, no IMU) read and dropped nothing
    events_read = int(sum(feeder.events_in)) if feeder is not None else 0
    dropped_rate_cap = int(feeder.dropped_rate_cap) if feeder is not None else 0
    dropped_noise_filter = int(feeder.dropped_noise_filter) if feeder is not None else 0
    if dropped_rate_cap:  # only events that were read can be dropped, so events_read > 0
        # one warning with the total: the cap thins bursts evenly (mcts.TimestampBuffer), so what a
        # user needs is how much of the input it cost, not a message per packet
        log.warn("rate-cap", f"the event-rate cap ({config.input.rate_cap_mev_s:g} Mev/s per camera, input.rate_cap_mev_s) "
                             f"dropped {dropped_rate_cap} of {events_read} events ({100 * dropped_rate_cap / events_read:.1f} %) "
                             f"in bursts above it")
    pose7 = matrix_to_pose7(np.stack(T_out)) if T_out else np.zeros((0, 7))
    pose7_final = matrix_to_pose7(T_final) if (complete and T_final is not None) else None
    info = {
        "events": events_read,
        "dropped_rate_cap": dropped_rate_cap,
        "dropped_noise_filter": dropped_noise_filter,  # input.noise_filter_ms
        "imu_gaps": len(gaps),
        "landmarks": len(odo.lmap),
        "loop_corrections_applied": odo.loop_corrections,
        "backend_qr_fallbacks": odo.smoother.qr_fallbacks,
        "stereo_row_search": row_search,
        "backend_stereo_factors": odo.smoother.stereo_factors,
        "pose_refits": odo.pose_refits,  # tracking.refit_on_disagreement: frames the loosened refit tracked
        # backend.time_budget_ms: updates run with fewer than max_iterations (the cap depends on the
        # machine's speed; frames.txt logs every cap, and a frame-slot replay imposes them again)
        "backend_budget_cuts": odo.smoother.budget_cuts,
        "replay_cap_mismatches": cap_mismatches[0] if frame_caps is not None else None,
        "initialized": odo.initialized,
        "t_initialized_us": odo.t_initialized,  # outputs before it are vision-only (gyro rotation, no gravity yet)
        "resolution": [cams.left.width, cams.left.height],
        "t_begin_us": int(t_begin), "t_end_us": int(t_end),
        "t_first_frame_us": t_warm[0],  # input.warm_up: the first frame processed (t_begin without it)
        # detector.observation_lag_events_per_px: how far before their frame slot outputs were placed
        "observation_lag_ms": ({"median": float(np.median(obs_lag)) / 1000, "max": float(np.max(obs_lag)) / 1000}
                               if obs_lag and config.detector.observation_lag_events_per_px > 0 else None),
        "camera_timeshift_us": shifts,
    }
    if oracle is not None and oracle.replaces:
        info["oracle"] = oracle.stats.as_dict(oracle.noise_px)
    if oracle is not None and not oracle.replaces:
        info["keypoint_errors"] = oracle.error_summary()
    # refinement.enabled: how many observations were aligned to their anchors (refine.py)
    info["refinement"] = odo.refiner.stats.as_dict() if odo.refiner is not None else None
    if failure_trace:
        info["traceback"] = failure_trace
    return SlamResult(
        t_us=np.asarray(t_out, np.int64), pose7=pose7, latency_ms=np.asarray(lat, np.float64),
        stage_ms={k: v for k, v in stages.items()}, wall_s=wall, sequence_duration_s=(t_end - t_begin) * 1e-6,
        loop_closures=int(getattr(loop_closer, "n_closures", 0)) if loop_closer is not None else 0,
        tracking_losses=odo.tracking_losses, warnings=log.as_list(), status=status, complete=complete, mode=mode,
        detector=str(getattr(detector, "name", type(detector).__name__)), config=config.name, keyframes=odo.n_keyframes,
        tracked=np.asarray(tracked, bool), info=info, pose7_final=pose7_final, slot_us=np.asarray(slots, np.int64),
        iteration_caps=caps)

