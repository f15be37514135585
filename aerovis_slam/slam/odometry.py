"""One frontend iteration after another: stereo event-inertial odometry with loop-closure corrections.

:class:`StereoInertialOdometry` turns a stereo MCTS batch at time ``tau`` into a pose (paper Fig. 1,
OKVIS2 frontend + backend):

1. keypoints of both cameras from one detector call on the stereo batch;
2. IMU propagation from the last keyframe's estimate to ``tau`` (gtsam preintegration);
3. matching to map landmarks projected with the propagated pose (window search);
4. 3D-2D RANSAC (P3P + refinement) in the camera with more matches, the other camera checked
   against its pose; when too few 3D-2D inliers remain, 2D-2D matching to the last keyframe with
   the rotation-only model (pure rotation) constrains the rotation;
5. motion-only optimisation (IMU factor + fixed landmarks) for the frame's state;
6. keyframe decision by matched-area overlap; at a keyframe: new landmarks by left-right epipolar
   matching and triangulation, and a fixed-lag smoother update (:mod:`.backend`);
7. loop closure (optional): each keyframe goes to the ``LoopCloser``, whose place recognition and
   PnP verification run here, at the keyframe; its pose-graph optimisation runs in another thread,
   and the corrections it publishes are applied to the output pose without waiting.

Initialisation: vision-only stereo tracking (metric: stereo gives the scale) for ``init.window_s``,
then the visual-inertial alignment (:func:`~aerovis_slam.slam.imu.align_visual_inertial`) gives
gravity, velocities and the gyroscope bias, and the smoother starts with the keyframes tracked so far
(their IMU factors and observations: a visual-inertial bundle adjustment, as in VINS-Mono, that
re-estimates gravity, velocities and those poses together); without an accepted alignment by
``init.timeout_s`` gravity comes from the velocity change over the frames tracked so far, or where
tracking does not cover that, from the accelerometer alone (a static start; both with a warning).

Frames: the world W is gravity-aligned (z up) with its origin and yaw at the first body pose; the
body B is the IMU frame; outputs are ``T_world_body``. Before initialisation, poses live in the
frame of the first body pose V and are rotated into W when gravity is known.

Failures (warned, counted): a frame without new events (static or dark stretch) or without enough
inliers is propagated with the IMU; after
``tracking.loss_frames`` such frames (or ``loss_time_s``) the map is dropped (a tracking loss) and
re-initialised from the next stereo frame with landmarks, continuing from the IMU-propagated state.
"""

from __future__ import annotations

import time
from collections import Counter, deque
from dataclasses import dataclass, field

import cv2
import gtsam
import numpy as np

from ..calib import ImuNoise
from ..geometry import invert_T, transform_points
from ..keypoints import Keypoints, match_keypoints
from .backend import (TRACKING_KF_SIGMAS, KeyframeSmoother, NavEstimate, Observations, loose_kf_sigmas, track_age_shapes,
                      track_frame_or_refit)
from .cameras import StereoCameras
from .config import SlamConfig
from .frontend import (KeyframeSelector, LandmarkMap, edge_shapes, match_to_map, spread_subset, structure_tensor,
                       supported_keypoints)
from .imu import (GRAVITY, ImuStream, align_visual_inertial, gravity_from_velocity_change, gravity_rotation_from_acc,
                  new_preintegration, preintegration_params, standstill_chi2)
from .ransac import bearings, pnp_ransac, position_given_rotation, relative_pose_ransac, reprojection_error, rotation_ransac
from .refine import TrackRefiner, alignment_images
from .stereo import match_stereo, triangulate, uses_row_search


def perturb_keypoints(kp: Keypoints, rng: np.random.Generator, noise_px: float, width: int, height: int) -> Keypoints:
    """``kp`` with uniform noise in ``[-noise_px, noise_px]`` added to each coordinate, kept inside the
    ``width`` x ``height`` image; scores and descriptors unchanged. The sensitivity probe of
    :attr:`~aerovis_slam.slam.config.DetectorConfig.keypoint_noise_px`."""
    xy = kp.xy + rng.uniform(-noise_px, noise_px, kp.xy.shape)
    return Keypoints(np.clip(xy, 0, [width - 1, height - 1]).astype(np.float32), kp.scores, kp.descriptors)


def _plausible_gravity(norm_m_s2: float) -> bool:
    """An estimated gravity's norm is within 1 m/s² of the true one: the fit explains the motion
    (the check on every gravity estimate of the initialisation)."""
    return abs(norm_m_s2 - GRAVITY) < 1.0


def vision_velocity(p_new: np.ndarray, p_old: np.ndarray, v_old: np.ndarray, dt_s: float, min_dt_s: float) -> np.ndarray:
    """Velocity before the initialisation (m/s, in the positions' frame: the vision frame) from two
    tracked positions ``dt_s`` apart,
    averaged half and half with the previous estimate ``v_old`` (only the next frame's prediction
    uses it).

    Positions closer in time than ``min_dt_s`` keep ``v_old``: with the observation lag two frames
    can be estimated 1 µs apart (the second's time is clamped to just after the first's), and a
    few millimetres of position noise over 1 µs are kilometres per second (an async ORB run on
    ``drone8_lit`` left at 11 km/s before its initialisation and ended at 934 m ATE).

    Example:
        >>> v = vision_velocity(np.array([0.02, 0, 0]), np.zeros(3), np.array([1.0, 0, 0]), 1e-6, 0.005)
        >>> v.tolist()
        [1.0, 0.0, 0.0]
        >>> vision_velocity(np.array([0.02, 0, 0]), np.zeros(3), np.zeros(3), 0.02, 0.005).tolist()  # 1 m/s, halved
        [0.5, 0.0, 0.0]
    """
    v_old = np.asarray(v_old, np.float64)
    if not dt_s >= min_dt_s:
        return v_old.copy()
    return 0.5 * (np.asarray(p_new, np.float64) - np.asarray(p_old, np.float64)) / dt_s + 0.5 * v_old


@dataclass
class FrameResult:
    """Output of one iteration.

    Attributes:
        t_us: the frame time ``tau``. T_world_body: (4, 4) output pose (loop-corrected).
        tracked: visually tracked (else IMU-only). keyframe: a keyframe was created.
        inliers: 3D-2D inliers (both cameras). timings_ms: per-stage durations.
        anchor_kf: the keyframe the pose was estimated against (-1 before the initialisation).
        T_kf_body: (4, 4) the pose in that keyframe's body frame (None without an anchor).
        T_corr: (4, 4) the loop correction applied to the output (world <- odometry world).
        The last three let :func:`~aerovis_slam.slam.trajectory.final_trajectory` move the output
        with its keyframe when the smoother or the pose graph moves the keyframe later.
    """

    t_us: int
    T_world_body: np.ndarray
    tracked: bool
    keyframe: bool
    inliers: int
    timings_ms: dict[str, float] = field(default_factory=dict)
    anchor_kf: int = -1
    T_kf_body: np.ndarray | None = None
    T_corr: np.ndarray | None = None


# velocity prior (m/s) of a start whose velocity no alignment estimated (the static-start
# fallback; the oldest keyframe of the initialisation's window when it precedes the aligned stretch)
UNALIGNED_VELOCITY_SIGMA = 0.5


class WarningLog:
    """Warnings by kind: the first message of each kind is kept with a count (no flood of repeats)."""

    def __init__(self):
        self.first: dict[str, str] = {}
        self.count: Counter = Counter()

    def warn(self, kind: str, message: str) -> None:
        if kind not in self.first:
            self.first[kind] = message
        self.count[kind] += 1

    def as_list(self) -> list[str]:
        return [f"{m} (x{self.count[k]})" if self.count[k] > 1 else m for k, m in self.first.items()]


class StereoInertialOdometry:
    """Per-frame estimator (see the module docstring).

    Args:
        cams: stereo camera models. stream: the IMU samples. noise: IMU noise densities.
        cfg: settings. loop_closer: optional ``LoopCloser`` (:mod:`aerovis_slam.slam.loop` API).
        log: warning log shared with the caller.
    """

    def __init__(self, cams: StereoCameras, stream: ImuStream, noise: ImuNoise | None, cfg: SlamConfig, *,
                 loop_closer=None, log: WarningLog | None = None, oracle=None):
        self.cams = cams
        self.oracle = oracle  # ObservationOracle (diagnostic): true observation positions (see oracle.py)
        rc = cfg.refinement
        self.refiner = TrackRefiner(rc.window_px, rc.max_shift_px, rc.max_fb_px, rc.max_anchor_age_s) if rc.enabled else None
        self.stream = stream
        self.cfg = cfg
        self.noise = noise
        self.params = preintegration_params(noise)
        self.loop_closer = loop_closer
        self.log = log or WarningLog()
        self.lmap = LandmarkMap()
        self.kfsel = KeyframeSelector(cfg.keyframes.overlap_threshold, cfg.keyframes.cell_px, cfg.backend.window_keyframes)
        self.smoother = KeyframeSmoother(cfg.backend, cams, self.params)
        self.frame = -1
        self.t_last: int | None = None
        self.state: NavEstimate | None = None           # current frame state (odometry frame)
        self.t_initialized: int | None = None           # tau (µs) at which gravity, velocity and biases became known
        self.init_frames: list[tuple[int, np.ndarray]] = []  # (t, T_V_B) tracked before initialisation
        self.preinit_frames: list[tuple[int, np.ndarray, bool]] = []  # (t, T_V_B, tracked): every frame before it
        self.t_first: int | None = None
        self.kf_id = -1
        self.kf_t: int | None = None
        self.kf_state: NavEstimate | None = None
        self.kf_keypoints: Keypoints | None = None
        self.pim = None
        self.fail_count = 0
        self.t_last_good: int | None = None
        self.lost = False
        self.rest: tuple[np.ndarray, np.ndarray, float] | None = None  # at rest: reference (gyro, acc, window s)
        self.tracking_losses = 0
        self.pose_refits = 0  # frames tracked by the loosened refit (tracking.refit_on_disagreement)
        self.recent_velocities: deque[np.ndarray] = deque(maxlen=10)  # of visually tracked frames (initialised)
        self.recovery_kfs = 0                           # keyframes left with loose tracking priors
        self._restart_sigma_vel: float | None = None    # velocity prior of the last smoother restart
        self.n_keyframes = 0
        self.kf_odom: dict[int, np.ndarray] = {}       # keyframe id -> T_world_body (odometry) at insertion
        self.kf_loop_rows: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # window keyframe -> (keypoint rows, landmark ids) given to the loop closer
        self.preinit_kfs: list[tuple] = []              # keyframes before initialisation, for the loop closer (see _to_loop_closer)
        self.preinit_window: list[tuple] = []           # the newest keyframes before initialisation: (id, t µs, T_vision_body, Observations)
        self.T_corr = np.eye(4)                         # loop-closure correction: world <- odometry world
        self.kf_smoothed: dict[int, np.ndarray] = {}    # keyframe id -> last smoother estimate T_world_body
        self.loop_corrections = 0
        self.rotate_outputs = None                      # set at initialisation: R_world_vision to apply to earlier outputs
        self.init_anchor: tuple[int, np.ndarray] | None = None  # set with it: the window's oldest keyframe, its T_world_body then
        self._keypoint_noise = np.random.default_rng(cfg.detector.keypoint_noise_seed)

    # ------------------------------------------------------------------------------------------
    @property
    def initialized(self) -> bool:
        """Gravity, velocity and biases are known (the smoother runs)."""
        return self.t_initialized is not None

    def _detect(self, detector, batch: np.ndarray) -> tuple[Keypoints, Keypoints]:
        dc = self.cfg.detector
        k = dc.top_k
        kps = detector.detect(batch, top_k=k) if k is not None else detector.detect(batch)
        if dc.min_event_support > 0:  # keypoints on lone noise events out (see event_support)
            kps = [supported_keypoints(kp, surfaces, dc.support_window, dc.min_event_support)
                   for kp, surfaces in zip(kps[:2], batch[:2])]
        noise = dc.keypoint_noise_px
        if noise > 0:
            h, w = batch.shape[-2:]
            kps = [perturb_keypoints(kp, self._keypoint_noise, noise, w, h) for kp in kps[:2]]
        return kps[0], kps[1]

    def _min_similarity(self, kp: Keypoints) -> float:
        m = self.cfg.matching
        return m.min_similarity_binary if kp.descriptors.dtype == np.uint8 else m.min_similarity

    def _predict(self, tau: int) -> NavEstimate:
        """IMU-propagated state at ``tau``."""
        if self.initialized:
            # From the keyframe's smoothed state, not the last frame's: per-frame tracking is noisier
            # than the smoother, and predicting from it carried that jitter into the next frame
            # (measured on the bench preset: SuperLitE sync ATE worse on 5 of 7 sequences).
            self.stream.integrate(self.pim, self.t_last, tau)
            ns = self.pim.predict(self.kf_state.navstate(), self.kf_state.bias)
            return NavEstimate.from_navstate(ns, self.kf_state.bias)
        # before gravity is known: gyro rotation, constant velocity from vision
        pim = new_preintegration(self.params)
        self.stream.integrate(pim, self.t_last, tau)
        T = self.state.T_world_body.copy()
        T[:3, :3] = T[:3, :3] @ pim.deltaRij().matrix()
        T[:3, 3] = T[:3, 3] + self.state.v_world * (tau - self.t_last) * 1e-6
        return NavEstimate(T, self.state.v_world.copy(), self.state.bias)

    def _pnp(self, m, kp: Keypoints, cam, T_pred: np.ndarray):
        pts = self.lmap.pos[m.landmark]
        T_cw_guess = invert_T(T_pred @ cam.T_body_cam)
        r = self.cfg.ransac
        ok, T_cw, inl = pnp_ransac(pts, kp.xy[m.keypoint].astype(np.float64), cam.K, reproj_px=r.pnp_reproj_px,
                                   iterations=r.pnp_iterations, confidence=r.confidence, T_guess=T_cw_guess,
                                   min_inliers=r.min_inliers)
        T_wb = invert_T(T_cw) @ invert_T(cam.T_body_cam)
        return ok, T_wb, inl

    def _check_reprojection(self, m, kp: Keypoints, cam, T_wb: np.ndarray, thr: float) -> np.ndarray:
        if len(m) == 0:
            return np.zeros(0, bool)
        return reprojection_error(self.lmap.pos[m.landmark], invert_T(T_wb @ cam.T_body_cam), cam.K, kp.xy[m.keypoint]) <= thr

    def _rotation_only(self, kpL: Keypoints) -> np.ndarray | None:
        """``R_world_body`` from 2D-2D matches to the last keyframe under pure rotation, or None."""
        if self.kf_keypoints is None or self.kf_state is None or len(kpL) < 5:
            return None
        pairs = match_keypoints(self.kf_keypoints, kpL)
        r = self.cfg.ransac
        if len(pairs) < r.rotation_min_inliers:
            return None
        K = self.cams.left.K
        xy0 = self.kf_keypoints.xy[pairs[:, 0]].astype(np.float64)
        xy1 = kpL.xy[pairs[:, 1]].astype(np.float64)
        R_10, inl = rotation_ransac(bearings(xy0, K), bearings(xy1, K), threshold_rad=np.radians(r.rotation_threshold_deg),
                                    rng=np.random.default_rng(self.frame))
        if inl.sum() < r.rotation_min_inliers:
            return None
        # model selection: the rotation must explain about as many matches as a general motion
        thr_px = np.radians(r.rotation_threshold_deg) * K[0, 0]
        _, inl_e = relative_pose_ransac(xy0, xy1, K, threshold_px=max(thr_px, 0.5), confidence=r.confidence)
        if inl.sum() < 0.9 * inl_e.sum():
            return None
        R_bc = self.cams.left.T_body_cam[:3, :3]
        R_w_ckf = self.kf_state.T_world_body[:3, :3] @ R_bc
        return R_w_ckf @ R_10.T @ R_bc.T

    # ------------------------------------------------------------------------------------------
    def process(self, tau: int, batch: np.ndarray, detector, new_events: int | None = None) -> FrameResult:
        """Estimate the pose at ``tau`` from the stereo MCTS ``batch`` (2, C, H, W).

        Args:
            new_events: events ingested (both cameras) since the previous frame. Below
                ``input.min_new_events_per_px`` the time surfaces are those of the previous frame (a
                static or dark stretch): they carry no information about the motion since, so the
                frame is propagated with the IMU alone, or held where the IMU says the camera is at rest
                (``tracking.zero_velocity``).
        """
        cfg = self.cfg
        if new_events is not None and self.t_last is not None:
            min_ev = cfg.input.min_new_events_per_px * self.cams.left.width * self.cams.left.height
            if new_events < min_ev:
                return self._imu_only_frame(tau, f"{new_events} new events (< {min_ev:.0f})")
        self.rest = None  # events again: whatever the IMU says, tracking takes over
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        kpL, kpR = self._detect(detector, batch)
        timings["detector"] = (time.perf_counter() - t0) * 1e3
        self.frame += 1
        if self.t_last is None:  # the very first frame: identity pose in the vision frame
            self.t_first = tau
            self.state = NavEstimate(np.eye(4), np.zeros(3), gtsam.imuBias.ConstantBias())
            self.t_last = tau
            self.t_last_good = tau
            pred = self.state
        else:
            pred = self._predict(tau)

        # -- matching to the map --------------------------------------------------------------
        t1 = time.perf_counter()
        life = None if cfg.matching.max_landmark_age_s is None else int(cfg.matching.max_landmark_age_s * 1e6)
        ids = self.lmap.local_ids(tau, cfg.backend.max_landmarks, int(2.0e6), life)
        window = cfg.matching.window_px if self.fail_count == 0 else cfg.matching.window_px_lost
        simL, simR = self._min_similarity(kpL), self._min_similarity(kpR)
        mL = match_to_map(self.lmap, ids, pred.T_world_body, self.cams.left, kpL, window_px=window,
                          min_similarity=simL, ratio=cfg.matching.ratio)
        mR = match_to_map(self.lmap, ids, pred.T_world_body, self.cams.right, kpR, window_px=window,
                          min_similarity=simR, ratio=cfg.matching.ratio)
        thr = cfg.ransac.pnp_reproj_px
        ok = False
        T_pnp = pred.T_world_body
        inlL = np.zeros(len(mL), bool)
        inlR = np.zeros(len(mR), bool)
        if max(len(mL), len(mR)) >= 4:
            if len(mL) >= len(mR):
                ok, T_pnp, inlL = self._pnp(mL, kpL, self.cams.left, pred.T_world_body)
                inlR = self._check_reprojection(mR, kpR, self.cams.right, T_pnp, thr)
            else:
                ok, T_pnp, inlR = self._pnp(mR, kpR, self.cams.right, pred.T_world_body)
                inlL = self._check_reprojection(mL, kpL, self.cams.left, T_pnp, thr)
        n_inl = int(inlL.sum() + inlR.sum())
        rot_prior = None
        if n_inl < cfg.ransac.min_inliers and self.initialized:
            R = self._rotation_only(kpL)
            if R is not None:
                rot_prior = (R, np.radians(max(cfg.ransac.rotation_threshold_deg, 0.1)))
        timings["matching"] = (time.perf_counter() - t1) * 1e3

        # -- state estimate ---------------------------------------------------------------------
        t2 = time.perf_counter()
        # images of the frame (blurred channel means) and their structure tensors: observation shapes
        # now and at a keyframe, the images for the stereo search at a keyframe
        means = batch[:2].mean(axis=1)  # (2, H, W)
        images = tuple(cv2.GaussianBlur(np.ascontiguousarray(m), (0, 0), 1.0) for m in means)
        tensors = tuple(structure_tensor(im) for im in images)
        obs = Observations(np.concatenate([mL.landmark[inlL], mR.landmark[inlR]]),
                           np.concatenate([np.zeros(int(inlL.sum()), np.int8), np.ones(int(inlR.sum()), np.int8)]),
                           np.concatenate([kpL.xy[mL.keypoint[inlL]], kpR.xy[mR.keypoint[inlR]]]).astype(np.float64))
        obs_kp = np.concatenate([mL.keypoint[inlL], mR.keypoint[inlR]])
        if self.refiner is not None:
            tr = time.perf_counter()
            # the unblurred channel means: the tracker's window does the smoothing (measured: blurred
            # images refine fewer observations, and no better)
            windows = cfg.refinement.windows
            self.refiner.begin_frame(tau, means if windows is None else alignment_images(batch[:2], windows))
            obs = self.refiner.refine(obs)
            timings["refine"] = (time.perf_counter() - tr) * 1e3
        for c in (0, 1):  # observation shapes at the (refined) positions
            rows = obs.cam == c
            obs.shape[rows] = edge_shapes(tensors[c], obs.xy[rows], max_ratio=cfg.matching.edge_max_ratio)
        # older sightings have wandered further from the track's scene point (backend.track_drift_px2_per_s)
        obs.shape = track_age_shapes(cfg.backend, obs.shape, (tau - self.lmap.born_t[obs.landmark]) * 1e-6)
        if self.oracle is not None:
            obs, keep = self.oracle.replace(tau, obs)
            obs_kp = obs_kp[keep]
        visual = n_inl >= cfg.ransac.min_inliers
        tracked = False
        if self.frame == 0:
            state, tracked = self.state, True
        elif self.initialized:
            if visual or rot_prior is not None:
                guess = NavEstimate(T_pnp if visual else pred.T_world_body, pred.v_world, self.kf_state.bias)
                try:
                    use = spread_subset(obs.xy, cfg.backend.tracking_max_observations, cfg.keyframes.cell_px,
                                        self.cams.left.width)
                    # after a restart the keyframe's velocity is not converged: hold it loosely
                    recovery = loose_kf_sigmas(cfg.tracking.recovery_velocity_sigma)
                    tight = TRACKING_KF_SIGMAS if self.recovery_kfs == 0 else recovery
                    # vision against the keyframe's IMU prediction: see tracking.refit_on_disagreement
                    refit = recovery if (cfg.tracking.refit_on_disagreement and visual and self.recovery_kfs == 0) else None
                    tr, refitted = track_frame_or_refit(
                        self.cams, cfg.backend, self.kf_state, self.pim, guess, obs, self.lmap.pos[obs.landmark],
                        max_reproj_px=cfg.matching.max_reproj_px, min_inliers=cfg.ransac.min_inliers, kf_sigmas=tight,
                        loose_kf_sigmas=refit, rotation_prior=rot_prior, use=use)
                    self.pose_refits += int(refitted)
                    state = tr.state
                    keep = tr.inliers
                    obs, obs_kp = obs.subset(keep), obs_kp[keep]
                    tracked = (len(obs) >= cfg.ransac.min_inliers) or rot_prior is not None
                except RuntimeError as exc:
                    self.log.warn("tracking-solver", f"t={tau} µs: tracking optimisation failed ({exc}); IMU-only propagation")
                    state = pred
            else:
                state = pred
        else:
            # Before initialisation: the rotation comes from the gyroscope (precise over these spans
            # and independent of gravity), the position from the 3D-2D inliers of both cameras with
            # that rotation fixed. A full single-camera PnP over a narrow field of view confuses small
            # rotations with translations, and its jitter would spoil the visual-inertial alignment.
            # With the rotation fixed, fewer inliers suffice (init.min_position_inliers).
            state = pred
            if n_inl >= cfg.init.min_position_inliers:
                cams = self.cams
                p, err = position_given_rotation(
                    self.lmap.pos[obs.landmark], obs.xy, obs.cam, [cams.left.K, cams.right.K],
                    [cams.left.T_body_cam, cams.right.T_body_cam], pred.T_world_body[:3, :3], pred.T_world_body[:3, 3])
                keep = err <= cfg.ransac.pnp_reproj_px
                obs, obs_kp = obs.subset(keep), obs_kp[keep]
                if len(obs) >= cfg.init.min_position_inliers:
                    T = pred.T_world_body.copy()
                    T[:3, 3] = p
                    # at least a tenth of the shortest frame interval (1 ms by default): 5 ms dropped the
                    # estimate from drone8_lit's first two frames, 4.9 ms apart, and its four-run mean
                    # rose from 0.52 to 0.74 %; over 1 ms millimetres of noise stay metres per second
                    v = vision_velocity(p, self.state.T_world_body[:3, 3], self.state.v_world, (tau - self.t_last) * 1e-6,
                                        0.1 / max(cfg.rate_hz, cfg.max_rate_hz))
                    state, tracked = NavEstimate(T, v, pred.bias), True
        timings["tracking"] = (time.perf_counter() - t2) * 1e3 - timings.get("refine", 0.0)

        # -- failure handling -------------------------------------------------------------------
        if tracked:
            self.fail_count = 0
            self.t_last_good = tau
            if self.initialized:
                self.recent_velocities.append(np.asarray(state.v_world, np.float64).copy())
        else:
            # the count that decided: RANSAC's inliers, or fewer once the pose fit dropped outliers
            self.log.warn("imu-only", f"t={tau} µs: {n_inl} 3D-2D RANSAC inliers, {len(obs)} kept by the pose fit "
                                      f"(< {cfg.ransac.min_inliers}): frame propagated with the IMU only")
            if self._visual_failure(tau):
                state = self._recover(tau, state)
        # landmark statistics (culling of landmarks that project but rarely match)
        self.lmap.n_projected[np.union1d(mL.projected, mR.projected)] += 1
        seen = np.unique(obs.landmark)
        self.lmap.n_matched[seen] += 1
        self.lmap.last_t[seen] = tau
        self.lmap.cull()

        # -- keyframe ---------------------------------------------------------------------------
        t3 = time.perf_counter()
        is_kf = self._keyframe_needed(tau, kpL, obs, obs_kp, tracked)
        if is_kf:
            is_kf = self._make_keyframe(tau, kpL, kpR, state, obs, obs_kp, timings, images, tensors)
            if is_kf and self.initialized:
                state = self.kf_state
        timings.setdefault("backend", 0.0)
        timings["keyframe"] = (time.perf_counter() - t3) * 1e3 - timings["backend"]

        self.state = state
        self.t_last = tau
        if not self.initialized:
            self.preinit_frames.append((tau, state.T_world_body.copy(), bool(tracked)))
            if tracked:
                self.init_frames.append((tau, state.T_world_body.copy()))
            elif self.frame > 0:
                self.init_frames = []  # the alignment needs a contiguous run of tracked frames
            self._try_initialize(tau, kpL, kpR)

        # -- loop-closure corrections (never waits) -------------------------------------------------
        t4 = time.perf_counter()
        self._poll_loop_closer()
        timings["loop"] = (time.perf_counter() - t4) * 1e3
        return self._result(tau, tracked, is_kf, n_inl, timings)

    def _result(self, tau: int, tracked: bool, is_kf: bool, n_inl: int, timings: dict) -> FrameResult:
        """The frame's output: ``self.state`` with the loop correction, anchored to the newest
        smoother keyframe (the state was estimated or IMU-propagated from it, so the final
        trajectory moves it with that keyframe's later estimates)."""
        anchor, T_kf_body = -1, None
        if self.initialized and self.smoother.kf_ids:
            anchor = self.smoother.kf_ids[-1]
            T_kf_body = invert_T(self.smoother.estimates[anchor].T_world_body) @ self.state.T_world_body
        elif not self.initialized and self.preinit_window:
            # vision-only: relative to the newest keyframe's tracked pose (a relative pose, the same
            # in the vision and the world frame); the initialisation's bundle adjustment estimates it
            anchor, _, T_kf, _ = self.preinit_window[-1]
            T_kf_body = invert_T(T_kf) @ self.state.T_world_body
        return FrameResult(tau, self.T_corr @ self.state.T_world_body, tracked, is_kf, n_inl, timings, anchor, T_kf_body,
                           self.T_corr.copy())

    def _imu_only_frame(self, tau: int, why: str) -> FrameResult:
        """A frame without visual information: IMU propagation (or, at rest, the held pose), failure
        bookkeeping, loop corrections."""
        t0 = time.perf_counter()
        self.frame += 1
        if self.rest is not None and self._stays_at_rest(self.t_last, tau):
            return self._held_frame(tau, why, t0)
        self.rest = None
        t_prev = self.t_last
        state = self._predict(tau)
        rest = self._comes_to_rest(t_prev, tau, state)
        if rest is not None:
            # The time surfaces are unchanged because nothing moved: the map stays valid. A keyframe
            # now holds the velocity at zero; until the body moves again its pose is held and no IMU
            # sample is integrated (integrated, the bias error would move a body at rest).
            self._warn_still(tau, why)
            self.kf_id += 1
            state = self._smoother_keyframe(self.kf_id, tau, NavEstimate(state.T_world_body, np.zeros(3), state.bias),
                                            Observations.empty(), {}, update_landmarks=False, zero_velocity=True)
            self.kf_t = tau
            self.rest = rest
            self.t_last_good = tau
        else:
            self.log.warn("no-events", f"t={tau} µs: {why}: frame propagated with the IMU only")
            # unchanged time surfaces say nothing against the map, so only the time without vision
            # (loss_time_s) counts, not the frames: a camera slowing to a halt sends few events for
            # several frames before the IMU can tell that it is at rest
            if self._visual_failure(tau, count_frame=False):
                state = self._recover(tau, state)
            if self.initialized and self.kf_t is not None and (tau - self.kf_t) * 1e-6 >= self.cfg.keyframes.max_interval_s:
                # keep the smoother's IMU chain bounded: a keyframe with the IMU factor only
                self.kf_id += 1
                state = self._smoother_keyframe(self.kf_id, tau, state, Observations.empty(), {}, update_landmarks=False)
                self.kf_t = tau
        self.state = state
        self.t_last = tau
        if not self.initialized:
            self.preinit_frames.append((tau, state.T_world_body.copy(), False))
            self.init_frames = []
            self._try_initialize(tau, None, None)
        self._poll_loop_closer()
        return self._result(tau, False, False, 0, {"tracking": (time.perf_counter() - t0) * 1e3})

    def _warn_still(self, tau: int, why: str) -> None:
        self.log.warn("still", f"t={tau} µs: {why}, and the IMU says the camera is at rest: pose held, velocity zero, map kept")

    def _held_frame(self, tau: int, why: str, t0: float) -> FrameResult:
        """A frame at rest: the pose of the keyframe that came to rest, zero velocity. The IMU's
        preintegration skips the rest (it starts again from this frame's time), which the body's rest
        makes exact: the next keyframe's IMU factor sees the rest keyframe's state at its end."""
        self._warn_still(tau, why)
        self.state = NavEstimate(self.kf_state.T_world_body.copy(), np.zeros(3), self.kf_state.bias)
        self.t_last = self.t_last_good = tau
        self._poll_loop_closer()
        return self._result(tau, False, False, 0, {"tracking": (time.perf_counter() - t0) * 1e3})

    def _comes_to_rest(self, t0: int, t1: int, state: NavEstimate) -> tuple[np.ndarray, np.ndarray, float] | None:
        """Whether the body is at rest over ``[t0, t1]`` µs (``tracking.zero_velocity``): after
        initialisation, with a tracked map, the speed estimate under the gate and the IMU samples of at
        least the last ``still_window_s`` fitting the readings that the state's bias and attitude
        predict at rest (:func:`~aerovis_slam.slam.imu.standstill_chi2`). Returns the window's mean
        readings and length (the reference that :meth:`_stays_at_rest` compares with), or None."""
        tc = self.cfg.tracking
        if not (tc.zero_velocity and self.initialized and not self.lost):
            return None
        if float(np.linalg.norm(state.v_world)) > tc.still_max_speed_m_s:
            return None
        b = state.bias
        acc_at_rest = np.asarray(b.accelerometer()) + state.T_world_body[:3, :3].T @ np.array([0.0, 0.0, GRAVITY])
        chi2, gyro_mean, acc_mean, window_s = self._rest_chi2(t0, t1, np.asarray(b.gyroscope()), acc_at_rest)
        return (gyro_mean, acc_mean, window_s) if chi2 <= tc.still_chi2 else None

    def _stays_at_rest(self, t0: int, t1: int) -> bool:
        """Whether a body at rest still is: the IMU samples since the previous frame (at least the last
        ``still_window_s``) against the mean readings of the window in which it came to rest. Unlike
        that first test this needs no estimate, so an update of the bias at the rest keyframe cannot
        end the rest."""
        gyro_ref, acc_ref, ref_s = self.rest
        return self._rest_chi2(t0, t1, gyro_ref, acc_ref, reference_window_s=ref_s)[0] <= self.cfg.tracking.still_chi2

    def _rest_chi2(self, t0: int, t1: int, gyro_at_rest: np.ndarray, acc_at_rest: np.ndarray,
                   reference_window_s: float | None = None) -> tuple[float, np.ndarray, np.ndarray, float]:
        """:func:`~aerovis_slam.slam.imu.standstill_chi2` over ``[t0, t1]`` µs widened to at least the last
        ``tracking.still_window_s``, with the configured floors."""
        tc = self.cfg.tracking
        return standstill_chi2(self.stream, min(t0, t1 - int(tc.still_window_s * 1e6)), t1, gyro_at_rest, acc_at_rest,
                               self.noise, gyro_floor_rad_s=tc.still_gyro_floor_rad_s, acc_floor_m_s2=tc.still_acc_floor_m_s2,
                               reference_window_s=reference_window_s)

    def _visual_failure(self, tau: int, count_frame: bool = True) -> bool:
        """Count a frame without visual tracking; declare a tracking loss when they pile up (True).
        ``count_frame=False``: a frame without new events, which counts towards ``loss_time_s`` only."""
        cfg = self.cfg
        self.fail_count += int(count_frame)
        lost_time = (tau - self.t_last_good) * 1e-6 >= cfg.tracking.loss_time_s
        if self.initialized and not self.lost and (self.fail_count >= cfg.tracking.loss_frames or lost_time):
            self.lost = True
            self.tracking_losses += 1
            self.log.warn("tracking-loss", f"t={tau} µs: tracking lost after {self.fail_count} frames without visual "
                                           "tracking; map dropped, re-initialising from stereo")
            self.lmap.retire_all()
            self.kfsel.clear()
            return True
        return False

    def _recover(self, tau: int, state: NavEstimate) -> NavEstimate:
        """Restart the backend at a tracking loss: the IMU-propagated pose, the median velocity of the
        last visually tracked frames (loosely), the last keyframe's bias.

        Without vision the smoother's velocity is only as good as the IMU integration since the last
        tracked frame, and a velocity error grows the position error linearly for as long as tracking
        stays lost (measured on the bench's handheld sequences: metres within seconds). The velocity
        before the loss is a better guess; the stereo map built at the next keyframe and the IMU
        factors after it re-estimate it.
        """
        tc = self.cfg.tracking
        v = np.median(np.stack(self.recent_velocities), axis=0) if self.recent_velocities else np.zeros(3)
        state = NavEstimate(state.T_world_body, v, self.kf_state.bias)
        self.kf_id += 1
        self._restart_smoother(self.kf_id, tau, state, sigma_vel=tc.recovery_velocity_sigma)
        self.pim = new_preintegration(self.params, state.bias)
        self.kf_t = tau
        self.recovery_kfs = tc.recovery_keyframes
        self.recent_velocities.clear()
        return state

    def _poll_loop_closer(self) -> None:
        """Apply a published loop-closure correction (never waits)."""
        if self.loop_closer is None or not self.initialized:
            return
        corrected = self.loop_closer.poll()
        if corrected:
            known = [k for k in corrected if k in self.kf_odom]
            if known:
                k = max(known)
                self.T_corr = np.asarray(corrected[k], np.float64) @ invert_T(self.kf_odom[k])
                self.loop_corrections += 1

    # ------------------------------------------------------------------------------------------
    def _keyframe_needed(self, tau: int, kpL: Keypoints, obs: Observations, obs_kp: np.ndarray, tracked: bool) -> bool:
        kc = self.cfg.keyframes
        if self.kf_t is None or self.lost:
            return True
        dt = (tau - self.kf_t) * 1e-6
        if dt < kc.min_interval_s:
            return False
        if dt >= kc.max_interval_s:
            return True
        n_tracked = len(np.unique(obs.landmark))
        if n_tracked < kc.min_tracked:
            return True
        left = obs.cam == 0
        overlap = self.kfsel.best_overlap(kpL.xy[obs_kp[left]], obs.landmark[left], self.cams.left.width)
        return overlap < kc.overlap_threshold

    def _make_keyframe(self, tau, kpL, kpR, state, obs: Observations, obs_kp, timings, images, tensors) -> bool:
        cfg = self.cfg
        mc = cfg.matching
        # new landmarks: left keypoints without a landmark, found in the right view along the epipolar line
        usedL = np.zeros(len(kpL), bool)
        usedL[obs_kp[obs.cam == 0]] = True
        usedR = np.zeros(len(kpR), bool)
        usedR[obs_kp[obs.cam == 1]] = True
        free_r = np.flatnonzero(~usedR)
        kpR_free = Keypoints(kpR.xy[free_r], kpR.scores[free_r], kpR.descriptors[free_r])
        rowsL, pts_c0, xyR = match_stereo(kpL, kpR_free, self.cams.left.K, self.cams.right.K, self.cams.T_right_left,
                                          min_similarity=self._min_similarity(kpL), max_epipolar_px=mc.stereo_epipolar_px,
                                          min_disparity_px=mc.min_disparity_px, max_depth_m=mc.max_depth_m, ratio=mc.ratio,
                                          rows0=np.flatnonzero(~usedL), images=images, min_ncc=mc.stereo_min_ncc)
        if self.lost and len(rowsL) < cfg.ransac.min_inliers:
            # cannot re-initialise from this frame; keep the IMU chain of the smoother bounded
            if not (self.initialized and self.kf_t is not None and (tau - self.kf_t) * 1e-6 >= cfg.keyframes.max_interval_s):
                return False
            rowsL, pts_c0, xyR = rowsL[:0], pts_c0[:0], xyR[:0]
        T_wc0 = state.T_world_body @ self.cams.left.T_body_cam
        pts_w = pts_c0 @ T_wc0[:3, :3].T + T_wc0[:3, 3]
        self.kf_id += 1
        kf = self.kf_id
        new_ids = self.lmap.add(pts_w, kpL.descriptors[rowsL], tau, kf)
        if len(new_ids):
            self.lmap.last_t[new_ids] = tau
        left = obs.cam == 0
        if len(obs) and mc.update_descriptors:
            # descriptors follow the newest keyframe view (event appearance changes with the motion)
            self.lmap.desc[obs.landmark[left]] = kpL.descriptors[obs_kp[left]]
            right_only = ~np.isin(obs.landmark, obs.landmark[left]) & (obs.cam == 1)
            self.lmap.desc[obs.landmark[right_only]] = kpR.descriptors[obs_kp[right_only]]
        if len(obs):
            self.lmap.last_kf[np.unique(obs.landmark)] = kf
        ratio = mc.edge_max_ratio
        # the rectified row search places the right position at the left keypoint minus the measured
        # disparity: the two rows share the keypoint's error (backend.disparity_sigma_px models that)
        row_search = uses_row_search(self.cams.left.K, self.cams.right.K, self.cams.T_right_left, images)
        new_obs = Observations(np.concatenate([new_ids, new_ids]),
                               np.concatenate([np.zeros(len(new_ids), np.int8), np.ones(len(new_ids), np.int8)]),
                               np.concatenate([kpL.xy[rowsL], xyR]).astype(np.float64),
                               np.concatenate([edge_shapes(tensors[0], kpL.xy[rowsL], max_ratio=ratio),
                                               edge_shapes(tensors[1], xyR, max_ratio=ratio)]),
                               np.full(2 * len(new_ids), row_search))
        if self.refiner is not None and len(new_obs):
            self.refiner.anchor(new_obs)
        if self.oracle is not None and len(new_obs):
            new_obs, _ = self.oracle.replace(tau, new_obs)
            # (a replacement holds true projections plus independent noise per row: no shared error,
            # and Observations made anew carry no stereo_pair flags)
            if self.oracle.replaces:
                self._triangulate_oracle_pairs(new_obs, T_wc0)
        all_obs = Observations.concatenate([obs, new_obs])
        if self.initialized:
            tb = time.perf_counter()
            self._smoother_keyframe(kf, tau, state, all_obs, self._positions(all_obs))
            self.recovery_kfs = max(0, self.recovery_kfs - 1)
            timings["backend"] = (time.perf_counter() - tb) * 1e3
        else:  # for the bundle adjustment at the initialisation (see _start)
            self.preinit_window.append((kf, int(tau), state.T_world_body.copy(), all_obs))
            del self.preinit_window[:-cfg.backend.window_keyframes]
        self.kf_t = tau
        self.kf_keypoints = kpL
        self.n_keyframes += 1
        lm_left = np.concatenate([obs.landmark[left], new_ids])
        self.kfsel.add(kf, lm_left, np.concatenate([kpL.xy[obs_kp[left]], kpL.xy[rowsL]]), self.cams.left.width)
        if self.lost and len(new_ids) >= cfg.ransac.min_inliers:
            self.lost = False
            self.fail_count = 0
            self.t_last_good = tau
        if self.loop_closer is not None:
            self._to_loop_closer(kf, tau, self.kf_state if self.initialized else state, kpL, obs, obs_kp, new_ids, rowsL)
        return True

    def _triangulate_oracle_pairs(self, new_obs: Observations, T_wc0: np.ndarray) -> None:
        """New landmarks placed where the oracle's stereo pair puts them (world, m), as the detector's
        own pair placed them before the replacement; one without a kept pair keeps that position."""
        xy = [{int(j): p for j, p in zip(new_obs.landmark[new_obs.cam == c], new_obs.xy[new_obs.cam == c])} for c in (0, 1)]
        ids = np.array([j for j in xy[0] if j in xy[1]], np.int64)
        if not len(ids):
            return
        xyL, xyR = np.stack([xy[0][j] for j in ids]), np.stack([xy[1][j] for j in ids])
        pts_c0, valid = triangulate(xyL, xyR, self.cams.left.K, self.cams.right.K, self.cams.T_right_left,
                                    max_reproj_px=np.inf)
        self.lmap.pos[ids[valid]] = transform_points(T_wc0, pts_c0[valid])

    def _positions(self, obs: Observations) -> dict[int, np.ndarray]:
        """Map positions (world, m) of the landmarks in ``obs``, by landmark id."""
        return {int(j): self.lmap.pos[j] for j in np.unique(obs.landmark)}

    def _smoother_keyframe(self, kf: int, tau: int, state: NavEstimate, obs: Observations, positions: dict,
                           *, update_landmarks: bool = True, zero_velocity: bool = False) -> NavEstimate:
        """Add keyframe ``kf`` (initial state ``state``) to the smoother, restarting it at ``state``
        when gtsam fails; its estimate becomes ``kf_state`` and starts a fresh preintegration.
        ``update_landmarks``: copy the window's landmark estimates back into the map; ``zero_velocity``:
        the body is at rest (a prior holds the keyframe's velocity at zero)."""
        est = state
        if self.pim.deltaTij() <= 0.0:
            # a second keyframe at the time of the smoother's newest: the backend was restarted at this
            # very frame (tracking loss) and the frame re-initialises from stereo. A zero-length IMU
            # factor has no information (gtsam: "indeterminate linear system"), so this keyframe takes
            # the restart's place, with the same priors.
            self._restart_smoother(kf, tau, state, sigma_vel=self._restart_sigma_vel)
        else:
            try:
                self.smoother.add_keyframe(kf, self.pim, state, obs, positions,
                                           zero_velocity_sigma=self.cfg.tracking.still_velocity_sigma_m_s if zero_velocity else None)
                _, est = self.smoother.latest
                if update_landmarks:
                    for j, p in self.smoother.landmark_estimates().items():
                        self.lmap.pos[j] = p
            except RuntimeError as exc:
                self.log.warn("backend-reset", f"t={tau} µs: smoother update failed ({exc}); backend restarted at the tracked state")
                self._restart_smoother(kf, tau, state)
                est = state
        self.kf_state = est
        self.pim = new_preintegration(self.params, est.bias)
        self._remember_window()
        return est

    def _remember_window(self) -> None:
        """Keep the smoother's estimate of every keyframe in its window: the last one a keyframe
        gets before it is marginalised is its final estimate (see ``final_trajectory``)."""
        for k, e in self.smoother.estimates.items():
            self.kf_smoothed[k] = e.T_world_body.copy()

    def _restart_smoother(self, kf: int, tau: int, state: NavEstimate, sigma_vel: float | None = None) -> None:
        b = self.cfg.backend
        sigma_vel = max(b.prior_velocity_m_s, 0.3) if sigma_vel is None else sigma_vel
        self._restart_sigma_vel = sigma_vel
        self.smoother.initialize(kf, tau * 1e-6, state, sigma_rollpitch_rad=np.radians(b.prior_rollpitch_deg),
                                 sigma_yaw_rad=np.radians(1.0), sigma_pos_m=0.01, sigma_vel=sigma_vel,
                                 sigma_acc_bias=b.prior_acc_bias, sigma_gyro_bias=b.prior_gyro_bias)
        self.kf_state = state
        self._remember_window()

    def _to_loop_closer(self, kf, tau, kf_state: NavEstimate, kpL, obs, obs_kp, new_ids, rowsL) -> None:
        """Give keyframe ``kf`` (its estimate, left keypoints and their landmarks) to the loop closer.

        Before initialisation the keyframe waits in ``preinit_kfs`` (its pose is in the vision
        frame, which only gravity turns into the world frame; body-frame points need no turning)
        and :meth:`_start` hands them over. A run that comes back to where it began (a figure of
        eight, a spin) finds these first keyframes: 6 of the 15 loops of SuperLitE on the bench
        preset match one of them.
        """
        T_wb = kf_state.T_world_body
        pts_body = np.zeros((len(kpL), 3))
        valid = np.zeros(len(kpL), bool)
        left = obs.cam == 0
        kp_idx = np.concatenate([obs_kp[left], rowsL]).astype(np.int64)
        lm_idx = np.concatenate([obs.landmark[left], new_ids]).astype(np.int64)
        pts_body[kp_idx] = transform_points(invert_T(T_wb), self.lmap.pos[lm_idx])
        valid[kp_idx] = True
        if not self.initialized:
            self.preinit_kfs.append((kf, int(tau), T_wb.copy(), kpL, pts_body, valid))
            return
        self._refresh_loop_points()
        self.kf_loop_rows[kf] = (kp_idx, lm_idx)
        self._add_loop_keyframe(kf, int(tau), T_wb, kpL, pts_body, valid)

    def _add_loop_keyframe(self, kf, tau, T_wb, kpL, pts_body, valid, *, unrefined: bool = False) -> None:
        """Hand keyframe ``kf`` to the loop closer and chain it to the previous one it took
        (``unrefined``: see :meth:`aerovis_slam.slam.loop.LoopCloser.add_keyframe`)."""
        prev = max(self.kf_odom) if self.kf_odom else None
        if not self.loop_closer.add_keyframe(kf, tau, T_wb.copy(), kpL, pts_body, valid, self.cams.left.K.copy(),
                                             self.cams.left.T_body_cam.copy(), unrefined=unrefined):
            return
        self.kf_odom[kf] = T_wb.copy()
        if prev is not None:
            self.loop_closer.add_odometry(prev, kf, invert_T(self.kf_odom[prev]) @ T_wb)

    def _refresh_loop_points(self) -> None:
        """Give the loop closer the smoother's current landmarks of the keyframes still in its window.

        A keyframe's landmarks as inserted are mostly fresh stereo triangulations (~4 px of
        disparity at 424x240: +-6-9 % in depth); later keyframes refine them. Expressed in the body
        frame of the same estimate's keyframe pose (not the pose at insertion, from which the window
        has moved on), they measured loops about twice as accurately on the bench preset (the same
        five loops: 1.5-10.4 cm instead of 3.5-17.7 cm). Each keyframe keeps the estimate of the last
        update before it leaves the window.
        """
        window = set(self.smoother.kf_ids)
        landmarks = self.smoother.landmark_estimates()
        for k in [k for k in self.kf_loop_rows if k not in window]:
            del self.kf_loop_rows[k]
        for k, (kp_idx, lm_idx) in self.kf_loop_rows.items():
            refined = np.array([j in landmarks for j in lm_idx.tolist()], bool)
            if not refined.any():
                continue
            P_world = np.stack([landmarks[j] for j in lm_idx[refined].tolist()])
            self.loop_closer.update_points(k, kp_idx[refined],
                                           transform_points(invert_T(self.smoother.estimates[k].T_world_body), P_world))

    # ------------------------------------------------------------------------------------------
    def _try_initialize(self, tau: int, kpL: Keypoints, kpR: Keypoints) -> None:
        ic = self.cfg.init
        frames = self.init_frames
        span = (frames[-1][0] - frames[0][0]) * 1e-6 if len(frames) >= 2 else 0.0
        aligned = None
        if ic.gravity == "velocity_change":
            tracked_t = [f[0] for f in self.preinit_frames if f[2]]
            if tracked_t and (tracked_t[-1] - tracked_t[0]) * 1e-6 >= ic.velocity_change_s and tracked_t[-1] == tau:
                est = self._velocity_change_gravity()
                if est is not None and est.tilt_sigma_deg <= ic.max_tilt_sigma_deg:
                    R_wv = est.R_world_vision
                    # no velocities from it: the initialisation's window takes the keyframe positions'
                    # slopes, with the fallback's velocity prior; its roll and pitch prior is the
                    # estimate's own sigma (see _start)
                    self._start(tau, R_wv, R_wv @ self.state.v_world, gtsam.imuBias.ConstantBias(), kpL, kpR,
                                tilt_sigma_deg=est.tilt_sigma_deg)
                    return
        elif len(frames) >= ic.min_frames and span >= ic.window_s and frames[-1][0] == tau:
            t = np.array([f[0] for f in frames])
            T = np.stack([f[1] for f in frames])
            try:
                al = align_visual_inertial(t, T, self.stream, self.params)
                # a consistent fit: gravity of the right size, small position residuals, a plausible gyro bias
                # and an uncertainty the smoother can start from (its own covariance)
                if (_plausible_gravity(al.gravity_norm) and al.residual_m < 0.05 and np.linalg.norm(al.gyro_bias) < 0.05
                        and al.tilt_sigma_deg <= ic.max_tilt_sigma_deg and al.velocity_sigma <= ic.max_velocity_sigma):
                    aligned = al
                else:
                    self.log.warn("init-gravity", f"t={tau} µs: visual-inertial alignment rejected (|g| = {al.gravity_norm:.2f} m/s², "
                                                  f"residual {al.residual_m * 100:.1f} cm, |b_g| = {np.linalg.norm(al.gyro_bias):.3f} rad/s, "
                                                  f"tilt sigma {al.tilt_sigma_deg:.1f} deg, velocity sigma {al.velocity_sigma:.2f} m/s); "
                                                  "collecting more frames")
                    self.init_frames = frames[len(frames) // 2:]
            except (ValueError, np.linalg.LinAlgError) as exc:
                self.log.warn("init-failed", f"t={tau} µs: visual-inertial alignment failed ({exc})")
        if aligned is not None:
            R_wv, tilt_sigma = aligned.R_world_vision, aligned.tilt_sigma_deg
            if ic.velocity_change_check:
                # the alignment's sigma assumes white position noise, a lower bound: on handheld_office
                # (bench preset) alignments accepted at 2 and 3 deg were 4-5 deg off. Where tracking
                # already spans enough for the velocity-change estimate and that is the more certain
                # one, its gravity replaces the alignment's (velocities and bias stay the alignment's)
                vc = self._velocity_change_gravity()
                if vc is not None and vc.tilt_sigma_deg < tilt_sigma:
                    R_wv, tilt_sigma = vc.R_world_vision, vc.tilt_sigma_deg
            v_w = R_wv @ aligned.velocities[-1]
            bias = gtsam.imuBias.ConstantBias(np.zeros(3), aligned.gyro_bias)
            self._start(tau, R_wv, v_w, bias, kpL, kpR, tilt_sigma_deg=tilt_sigma, velocity_sigma=aligned.velocity_sigma,
                        velocities={int(ti): vi for ti, vi in zip(t, aligned.velocities)})
        elif (tau - self.t_first) * 1e-6 >= ic.timeout_s:
            R_wv, how, tilt_sigma = self._fallback_gravity()
            v_w = R_wv @ self.state.v_world if len(frames) >= 2 else np.zeros(3)
            self.log.warn("init-static", f"t={tau} µs: no visual-inertial alignment accepted within {ic.timeout_s} s; "
                                         f"gravity {how}")
            # the velocity change's own tilt sigma as the roll and pitch prior, as where it is the
            # chosen start (init.gravity: velocity_change); the accelerometer's mean has none
            self._start(tau, R_wv, v_w, gtsam.imuBias.ConstantBias(), kpL, kpR, tilt_sigma_deg=tilt_sigma)

    def _fallback_gravity(self) -> tuple[np.ndarray, str, float | None]:
        """``R_world_vision`` (3, 3) for an initialisation without an accepted alignment, how it was
        found, and its 1-sigma tilt (deg; None for the accelerometer's mean, which has no estimate of it).

        First choice: the velocity change over all the frames tracked so far
        (:func:`~aerovis_slam.slam.imu.gravity_from_velocity_change`), when its norm passes the
        alignment's check (within 1 m/s² of 9.81). On handheld_office (bench preset, SuperLitE
        sync) that is 1.9 deg off (1.0 deg after the initialisation's window) where the
        accelerometer's mean over the first 0.2 s, which assumes a static start, is 19.9 deg off
        (8.1 deg after the window): the camera accelerates there. Otherwise that mean.
        """
        est = self._velocity_change_gravity()
        if est is not None:
            return (est.R_world_vision,
                    f"from the velocity change over the tracked frames {est.t_start_us}-{est.t_end_us} µs "
                    f"(|g| = {np.linalg.norm(est.gravity_vision):.2f} m/s², tilt sigma {est.tilt_sigma_deg:.1f} deg)",
                    est.tilt_sigma_deg)
        acc = self.stream.mean_acc(self.t_first, self.t_first + 200_000)
        return gravity_rotation_from_acc(acc), "from the accelerometer (assumes a static start)", None

    def _velocity_change_gravity(self):
        """:func:`~aerovis_slam.slam.imu.gravity_from_velocity_change` over the frames before the
        initialisation, or None where tracking does not cover it or its norm is not within 1 m/s²
        of 9.81 (the alignment's check)."""
        if len(self.preinit_frames) < 6:
            return None
        # appended frame by frame: already in time order
        est = gravity_from_velocity_change(np.array([f[0] for f in self.preinit_frames], np.int64),
                                           np.stack([f[1] for f in self.preinit_frames]),
                                           np.array([f[2] for f in self.preinit_frames]), self.stream, self.params)
        if est is None or not _plausible_gravity(float(np.linalg.norm(est.gravity_vision))):
            return None
        return est

    def _start(self, tau, R_wv, v_w, bias, kpL, kpR, *, tilt_sigma_deg: float | None = None,
               velocity_sigma: float | None = None, velocities: dict[int, np.ndarray] | None = None) -> None:
        """Rotate the vision frame into the gravity-aligned world and start the smoother at ``tau``.

        ``tilt_sigma_deg``, ``velocity_sigma``: the gravity estimate's own 1-sigma tilt (deg; the
        alignment's, or the velocity change's) and the alignment's velocity uncertainty (m/s); the
        smoother's priors are never tighter than them (a prior tighter than the estimate would pin
        its error), floored at ``backend.prior_rollpitch_deg`` / ``prior_velocity_m_s``. None: no
        such estimate (the static start's 5 deg, 10 in the initialisation's window;
        ``UNALIGNED_VELOCITY_SIGMA``).
        ``velocities``: the alignment's velocity (vision frame, m/s) per aligned frame time (µs),
        None after the static-start fallback; with ``init.bundle_adjustment`` the keyframes tracked
        before the initialisation start the window either way (see :meth:`_start_window`).
        """
        Rh = np.eye(4)
        Rh[:3, :3] = R_wv
        n = len(self.lmap)
        self.lmap.pos[:n] = self.lmap.pos[:n] @ R_wv.T
        T = Rh @ self.state.T_world_body
        self.state = NavEstimate(T, v_w, bias)
        self.rotate_outputs = Rh
        b = self.cfg.backend
        # gravity from the velocity change over a second of tracking is good to a degree or two (its
        # sigma predicts its error, tests/test_slam_core.py): with the static start's 10 deg the
        # window's few keyframes tilted it again (handheld_office, bench preset: eight-run median
        # 1.01 % with its own sigma, 1.06 % with 10 deg, the worst run 1.71 against 2.47 %; docs/slam.md)
        has_tilt_estimate = tilt_sigma_deg is not None  # the alignment's or the velocity change's
        sig_rp = np.radians(max(b.prior_rollpitch_deg, tilt_sigma_deg) if has_tilt_estimate else 5.0)
        priors = dict(sigma_rollpitch_rad=sig_rp,
                      sigma_vel=UNALIGNED_VELOCITY_SIGMA if velocity_sigma is None else max(b.prior_velocity_m_s, velocity_sigma),
                      sigma_acc_bias=b.prior_acc_bias, sigma_gyro_bias=b.prior_gyro_bias)
        started = False
        if self.cfg.init.bundle_adjustment:
            # the accelerometer's mean direction (the static-start fallback) was 1.4-19 deg off on the
            # bench preset's handheld starts: with keyframes to correct it, a prior that admits that
            window_priors = priors if has_tilt_estimate else dict(priors, sigma_rollpitch_rad=np.radians(10.0))
            started = self._start_window(tau, Rh, bias, velocities or {}, window_priors)
        if not started:
            self.kf_id += 1
            self.smoother.initialize(self.kf_id, tau * 1e-6, self.state, **priors)
            self.init_anchor = (self.kf_id, self.state.T_world_body.copy())
        self.kf_state = self.state
        self._remember_window()
        # the keyframe's bias: after the initialisation's window that is the smoother's estimate, not
        # the alignment's (track_frame integrates from the keyframe with its bias)
        self.pim = new_preintegration(self.params, self.kf_state.bias)
        self.kf_t = tau
        self.kf_keypoints = kpL
        self.t_initialized = int(tau)
        self.init_frames = []
        self.preinit_frames = []
        if self.loop_closer is not None:
            for kf, t_kf, T_vb, kp, pts_body, valid in self.preinit_kfs:
                # their landmarks as triangulated then: refining them with the smoother's later
                # estimates (as for the window's keyframes) was measured worse (four-run means of
                # the drone flights' final ATE 0.93 / 1.12 % instead of 0.82 / 0.89 %)
                est = self.smoother.estimates.get(kf)
                # a keyframe the initialisation's bundle adjustment left out (the first frame's, whose
                # long MCTS windows were still empty, and any older than the window) keeps a
                # vision-only pose beside the re-estimated ones: unrefined, which the loop closer's
                # setting ``unrefined_start_keyframes`` decides on (without that adjustment every
                # one of them keeps such a pose and none is marked: there is no other map)
                self._add_loop_keyframe(kf, t_kf, Rh @ T_vb if est is None else est.T_world_body, kp, pts_body, valid,
                                        unrefined=started and est is None)
        self.preinit_kfs = []
        self.preinit_window = []

    def _start_window(self, tau: int, Rh: np.ndarray, bias, velocities: dict[int, np.ndarray], priors: dict) -> bool:
        """Start the smoother with the keyframes tracked before the initialisation and the frame at ``tau``.

        The alignment fits gravity and velocities to the vision-only poses, which it takes as exact;
        on the bench preset its gravity was 1.7-17 deg off (1.7-3.5x its own sigma), and the
        smoother, started from the newest frame alone, needed about a second of new keyframes to
        see gravity again. The keyframes tracked before the initialisation (up to
        ``backend.window_keyframes``, also those of alignment windows that were rejected as too
        short) hold that second already: started with them (their IMU factors and landmark
        observations; the priors on the oldest), the window re-estimates gravity, velocities, those
        poses and their landmarks jointly at once, as VINS-Mono's visual-inertial bundle adjustment
        after its alignment does (handheld_office, bench preset: the newest state's tilt error 15.6
        -> 2.2 deg). The map takes the window's landmarks (not writing them back measured better on
        spin_hdr_window, worse on the drone flights and handheld_office; four runs each).

        Args:
            Rh: (4, 4) world <- vision rotation. bias: the alignment's bias (gyroscope; zero after
                the static-start fallback).
            velocities: the alignment's velocity (vision frame) per frame time (µs); empty after the
                static-start fallback (then every keyframe's velocity is the positions' slope).
            priors: ``KeyframeSmoother.initialize``'s priors (for the oldest keyframe).
        Returns:
            False (nothing changed) when fewer than two keyframes qualify or gtsam fails.
        """
        R_wv = Rh[:3, :3]
        n_max = self.cfg.backend.window_keyframes
        # not the keyframe of the first frame: its time surfaces hold the first events only (the
        # long channels are empty), and tracking against its landmarks jumped by 23 cm on a test
        # flight; started with it, the window tilted gravity further (7 -> 14.5 deg), without it
        # corrected it (7 -> 3.8 deg)
        chain = [kf for kf in self.preinit_window if self.t_first < kf[1] <= tau]
        if not chain or chain[-1][1] != tau:
            # the frame at tau joins as a keyframe with its IMU factor alone (the outputs go on from it)
            chain = chain[-(n_max - 1):] + [(self.kf_id + 1, int(tau), invert_T(Rh) @ self.state.T_world_body, Observations.empty())]
        chain = chain[-n_max:]
        if len(chain) < 2:
            return False
        # initial velocities: the alignment's where it has them; for keyframes before the aligned
        # stretch (an alignment rejected on a short window keeps only its newer half) the slope of
        # the keyframe positions, which the IMU factors then correct
        t_kf = np.array([c[1] for c in chain], np.float64) * 1e-6
        slope = np.gradient(np.stack([c[2][:3, 3] for c in chain]), t_kf, axis=0)
        v_init = {c[1]: velocities.get(c[1], slope[i]) for i, c in enumerate(chain)}

        def guess(T_vb, t):
            return NavEstimate(Rh @ T_vb, R_wv @ v_init[t], bias)

        if chain[0][1] not in velocities:
            # the oldest keyframe's velocity (the prior's centre) is the slope of the keyframe
            # positions, not the alignment's estimate: the alignment's sigma does not describe it.
            # With that sigma (0.12 m/s) the office start's window came out 1.3-1.6x too long
            # (the slope's error, carried by the IMU factors, outweighed the stereo scale);
            # with the fallback's 0.5 m/s its length was within 1 % of the truth (docs/slam.md)
            priors = dict(priors, sigma_vel=max(priors["sigma_vel"], UNALIGNED_VELOCITY_SIGMA))

        try:
            k0, t0, T0, obs0 = chain[0]
            self.smoother.initialize(k0, t0 * 1e-6, guess(T0, t0), obs=obs0, landmark_positions=self._positions(obs0), **priors)
            t_prev = t0
            for k, t, T_vb, obs in chain[1:]:
                pim = new_preintegration(self.params, bias)
                self.stream.integrate(pim, t_prev, t)
                self.smoother.add_keyframe(k, pim, guess(T_vb, t), obs, self._positions(obs))
                t_prev = t
        except RuntimeError as exc:
            self.log.warn("init-window", f"t={tau} µs: the bundle adjustment of the initialisation's keyframes failed ({exc}); "
                                         "the smoother starts from the newest frame alone")
            return False
        self.kf_id = max(self.kf_id, chain[-1][0])
        self.init_anchor = (chain[0][0], Rh @ chain[0][2])
        for j, p in self.smoother.landmark_estimates().items():
            self.lmap.pos[j] = p
        _, self.state = self.smoother.latest
        return True
