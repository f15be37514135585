"""SLAM configuration: :class:`SlamConfig` (nested dataclasses) loaded from ``conf/slam/<name>.yaml``.

Two shipped settings (paper Sec. III-C / REFERENCE section 5):

* ``realtime``: the asynchronous setting: the frontend always takes the newest state, at most
  424x240 pixels, fewer keypoints, a small backend window and a tight iteration/time budget.
* ``accurate``: synchronous processing at a fixed 50 Hz (every step processed, however long it
  takes), more keypoints and backend iterations.

A YAML file overrides any subset of the defaults below; an unknown key is an error that names it
(a typo must never silently fall back to a default).

Example:
    >>> cfg = load_config("accurate")
    >>> cfg.mode, cfg.rate_hz, cfg.backend.window_keyframes >= 3
    ('sync', 50.0, True)
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from ..errors import DataError

#: Folder of the shipped SLAM settings (``<repo>/conf/slam``).
CONFIG_DIR = Path(__file__).resolve().parents[2] / "conf" / "slam"
MODES = ("sync", "async", "live")


@dataclass
class InputConfig:
    """Preprocessing: which events reach the timestamp buffers and at what resolution.

    Attributes:
        max_width, max_height: MCTS resolution cap; larger sensors are downsampled (area binning,
            intrinsics scaled; the paper's drone goes 1280x720 -> 424x240).
        rate_cap_mev_s: per-camera event-rate cap in Mev/s (None: none); the paper caps at 35.
        min_new_events_per_px: a frame with fewer new events (both cameras, per pixel of one camera)
            than this since the previous frame is propagated with the IMU alone (static or dark
            stretch: the time surfaces have not changed).
        warm_up: the first frame waits until both cameras' MCTS are complete (the longest MCTS_Ne
            window holds its events, or the longest MCTS_dt window has passed since the first event;
            ``TimestampBuffer.is_complete``); frames before it are neither processed nor output.
            Before it the long channels show only the events since the start, and landmarks
            triangulated on such surfaces disagree with later ones by centimetres (a flying start
            of the bench preset's seed 2: 7 cm between frames 60 ms apart, which tilted the
            initialisation's gravity by 21 deg; docs/slam.md, "Warm-up").
        max_warm_up_s: the longest wait for it (s after the first frame slot; None: no limit): a
            slow or dark scene can take seconds to fill its longest window (3 s in a textureless
            room), and then starts on incomplete surfaces rather than lose its first seconds.
        noise_filter_ms: background-activity filter (``aerovis_slam.noise_filter``): an event reaches
            the buffers only when one of its 8 sensor neighbours fired at most this long before it
            (ms; None: off). Leak and shot noise fire alone; in a textureless room they fill the
            MCTS_Ne windows with lit dots that the detector takes for keypoints (docs/slam.md).
        chunk_events: events per read from the file (the prefetch thread's unit).
        prefetch_chunks: chunks read ahead per camera (bounded memory).
    """

    max_width: int = 424
    max_height: int = 240
    rate_cap_mev_s: float | None = 35.0
    min_new_events_per_px: float = 0.005
    warm_up: bool = True
    max_warm_up_s: float | None = 0.5
    noise_filter_ms: float | None = None
    chunk_events: int = 200_000
    prefetch_chunks: int = 4


@dataclass
class DetectorConfig:
    """Keypoint budget and the classical fallback.

    Attributes:
        top_k: keypoints per image (None: the detector's own default).
        threshold: detection threshold of learned detectors (None: the bundle's). Event scenes with
            large textureless areas give few keypoints above the bundle's 0.01; the runtime then
            lowers it and relies on ``top_k`` and matching to keep the good ones.
        classical: a classical detector kind (``orb``, ``sift``, ``gftt_brief``), validated but not
            read by ``aerovis-slam run``: ``--detector KIND`` chooses a classical detector there, and
            without it (or ``--model``) the run takes the shipped SuperLitE bundle.
        keypoint_noise_px: a sensitivity probe, 0 for every real use: uniform noise in
            ``[-keypoint_noise_px, +keypoint_noise_px]`` px added to each keypoint position after
            detection (descriptors unchanged), drawn from a generator seeded with
            ``keypoint_noise_seed``. A sync run is deterministic but chaotic (a fraction of a pixel
            decides which frames become keyframes and when initialisation is accepted), so one run
            is one draw; ``aerovis-slam bench --repeats`` uses this to measure the spread.
        keypoint_noise_seed: seed of that noise (and of ``oracle_noise_px``'s).
        oracle_noise_px: a diagnostic, None for every real use: on a sequence written by
            ``aerovis-sim``, every landmark observation is replaced by the true projection of one
            scene point per landmark plus Gaussian noise of this many px per axis
            (:mod:`~aerovis_slam.slam.oracle`: what a detector with perfect tracks would give).
        measure_keypoint_errors: a diagnostic on ``aerovis-sim`` sequences: every landmark observation
            (after refinement) is compared with the true projection of its landmark's scene point,
            fixed at the first sighting as the oracle fixes it, and the distances by track age go to
            ``metrics.json`` (``pipeline_info.keypoint_errors``); positions are not changed.
        observation_lag_events_per_px: the keypoints of the time surfaces at ``tau`` are taken to
            show the scene at the time of the N-th newest event before ``tau`` (N = this x the
            buffer's pixels; the mean over both cameras, at most :data:`~aerovis_slam.slam.preprocessing.MAX_OBSERVATION_LAG_US`
            behind), and the frame is estimated and output at that time. 0: at ``tau``. An
            edge's keypoint sits on the trail its events leave, not at its newest event.
            ``aerovis-eval lag --data bench`` (intensity-frame corners moved with depth and the
            ground truth) puts SuperLitE's keypoints on MCTS_Ne 0.018-0.046 events per pixel
            (median 0.026; 0.1-12 ms) and ORB's 0.009-0.043 (median 0.032; 0.1-18 ms) behind
            ``tau`` on the seven sequences. The measured effect on SLAM is in docs/slam.md: with
            the initialisation's bundle adjustment, 0.03 lowered the four-run sync means of
            SuperLitE on five bench sequences of seven and of ORB on six (on by default since).
        min_event_support: a keypoint is kept only where at least this many of the (2r+1)^2 = 25
            pixels around it had an event within the MCTS window ``support_window``
            (:func:`~aerovis_slam.slam.frontend.event_support`; 0: every keypoint). Keypoints on
            lone noise events, which the long windows of a sparse scene hold in place for a second
            or more, then never reach the map. Off by default: 3 pixels in window 1 rescued the
            bench preset's noisiest sequence (seed 1 slider_wall, two thirds of its events noise:
            22.9 -> 5.0 % ATE) and seed 1 shake_rapid (6.5 -> 0.9 %), but broke seed 2
            spin_hdr_window (2.9 -> 18.9 %; its first visual-inertial alignment fit |g| = 27.7
            m/s²) and left seed 0's four-run means within their spread (docs/slam.md, "Keypoints
            on noise"); for a sparse, noisy recording try ``min_event_support: 3, support_window: 1``.
        support_window: that window's index ``k`` (0: the shortest, 0.03 events per pixel for the
            default MCTS_Ne, which in a busy scene lights too few pixels of a real edge: window 0
            raised handheld_loop's ATE 2.5-fold on seed 0; 1: 0.1 events per pixel; for MCTS_dt's windows 2 = 10 ms).
    """

    top_k: int | None = 300
    threshold: float | None = 0.001
    classical: str = "orb"
    keypoint_noise_px: float = 0.0
    keypoint_noise_seed: int = 0
    oracle_noise_px: float | None = None
    measure_keypoint_errors: bool = False
    observation_lag_events_per_px: float = 0.03
    min_event_support: int = 0
    support_window: int = 0


@dataclass
class MatchingConfig:
    """Stereo, map and temporal matching thresholds (pixels at the MCTS resolution).

    Attributes:
        min_similarity: minimum cosine similarity of float/int8 descriptors for a match.
        min_similarity_binary: minimum ``1 - hamming / bits`` of binary (ORB) descriptors.
        ratio: second-best / best similarity gap: a match needs ``best - second >= ratio * (1 - best)``
            (0 disables; a Lowe-like test expressed on similarities).
        stereo_epipolar_px: maximum distance of a right keypoint to the left keypoint's epipolar line
            (unrectified pairs, matched by descriptors).
        stereo_min_ncc: minimum patch correlation of the row search in rectified pairs.
        min_disparity_px: left-right disparity below this gives no landmark (depth too uncertain).
        max_depth_m: landmarks farther than this are not created.
        window_px: radius of the projection window for map matching at the nominal prediction.
        window_px_lost: radius after a tracking failure (the IMU-only prediction is worse).
        max_reproj_px: a landmark observation with a larger reprojection error after tracking is dropped.
        max_landmark_age_s: landmarks older than this are no longer matched (None: no limit). Event
            keypoints drift along edges as a track ages (measured on the simulator: median error
            1.7 px under 50 ms, 2.6 px at 0.4-1 s, 5 px beyond 1 s), and old, drifted tracks bias the
            motion; fresh stereo landmarks replace them.
        edge_max_ratio: observations on edges get a noise variance along the edge up to this many
            times the variance across it (the structure tensor's anisotropy; 1 = isotropic noise),
            see :func:`~aerovis_slam.slam.frontend.edge_shapes`.
        update_descriptors: a landmark's descriptor follows its newest keyframe observation (else it
            keeps the one it was created with, which cannot drift onto a neighbouring feature).
    """

    min_similarity: float = 0.75
    min_similarity_binary: float = 0.7
    ratio: float = 0.0
    stereo_epipolar_px: float = 1.5
    stereo_min_ncc: float = 0.75
    min_disparity_px: float = 1.0
    max_depth_m: float = 30.0
    window_px: float = 10.0
    window_px_lost: float = 30.0
    max_reproj_px: float = 3.0
    max_landmark_age_s: float | None = None
    edge_max_ratio: float = 25.0
    update_descriptors: bool = True


@dataclass
class RefinementConfig:
    """Track refinement: landmark observations aligned to the landmark's anchor view by Lucas-Kanade
    (:mod:`aerovis_slam.slam.refine`; pixels at the MCTS resolution).

    Attributes:
        enabled: refine (else every observation stays where the detector put it).
        window_px: side of the alignment window (odd).
        max_shift_px: an alignment farther than this from the detection is rejected.
        max_fb_px: an alignment whose way back misses the anchor by more than this is rejected.
        max_anchor_age_s: anchors older than this are replaced by the current observation.
        windows: the alignment image is the mean of this many of the MCTS's shortest windows, both
            polarities (None: every channel). Short windows hold short trails, whose shape depends
            less on the direction and speed of the motion.
    """

    enabled: bool = True
    window_px: int = 13
    max_shift_px: float = 6.0
    max_fb_px: float = 2.0
    max_anchor_age_s: float = 5.0
    windows: int | None = None


@dataclass
class RansacConfig:
    """Outlier rejection.

    Attributes:
        pnp_reproj_px: 3D-2D RANSAC inlier threshold.
        pnp_iterations, confidence: RANSAC effort.
        min_inliers: fewer 3D-2D inliers means the frame is not tracked visually.
        rotation_threshold_deg: angular inlier threshold of the rotation-only 2D-2D model.
        rotation_min_inliers: inliers for an accepted rotation-only estimate.
    """

    pnp_reproj_px: float = 2.5
    pnp_iterations: int = 100
    confidence: float = 0.999
    min_inliers: int = 12
    rotation_threshold_deg: float = 0.5
    rotation_min_inliers: int = 15


@dataclass
class KeyframeConfig:
    """Keyframe decision (OKVIS2: a new keyframe when the matched-area overlap drops below ~0.6).

    Attributes:
        overlap_threshold: new keyframe when the best overlap with a window keyframe is below this.
        cell_px: grid cell of the keypoint-area measure.
        min_interval_s, max_interval_s: keyframe spacing bounds (seconds of sensor time).
        min_tracked: new keyframe (with new stereo landmarks) when fewer landmarks are tracked.
    """

    overlap_threshold: float = 0.6
    cell_px: int = 16
    min_interval_s: float = 0.1
    max_interval_s: float = 0.5
    min_tracked: int = 40


@dataclass
class BackendConfig:
    """gtsam fixed-lag keyframe smoother and per-frame tracking optimisation.

    Attributes:
        window_keyframes: keyframes kept in the smoother (older ones are marginalised).
        max_iterations: Levenberg-Marquardt iterations per keyframe update.
        time_budget_ms: the iteration count is lowered so that an update fits this budget
            (from the measured time per iteration); None: always ``max_iterations`` (deterministic).
        tracking_iterations: LM iterations of the per-frame (motion-only) optimisation.
        tracking_max_observations: observations it uses (spread over the image; all are checked).
        pixel_sigma: reprojection noise (px, 1 sigma). 1.5: event keypoints re-detected on time
            surfaces scatter by about a pixel around the true projection, with offsets that persist
            along a landmark's track, which i.i.d. 1 px does not cover (docs/slam.md, "Pixel noise").
        robust: ``huber`` or ``cauchy`` loss on reprojection errors; ``robust_k`` its threshold in sigmas.
        prior_rollpitch_deg, prior_velocity_m_s: initial-state uncertainty after initialisation.
        prior_acc_bias, prior_gyro_bias: initial bias uncertainty (m/s^2, rad/s).
        max_landmarks: landmarks in the local map used for matching (the oldest are dropped first).
        disparity_sigma_px: a new landmark's left observation and its right position from the
            rectified row search (the left keypoint shifted by the measured disparity) share the
            keypoint's error; only the disparity adds its own. With a value (px, 1 sigma) the pair
            enters as one stereo factor with that correlation; None: two independent projection
            factors, which weigh the disparity as if its error were ``sqrt(2) * pixel_sigma``
            (docs/slam.md, "Stereo pairs"). 0.6: the row search's measured disparity error, rms 0.33,
            0.37 and 0.70 px on slider_wall, spin_hdr_window and handheld_office (docs/slam.md,
            "The stereo search's sub-pixel error").
        track_drift_px2_per_s: a landmark observation's variance grows with the age of its track,
            ``pixel_sigma^2 + track_drift_px2_per_s * age_s`` (times its edge shape): keypoints
            wander from their first sighting's scene point like a random walk (docs/slam.md,
            "Track refinement": median 0.7 px in the first 50 ms, 1.9 px after a second on
            handheld_loop), so old sightings carry less. None: every sighting ``pixel_sigma``.
        leaving_observations: what happens to a leaving keyframe's observations of landmarks that
            stay in the window. ``marginalise``: gtsam marginalises them with the keyframe, so the
            window keeps what they said about those landmarks (a landmark's depth from the longer
            baseline of its older sightings). ``drop``: they are removed first, as OKVIS does, which
            keeps the marginal prior sparse but leaves a landmark's depth to the sightings within
            the window, where each new keyframe's stereo depth moves it (docs/slam.md, "Leaving
            keyframes' observations").
    """

    window_keyframes: int = 8
    max_iterations: int = 6
    time_budget_ms: float | None = 60.0
    tracking_iterations: int = 4
    tracking_max_observations: int = 120
    pixel_sigma: float = 1.5
    robust: str = "huber"
    robust_k: float = 1.345
    prior_rollpitch_deg: float = 2.0
    prior_velocity_m_s: float = 0.1
    prior_acc_bias: float = 0.1
    prior_gyro_bias: float = 0.01
    max_landmarks: int = 800
    disparity_sigma_px: float | None = 0.6
    track_drift_px2_per_s: float | None = None
    leaving_observations: str = "marginalise"


@dataclass
class InitConfig:
    """Initialisation of gravity, velocity and biases (stereo gives the scale).

    Attributes:
        window_s: vision-only tracking this long before the visual-inertial alignment. Gravity is seen
            through ``g t²/2`` against the visual positions' noise: with 1 cm of noise a 0.3 s window
            leaves about 3.5 deg of tilt and 0.09 m/s of velocity error, 1 s about 0.2 deg and 0.02 m/s
            (tests/test_slam_core.py). But the vision-only tracking before it drifts (keypoints lag
            the motion as it starts), and on the bench preset 0.3 s gave the lower ATE (SuperLitE,
            sync: slider_wall 2.02 % vs 2.15 %, handheld_office 1.46 % vs 2.71 % at 0.8 s); the
            smoother refines gravity and velocity afterwards.
        min_frames: tracked frames needed for the alignment.
        max_tilt_sigma_deg, max_velocity_sigma: an alignment is accepted only when its own
            least-squares uncertainty (:class:`~aerovis_slam.slam.imu.Alignment`) is below these;
            the smoother starts with priors no tighter than it.
        timeout_s: without an accepted estimate by then (s after the first frame), initialise
            anyway, with gravity from the velocity change over the frames tracked so far (its own
            tilt sigma as the roll and pitch prior), or where tracking does not cover that, from the
            accelerometer's mean over the first 0.2 s (a static start: 5 deg, 10 in the
            initialisation's window), with a warning.
        gravity: how gravity is found before the smoother starts. ``alignment``: the visual-inertial
            alignment over ``window_s`` of tracking (:func:`~aerovis_slam.slam.imu.align_visual_inertial`),
            accepted by its own sigmas. ``velocity_change``: once tracking spans ``velocity_change_s``,
            the velocity change between its ends against the rotated specific force
            (:func:`~aerovis_slam.slam.imu.gravity_from_velocity_change`, accepted when its norm is
            within 1 m/s² of 9.81 and its sigma below ``max_tilt_sigma_deg``); the smoother starts
            with that estimate's own tilt sigma as its roll and pitch prior (at least
            ``backend.prior_rollpitch_deg``) and the fallback's 0.5 m/s velocity prior, and the
            initialisation's window re-estimates velocities and gravity.
        velocity_change_s: tracked span before a ``velocity_change`` initialisation.
        min_position_inliers: before initialisation a frame counts as tracked with this many
            3D-2D inliers. Its rotation comes from the gyroscope, so only the position (3 unknowns, 2
            equations per observation) is fitted, and fewer inliers suffice than for the full 6-DoF
            pose (``ransac.min_inliers``). At 240x180 the first keyframe holds only ~10 stereo
            landmarks: with 12 required, handheld_office (bench preset) propagated its first 14 frames
            with a zero velocity, and the alignment started from them (SuperLitE sync 3.92 % -> 2.45 %
            with 6).
        velocity_change_check: when an alignment is accepted after tracking has spanned enough for
            the velocity-change estimate (about 0.8 s), the start takes that estimate's gravity
            where its tilt sigma is the smaller (the alignment's sigma is a lower bound: on
            handheld_office, bench preset, alignments accepted at 2-3 deg sigma were 3-5 deg off;
            docs/slam.md). Alignments accepted earlier are unaffected. On in ``accurate``; off in
            ``realtime`` (not measured in async).
        bundle_adjustment: start the smoother with the keyframes tracked before the
            initialisation (up to ``backend.window_keyframes``, not the first frame's: their IMU
            factors and observations, VINS-Mono's visual-inertial bundle adjustment after the
            alignment; also after the static-start fallback) instead of the newest frame alone, so
            that gravity, velocity and the vision-only poses are re-estimated jointly at once rather
            than over the following second.
    """

    window_s: float = 0.3
    min_frames: int = 8
    timeout_s: float = 1.5
    gravity: str = "alignment"
    velocity_change_s: float = 1.0
    max_tilt_sigma_deg: float = 6.0
    max_velocity_sigma: float = 0.3
    min_position_inliers: int = 6
    velocity_change_check: bool = False
    bundle_adjustment: bool = True


@dataclass
class TrackingConfig:
    """Failure handling.

    Attributes:
        loss_frames: consecutive visually untracked frames that count as a tracking loss.
        loss_time_s: or this long without visual tracking.
        max_imu_gap_ms: IMU gaps longer than this are reported (integration bridges them).
        recovery_velocity_sigma: at a tracking loss the backend restarts at the IMU-propagated pose
            with the median velocity of the last visually tracked frames, this uncertain (m/s, 1
            sigma): the smoother's own velocity is what drifted while vision was missing.
        recovery_keyframes: keyframes after a restart whose per-frame tracking holds the keyframe
            state loosely (its velocity is not converged yet).
        refit_on_disagreement: when RANSAC finds ``ransac.min_inliers`` 3D-2D inliers but the
            motion-only fit, which holds the last keyframe's state tightly, keeps fewer, fit again
            holding it as loosely as after a restart and take that fit when it keeps enough
            (:func:`~aerovis_slam.slam.backend.track_frame_or_refit`; counted as ``pose_refits``).
            For async processing on a slow CPU (``realtime``): at 4-8 poses/s a keyframe velocity
            0.5 m/s off (handheld_office, bench preset) rejected consistent observations frame after
            frame until tracking was lost. Off in ``accurate``: at 50 Hz the IMU prediction is
            rarely the one that is wrong (docs/slam.md, "Refit on disagreement").
        zero_velocity: a frame without new events (``input.min_new_events_per_px``) whose IMU samples
            fit a body at rest (:func:`~aerovis_slam.slam.imu.standstill_chi2` at most ``still_chi2``)
            while the estimated speed is below ``still_max_speed_m_s`` is a standstill: one keyframe
            holds the velocity at zero (sigma ``still_velocity_sigma_m_s``), then the pose is held and
            no time at rest counts towards a tracking loss. A camera put down on a quiet sensor sends no
            events, and without this the map was dropped after ``loss_time_s`` (warning ``still``).
        still_window_s: the IMU samples tested span this long before the frame (at least back to the
            previous frame): longer windows average more noise away (a DAVIS IMU's mean over 20 ms is
            0.3 m/s² and 1.3 deg/s uncertain per axis, over 0.1 s 0.14 m/s² and 0.6 deg/s).
        still_chi2: the test's threshold (chi-square, 6 degrees of freedom: 22.5 is its 99.9 % point).
        still_gyro_floor_rad_s, still_acc_floor_m_s2: the test's allowance for errors of the bias and
            attitude estimates (1 sigma per axis; 0.2 m/s² is 1.2 deg of tilt), added to the white noise
            of the window's mean.
        still_max_speed_m_s: the speed gate: a constant velocity in the dark fits the IMU test as well.
            Loose, since the estimate itself drifts while a halting camera sends too few events to
            track (0.27 m/s after 0.15 s on the test flight of ``test_a_camera_at_rest_keeps_its_map``).
        still_velocity_sigma_m_s: the zero-velocity prior's sigma (m/s).
    """

    loss_frames: int = 10
    loss_time_s: float = 0.5
    max_imu_gap_ms: float = 20.0
    recovery_velocity_sigma: float = 0.5
    recovery_keyframes: int = 3
    refit_on_disagreement: bool = False
    zero_velocity: bool = True
    still_window_s: float = 0.1
    still_chi2: float = 22.5
    still_gyro_floor_rad_s: float = 0.003
    still_acc_floor_m_s2: float = 0.2
    still_max_speed_m_s: float = 0.5
    still_velocity_sigma_m_s: float = 0.01


@dataclass
class SlamConfig:
    """All settings of one SLAM run.

    Attributes:
        name: setting name (``realtime``, ``accurate`` or the file stem).
        mode: the mode this setting is meant for (``sync`` | ``async`` | ``live``); the caller may override.
        rate_hz: sync-mode processing rate (Hz). In every mode the first frame slot also lies one
            ``1 / rate_hz`` after the data start, and the shortest frame interval before
            initialisation is the smaller of ``1 / rate_hz`` and ``1 / max_rate_hz``.
        max_rate_hz: async/live cap: the frontend waits instead of re-processing nearly the same state.
        blas_threads: threads of numpy's BLAS (OpenBLAS) while the run lasts (None: the library's own,
            one per core). 1 by default: the detector's ONNX Runtime pool takes every core, and the
            runtime's matrix products are small (descriptor similarities of a few hundred
            keypoints). After a multi-threaded product OpenBLAS's workers busy-wait for more work
            and take cores from the next inference: on the 2-core box a stereo inference at 424x240
            took 66 instead of 33 ms after 30 ms of products, and an async drone8_lit run
            processed 7.5 poses/s with OpenBLAS's 2 threads and 11.6 with 1 (docs/slam.md).
        input, detector, matching, refinement, ransac, keyframes, backend, init, tracking: the sections above.
        loop: overrides of the loop closer's settings (:data:`aerovis_slam.slam.loop.DEFAULT_CONFIG`,
            e.g. ``min_inliers``, ``drift_fraction``); empty: its defaults. A plain mapping rather than a
            dataclass so the loop closer stays the one place that names and documents them.
    """

    name: str = "default"
    mode: str = "sync"
    rate_hz: float = 50.0
    max_rate_hz: float = 100.0
    blas_threads: int | None = 1
    input: InputConfig = field(default_factory=InputConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    refinement: RefinementConfig = field(default_factory=RefinementConfig)
    ransac: RansacConfig = field(default_factory=RansacConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    init: InitConfig = field(default_factory=InitConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    loop: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """Plain nested dict (for metrics.json and reproducibility)."""
        return dataclasses.asdict(self)


def _build(cls, data: Any, path, prefix: str):
    """Instantiate dataclass ``cls`` from a mapping, recursing into nested dataclass fields."""
    if not isinstance(data, dict):
        raise DataError(path, f"{prefix or 'the file'} must be a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = [k for k in data if k not in fields]
    if unknown:
        where = f"{prefix}." if prefix else ""
        raise DataError(path, f"unknown key(s) {[where + str(k) for k in unknown]}; known keys of "
                              f"{prefix or 'the top level'}: {sorted(fields)}")
    kwargs = {}
    for k, v in data.items():
        default = getattr(cls(), k)
        key = f"{prefix}.{k}" if prefix else k
        if dataclasses.is_dataclass(default):
            kwargs[k] = _build(type(default), v, path, key)
        else:
            kwargs[k] = _coerce(v, default, path, key)
    return cls(**kwargs)


def _coerce(value: Any, default: Any, path, key: str):
    """Check a scalar against the default's type (int/float/str; None allowed for optional fields)."""
    if value is None:
        return None
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise DataError(path, f"{key} must be true or false, got {value!r}")
        return value
    if isinstance(default, (int, float)) or default is None:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            if default is None and isinstance(value, str):
                return value
            raise DataError(path, f"{key} must be a number, got {value!r}")
        return type(default)(value) if default is not None else value
    if isinstance(default, str):
        if not isinstance(value, str):
            raise DataError(path, f"{key} must be a string, got {value!r}")
        return value
    return value


def _validate(cfg: SlamConfig, path) -> None:
    if cfg.mode not in MODES:
        raise DataError(path, f"mode must be one of {MODES}, got {cfg.mode!r}")
    if cfg.rate_hz <= 0 or cfg.max_rate_hz <= 0:
        raise DataError(path, f"rate_hz and max_rate_hz must be positive (got {cfg.rate_hz}, {cfg.max_rate_hz})")
    if cfg.blas_threads is not None and not (isinstance(cfg.blas_threads, int) and cfg.blas_threads >= 1):
        raise DataError(path, f"blas_threads must be a whole number >= 1 or null (the BLAS library's own), got {cfg.blas_threads!r}")
    if cfg.backend.robust not in ("huber", "cauchy"):
        raise DataError(path, f"backend.robust must be 'huber' or 'cauchy', got {cfg.backend.robust!r}")
    if cfg.backend.leaving_observations not in ("marginalise", "drop"):
        raise DataError(path, "backend.leaving_observations must be 'marginalise' or 'drop', "
                              f"got {cfg.backend.leaving_observations!r}")
    rc = cfg.refinement
    if rc.window_px < 3 or rc.window_px % 2 == 0:
        raise DataError(path, f"refinement.window_px must be an odd number >= 3, got {rc.window_px}")
    for key in ("max_shift_px", "max_fb_px", "max_anchor_age_s"):
        if not getattr(rc, key) > 0:
            raise DataError(path, f"refinement.{key} must be positive, got {getattr(rc, key)}")
    if rc.windows is not None and not (isinstance(rc.windows, int) and rc.windows >= 1):
        raise DataError(path, f"refinement.windows must be a whole number >= 1 (the shortest MCTS windows) or null (all), got {rc.windows!r}")
    if cfg.backend.window_keyframes < 2:
        raise DataError(path, f"backend.window_keyframes must be at least 2, got {cfg.backend.window_keyframes}")
    if cfg.input.max_warm_up_s is not None and not cfg.input.max_warm_up_s >= 0:
        raise DataError(path, f"input.max_warm_up_s must be >= 0 s or null (no limit), got {cfg.input.max_warm_up_s}")
    if cfg.input.max_width < 16 or cfg.input.max_height < 16:
        raise DataError(path, f"input.max_width/max_height must be at least 16, got {cfg.input.max_width}x{cfg.input.max_height}")
    from ..classical import DETECTORS

    if cfg.init.gravity not in ("alignment", "velocity_change"):
        raise DataError(path, f"init.gravity must be 'alignment' or 'velocity_change', got {cfg.init.gravity!r}")
    if cfg.backend.disparity_sigma_px is not None and not cfg.backend.disparity_sigma_px > 0:
        raise DataError(path, f"backend.disparity_sigma_px must be positive (px) or null (off), got {cfg.backend.disparity_sigma_px}")
    drift = cfg.backend.track_drift_px2_per_s
    if drift is not None and not drift >= 0:
        raise DataError(path, f"backend.track_drift_px2_per_s must be >= 0 (px^2 per second of track age) or null (off), got {drift}")
    if cfg.input.noise_filter_ms is not None and not 0 < cfg.input.noise_filter_ms <= 1000:
        raise DataError(path, f"input.noise_filter_ms must be in (0, 1000] ms or null (off), got {cfg.input.noise_filter_ms}")
    if not cfg.init.velocity_change_s >= 0.8:
        raise DataError(path, f"init.velocity_change_s must be at least 0.8 s (two 0.3 s velocity fits 0.5 s apart), "
                              f"got {cfg.init.velocity_change_s}")
    if cfg.init.min_position_inliers < 3:
        raise DataError(path, f"init.min_position_inliers must be at least 3 (a position fit with outlier checks), "
                              f"got {cfg.init.min_position_inliers}")
    if cfg.detector.keypoint_noise_px < 0:
        raise DataError(path, f"detector.keypoint_noise_px must be >= 0, got {cfg.detector.keypoint_noise_px}")
    if not 0 <= cfg.detector.min_event_support <= 25:
        raise DataError(path, f"detector.min_event_support must be in [0, 25] pixels (of the 5x5 around a keypoint), "
                              f"got {cfg.detector.min_event_support}")
    if cfg.detector.support_window < 0:
        raise DataError(path, f"detector.support_window must be a window index >= 0, got {cfg.detector.support_window}")
    if not 0.0 <= cfg.detector.observation_lag_events_per_px <= 10.0:
        raise DataError(path, f"detector.observation_lag_events_per_px must be in [0, 10] events per pixel, "
                              f"got {cfg.detector.observation_lag_events_per_px}")
    if cfg.detector.classical not in DETECTORS:
        raise DataError(path, f"detector.classical must be one of {sorted(DETECTORS)}, got {cfg.detector.classical!r}")
    _validate_loop(cfg, path)


def _validate_loop(cfg: SlamConfig, path) -> None:
    """The ``loop`` section, checked by the loop closer's own check (and normalised: whole numbers as int)."""
    from .loop import check_loop_overrides

    try:
        cfg.loop = check_loop_overrides(cfg.loop)
    except ValueError as exc:
        raise DataError(path, str(exc)) from None


def config_path(name_or_path: str | os.PathLike) -> Path:
    """Resolve a setting name (``realtime``) or a YAML path."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        if not p.is_file():
            raise DataError(p, "SLAM config file not found")
        return p
    cand = CONFIG_DIR / f"{name_or_path}.yaml"
    if not cand.is_file():
        known = sorted(q.stem for q in CONFIG_DIR.glob("*.yaml")) if CONFIG_DIR.is_dir() else []
        raise DataError(cand, f"unknown SLAM config {str(name_or_path)!r}; shipped: {known}, or give a YAML file path")
    return cand


def load_config(name_or_path: str | os.PathLike = "realtime") -> SlamConfig:
    """Load ``realtime`` | ``accurate`` (``conf/slam``) or a YAML file as a :class:`SlamConfig`.

    Keys missing from the file keep the dataclass defaults; ``name`` defaults to the file stem.

    Raises:
        DataError: unreadable file, unknown key (named with its section), wrong type or bad value.
    """
    path = config_path(name_or_path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise DataError(path, f"not a readable YAML file ({exc})") from None
    data = dict(data) if isinstance(data, dict) else data
    if isinstance(data, dict):
        data.setdefault("name", path.stem)
    cfg = _build(SlamConfig, data, path, "")
    _validate(cfg, path)
    return cfg
