"""The estimator (gtsam): a fixed-lag keyframe smoother and the per-frame tracking optimisation.

State of a keyframe ``k`` (OKVIS2's): pose ``X(k)`` = ``T_world_body`` (gtsam ``Pose3``), velocity
``V(k)`` (world, m/s) and IMU biases ``B(k)`` (accelerometer m/s², gyroscope rad/s); landmarks ``L(j)``
are world points (m). Factors:

* ``CombinedImuFactor`` between consecutive keyframes (preintegrated IMU with bias random walk);
* ``GenericProjectionFactorCal3_S2`` for every landmark observation in the left or right camera,
  with ``body_P_sensor = T_body_cam`` and a robust (Huber or Cauchy) loss;
* priors on the first state (and after a reset).

:class:`KeyframeSmoother` keeps the last ``window_keyframes`` keyframes in a
``BatchFixedLagSmoother`` (Levenberg-Marquardt; its iteration count is bounded and lowered to fit
the time budget). Its "time" is the keyframe sequence number, so the lag counts keyframes, not
seconds; a landmark's time is its newest observing keyframe, so it leaves the window with the last
keyframe that saw it. Leaving variables are marginalised by gtsam into a linear prior on the rest,
by default with their observations of staying landmarks (``BackendConfig.leaving_observations``).

Frames between keyframes are estimated by :func:`track_frame` (motion-only, as in ORB-SLAM3's
visual-inertial tracking): the current pose, velocity and bias with the IMU factor from the last
keyframe (held at its smoother estimate) and the reprojections of map landmarks held fixed. This
keeps the smoother small (no fill-in from non-keyframe observations), while every output pose still
fuses vision and IMU.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from ..geometry import invert_T
from .cameras import StereoCameras
from .config import BackendConfig
from .ransac import reprojection_error
from .stereo import is_rectified

X = gtsam.symbol_shorthand.X
V = gtsam.symbol_shorthand.V
B = gtsam.symbol_shorthand.B
L = gtsam.symbol_shorthand.L


@dataclass
class NavEstimate:
    """An estimated state. ``T_world_body`` (4, 4), ``v_world`` (3,) m/s, ``bias`` gtsam ConstantBias."""

    T_world_body: np.ndarray
    v_world: np.ndarray
    bias: gtsam.imuBias.ConstantBias

    def navstate(self) -> gtsam.NavState:
        return gtsam.NavState(gtsam.Pose3(self.T_world_body), np.asarray(self.v_world, np.float64))

    @classmethod
    def from_navstate(cls, ns: gtsam.NavState, bias) -> "NavEstimate":
        return cls(ns.pose().matrix(), np.asarray(ns.velocity(), np.float64).copy(), bias)


@dataclass
class Observations:
    """Landmark observations of one frame.

    Attributes:
        landmark: (M,) int64 landmark ids. cam: (M,) int8 0 = left, 1 = right. xy: (M, 2) pixels.
        shape: (M, 2, 2) covariance shape of each observation (identity: isotropic); the pixel noise
            is ``pixel_sigma^2 * shape`` (see :func:`~aerovis_slam.slam.frontend.edge_shapes`).
        stereo_pair: (M,) bool: the left and right rows of one rectified row-search match (the right
            position is the left keypoint shifted by the measured disparity, so both carry the
            keypoint's error); False for independent detections.
    """

    landmark: np.ndarray
    cam: np.ndarray
    xy: np.ndarray
    shape: np.ndarray | None = None
    stereo_pair: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.shape is None:
            self.shape = np.broadcast_to(np.eye(2), (len(self.landmark), 2, 2)).copy()
        if self.stereo_pair is None:
            self.stereo_pair = np.zeros(len(self.landmark), bool)

    @classmethod
    def empty(cls) -> "Observations":
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int8), np.zeros((0, 2)), np.zeros((0, 2, 2)))

    def __len__(self) -> int:
        return len(self.landmark)

    def subset(self, mask: np.ndarray) -> "Observations":
        return Observations(self.landmark[mask], self.cam[mask], self.xy[mask], self.shape[mask], self.stereo_pair[mask])

    @classmethod
    def concatenate(cls, parts: list["Observations"]) -> "Observations":
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty()
        return cls(np.concatenate([p.landmark for p in parts]), np.concatenate([p.cam for p in parts]),
                   np.concatenate([p.xy for p in parts]), np.concatenate([p.shape for p in parts]),
                   np.concatenate([p.stereo_pair for p in parts]))


def pixel_noise(cfg: BackendConfig, shape: np.ndarray | None = None) -> gtsam.noiseModel.Base:
    """Pixel noise ``pixel_sigma^2 * shape`` (isotropic without a shape) in the configured robust loss.

    The robust threshold ``robust_k`` is in sigmas of the whitened residual.
    """
    if shape is None:
        base = gtsam.noiseModel.Isotropic.Sigma(2, cfg.pixel_sigma)
    else:
        base = gtsam.noiseModel.Gaussian.Covariance(cfg.pixel_sigma ** 2 * np.asarray(shape, np.float64))
    return _robust(cfg, base)


def _robust(cfg: BackendConfig, base: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
    """``base`` in the configured robust loss (``robust``, threshold ``robust_k`` in sigmas of the
    whitened residual)."""
    k = cfg.robust_k
    est = gtsam.noiseModel.mEstimator.Huber.Create(k) if cfg.robust == "huber" else gtsam.noiseModel.mEstimator.Cauchy.Create(k)
    return gtsam.noiseModel.Robust.Create(est, base)


def track_age_shapes(cfg: BackendConfig, shape: np.ndarray, age_s: np.ndarray) -> np.ndarray:
    """Observation shapes (M, 2, 2) with the track-age term of ``backend.track_drift_px2_per_s``.

    The covariance :func:`pixel_noise` makes of the result is ``(pixel_sigma^2 + drift * age_s) *
    shape``: a keypoint that wanders from its first sighting's scene point like a random walk
    (``drift`` px^2 per second of track age, ``age_s`` (M,) seconds since the landmark's first
    sighting). Unchanged without the option.
    """
    drift = cfg.track_drift_px2_per_s
    if not drift:
        return shape
    age = np.clip(np.asarray(age_s, np.float64), 0.0, None)
    return shape * (1.0 + drift * age / cfg.pixel_sigma ** 2)[:, None, None]


def _noise_for(cfg: BackendConfig, shape: np.ndarray, isotropic) -> gtsam.noiseModel.Base:
    return isotropic if np.allclose(shape, np.eye(2)) else pixel_noise(cfg, shape)


def stereo_pair_covariance(cfg: BackendConfig, shape: np.ndarray) -> np.ndarray:
    """(3, 3) covariance (px^2) of a row-search stereo pair as ``(u_left, u_right, v)``.

    The right position is ``u_left - d``: it repeats the left keypoint's error ``e`` (covariance
    ``pixel_sigma^2 * shape`` in (u, v)) and adds the disparity's, ``e_d`` (``disparity_sigma_px``),
    independent of it. So ``cov(u_r, u_r) = S_uu + s_d^2``, ``cov(u_r, u_l) = S_uu``,
    ``cov(u_r, v) = S_uv``.
    """
    S = cfg.pixel_sigma ** 2 * np.asarray(shape, np.float64)
    sd2 = float(cfg.disparity_sigma_px) ** 2
    return np.array([[S[0, 0], S[0, 0], S[0, 1]],
                     [S[0, 0], S[0, 0] + sd2, S[0, 1]],
                     [S[0, 1], S[0, 1], S[1, 1]]])


def stereo_pair_noise(cfg: BackendConfig, shape: np.ndarray) -> gtsam.noiseModel.Base:
    """:func:`stereo_pair_covariance` in the configured robust loss (threshold in sigmas of the
    whitened 3-vector, as for the projection factors)."""
    return _robust(cfg, gtsam.noiseModel.Gaussian.Covariance(stereo_pair_covariance(cfg, shape)))


def bias_noise(acc_sigma: float, gyro_sigma: float) -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Diagonal.Sigmas(np.array([acc_sigma] * 3 + [gyro_sigma] * 3))


@dataclass
class SmootherUpdate:
    """What one keyframe update did: LM ``iterations``, ``time_ms``, ``error`` (after), ``landmarks`` in
    the window, ``new_landmarks`` added, observations not added (``dropped_observations``: landmarks
    outside the window seen by one camera only) and old observations removed before marginalisation."""

    iterations: int = 0
    time_ms: float = 0.0
    error: float = float("nan")
    landmarks: int = 0
    new_landmarks: int = 0
    dropped_observations: int = 0
    removed_observations: int = 0


class KeyframeSmoother:
    """Fixed-lag smoother over keyframes (see the module docstring).

    Args:
        cfg: backend settings. cams: the stereo cameras. pim_params: IMU preintegration parameters.
    """

    def __init__(self, cfg: BackendConfig, cams: StereoCameras, pim_params: gtsam.PreintegrationCombinedParams):
        self.cfg = cfg
        self.cams = cams
        self.pim_params = pim_params
        self._cal = [c.cal3 for c in cams.cams]
        self._bPs = [c.body_P_sensor for c in cams.cams]
        self._noise = pixel_noise(cfg)
        self._lm_prior = gtsam.noiseModel.Isotropic.Sigma(3, 5.0)
        # backend.disparity_sigma_px: row-search pairs as one stereo factor, on a rectified rig only
        # (gtsam's stereo camera model: the right camera at +b along the left's x axis, same K)
        self._stereo_cal = None
        if cfg.disparity_sigma_px is not None and is_rectified(cams.left.K, cams.right.K, cams.T_right_left):
            K = cams.left.K
            self._stereo_cal = gtsam.Cal3_S2Stereo(K[0, 0], K[1, 1], 0.0, K[0, 2], K[1, 2], -float(cams.T_right_left[0, 3]))
        self.stereo_factors = 0  # stereo-pair factors added (over all resets)
        self.qr_fallbacks = 0  # updates that Cholesky could not solve and QR finished (over all resets)
        # backend.time_budget_ms makes the iteration cap of an update depend on the machine's speed;
        # to replay a run exactly, its caps are logged and can be imposed again (over all resets)
        self.iteration_caps: list[int] = []   # the cap of every update so far
        self.budget_cuts = 0                  # updates whose cap the time budget lowered below max_iterations
        self.forced_caps: list[int] | None = None  # when set: the caps of the next updates, in order
        self.forced_caps_missing = 0          # updates that found forced_caps set but empty (the budget decided)
        self.reset()

    def reset(self) -> None:
        """Forget everything (after a failure or a tracking loss the caller re-initialises)."""
        lm = gtsam.LevenbergMarquardtParams()
        lm.setMaxIterations(int(self.cfg.max_iterations))
        # Lag in keyframe counts (the smoother's "time" is the keyframe sequence number).
        self.smoother = gtsam.BatchFixedLagSmoother(float(self.cfg.window_keyframes) - 0.5, lm)
        self.kf_ids: list[int] = []           # keyframes in the window (oldest first)
        self.kf_seq: dict[int, int] = {}      # keyframe id -> sequence number (smoother time)
        self.lm_key: dict[int, int] = {}      # landmark id -> gtsam key, for landmarks in the window
        self.lm_time: dict[int, int] = {}     # landmark id -> newest observing keyframe sequence number
        self.lm_obs: dict[int, list[int]] = {}  # landmark id -> sequence numbers of its observation factors
        self._next_key = 0
        self._seq = 0
        self._iter_ms = 5.0                   # running estimate of one LM iteration's cost
        self.estimates: dict[int, NavEstimate] = {}
        self.landmarks: dict[int, np.ndarray] = {}  # landmark id -> world position (m), window after the last update
        self.initialized = False

    # ------------------------------------------------------------------------------------------
    def initialize(self, kf_id: int, t_s: float, state: NavEstimate, *, sigma_rollpitch_rad: float,
                   sigma_yaw_rad: float = 1e-3, sigma_pos_m: float = 1e-3, sigma_vel: float,
                   sigma_acc_bias: float, sigma_gyro_bias: float, obs: Observations | None = None,
                   landmark_positions: dict[int, np.ndarray] | None = None) -> None:
        """Start the window at keyframe ``kf_id`` with priors on its state.

        The pose prior is tight on position and yaw (the unobservable gauge of visual-inertial
        odometry) and looser on roll and pitch (gravity makes them observable). The sigmas are
        about world axes (yaw about world z, roll and pitch about world x and y), turned into gtsam's
        body-frame Pose3 tangent (rotation, translation) as ``R^T diag(...) R``, so they hold at any
        attitude.
        ``obs`` / ``landmark_positions``: the keyframe's own landmark observations, as for
        :meth:`add_keyframe` (a window started from earlier keyframes, see the odometry's
        initialisation, keeps what its first keyframe saw).
        """
        self.reset()
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        pose = gtsam.Pose3(state.T_world_body)
        # world-frame sigmas: yaw about world z, roll/pitch about world x/y, rotated into the body
        R = state.T_world_body[:3, :3]
        cov_w = np.diag([sigma_rollpitch_rad ** 2, sigma_rollpitch_rad ** 2, sigma_yaw_rad ** 2])
        cov_rot = R.T @ cov_w @ R
        cov = np.zeros((6, 6))
        cov[:3, :3] = cov_rot
        cov[3:, 3:] = np.eye(3) * sigma_pos_m ** 2
        graph.add(gtsam.PriorFactorPose3(X(kf_id), pose, gtsam.noiseModel.Gaussian.Covariance(cov)))
        graph.add(gtsam.PriorFactorVector(V(kf_id), np.asarray(state.v_world, np.float64),
                                          gtsam.noiseModel.Isotropic.Sigma(3, sigma_vel)))
        graph.add(gtsam.PriorFactorConstantBias(B(kf_id), state.bias, bias_noise(sigma_acc_bias, sigma_gyro_bias)))
        values.insert(X(kf_id), pose)
        values.insert(V(kf_id), np.asarray(state.v_world, np.float64))
        values.insert(B(kf_id), state.bias)
        stamps = {X(kf_id): 0.0, V(kf_id): 0.0, B(kf_id): 0.0}
        if obs is not None and len(obs):
            self._add_observations(graph, values, stamps, kf_id, 0, obs, landmark_positions or {})
        self.smoother.update(graph, values, stamps)
        self.kf_ids = [kf_id]
        self.kf_seq = {kf_id: 0}
        self._seq = 0
        self.estimates = {kf_id: NavEstimate(state.T_world_body.copy(), np.asarray(state.v_world, np.float64).copy(), state.bias)}
        if self.lm_key:  # the keyframe's own landmarks, as the update estimated them
            self.landmarks = self._landmarks_from(self.smoother.calculateEstimate())
        self.initialized = True

    def _landmarks_from(self, est: gtsam.Values) -> dict[int, np.ndarray]:
        """World positions (m) of the window's landmarks in ``est``, by landmark id."""
        return {j: np.asarray(est.atPoint3(k)) for j, k in self.lm_key.items() if est.exists(k)}

    def _add_observations(self, graph, values, stamps: dict, kf_id: int, seq: int, obs: Observations,
                          landmark_positions: dict[int, np.ndarray]) -> tuple[int, int]:
        """Projection factors of keyframe ``kf_id``'s observations into ``graph`` (new landmark
        variables into ``values``). Returns (observations dropped, landmarks added)."""
        # Landmarks: reuse the window's variable, or add one when this keyframe constrains it alone
        # (seen by both cameras: a stereo pair fixes a point); others only help tracking.
        ids, counts = np.unique(obs.landmark, return_counts=True)
        stereo_seen = set(ids[counts >= 2].tolist())
        dropped = 0
        new_keys = 0
        # backend.disparity_sigma_px: a row-search pair becomes one stereo factor (its right row is
        # then skipped below)
        pair_right: dict[int, np.ndarray] = {}
        if self._stereo_cal is not None and obs.stereo_pair.any():
            left = set(obs.landmark[obs.stereo_pair & (obs.cam == 0)].tolist())
            right = obs.stereo_pair & (obs.cam == 1)
            pair_right = {j: xy for j, xy in zip(obs.landmark[right].tolist(), obs.xy[right]) if j in left}
        for j, cam, xy, shape, paired in zip(obs.landmark.tolist(), obs.cam.tolist(), obs.xy, obs.shape, obs.stereo_pair.tolist()):
            if paired and cam == 1 and j in pair_right:
                continue
            key = self.lm_key.get(j)
            if key is None:
                if j not in stereo_seen or j not in landmark_positions:
                    dropped += 1
                    continue
                key = self._landmark_key(j)
                p = np.asarray(landmark_positions[j], np.float64)
                values.insert(key, p)
                # A weak prior (metres) keeps the system determinate when an observation degenerates
                # (a mismatch pulled behind a camera gives a projection factor without gradient);
                # against pixel-accurate stereo it weighs nothing.
                graph.add(gtsam.PriorFactorPoint3(key, p, self._lm_prior))
                new_keys += 1
            if paired and cam == 0 and j in pair_right:
                xr = float(pair_right[j][0])
                graph.add(gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(float(xy[0]), xr, float(xy[1])),
                                                      stereo_pair_noise(self.cfg, shape), X(kf_id), key, self._stereo_cal,
                                                      False, False, self._bPs[0]))
                self.stereo_factors += 1
                self.lm_obs.setdefault(j, []).append(seq)  # two rays in one factor (see _observations_to_drop)
            else:
                graph.add(gtsam.GenericProjectionFactorCal3_S2(np.asarray(xy, np.float64), _noise_for(self.cfg, shape, self._noise),
                                                               X(kf_id), key, self._cal[cam], False, False, self._bPs[cam]))
            stamps[key] = float(seq)
            self.lm_time[j] = seq
            self.lm_obs.setdefault(j, []).append(seq)
        return dropped, new_keys

    def _landmark_key(self, lm_id: int) -> int:
        key = L(self._next_key)
        self._next_key += 1
        self.lm_key[lm_id] = key
        return key

    def add_keyframe(self, kf_id: int, pim: gtsam.PreintegratedCombinedMeasurements, guess: NavEstimate,
                     obs: Observations, landmark_positions: dict[int, np.ndarray],
                     zero_velocity_sigma: float | None = None) -> SmootherUpdate:
        """Add keyframe ``kf_id`` (IMU factor from the previous keyframe) and its observations, optimise.

        Args:
            pim: IMU preintegration from the previous keyframe's time to this one's.
            guess: initial state of the new keyframe (from tracking).
            obs: its landmark observations (left and right).
            landmark_positions: world positions (3,) of every landmark in ``obs`` (initial values of
                landmarks new to the window).
            zero_velocity_sigma: the body is at rest: a prior holds the keyframe's velocity at zero
                with this sigma (m/s; None: no prior).
        Returns:
            a :class:`SmootherUpdate`. Raises RuntimeError (gtsam's) when the system is degenerate.
        """
        if not self.initialized:
            raise RuntimeError("KeyframeSmoother.add_keyframe before initialize")
        prev = self.kf_ids[-1]
        self._seq += 1
        seq = self._seq
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        stamps: dict[int, float] = {}
        graph.add(gtsam.CombinedImuFactor(X(prev), V(prev), X(kf_id), V(kf_id), B(prev), B(kf_id), pim))
        values.insert(X(kf_id), gtsam.Pose3(guess.T_world_body))
        values.insert(V(kf_id), np.asarray(guess.v_world, np.float64))
        values.insert(B(kf_id), guess.bias)
        for k in (X(kf_id), V(kf_id), B(kf_id)):
            stamps[k] = float(seq)
        if zero_velocity_sigma is not None:
            graph.add(gtsam.PriorFactorVector(V(kf_id), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, zero_velocity_sigma)))
        dropped, new_keys = self._add_observations(graph, values, stamps, kf_id, seq, obs, landmark_positions)
        remove = self._observations_to_drop(seq)
        # Iteration budget: as many LM iterations as the measured cost allows (at least one).
        # (no budget: always max_iterations, so that a sync run does not depend on the machine's load)
        budget = self.cfg.time_budget_ms
        n_iter = self.cfg.max_iterations if budget is None else int(np.clip(budget / max(self._iter_ms, 1e-3), 1,
                                                                            self.cfg.max_iterations))
        if self.forced_caps:  # a replay (pipeline frame_caps): the cap this update had in the run replayed
            n_iter = int(self.forced_caps.pop(0))
        elif self.forced_caps is not None:
            self.forced_caps_missing += 1
        self.iteration_caps.append(n_iter)
        self.budget_cuts += int(n_iter < self.cfg.max_iterations)
        self.smoother.params().setMaxIterations(n_iter)
        t0 = time.perf_counter()
        try:
            result = self.smoother.update(graph, values, stamps, remove)
        except RuntimeError as exc:
            if "ndetermina" not in str(exc):  # gtsam's IndeterminantLinearSystemException (both spellings)
                raise
            result = self._update_with_qr()
        dt_ms = (time.perf_counter() - t0) * 1e3
        iters = max(int(result.getIterations()), 1)
        self._iter_ms = 0.7 * self._iter_ms + 0.3 * dt_ms / iters
        self.kf_ids.append(kf_id)
        self.kf_seq[kf_id] = seq
        # forget what the smoother marginalised
        horizon = seq - (self.cfg.window_keyframes - 0.5)
        self.kf_ids = [k for k in self.kf_ids if self.kf_seq[k] >= horizon]
        for j in [j for j, s in self.lm_time.items() if s < horizon]:
            del self.lm_time[j]
            self.lm_key.pop(j, None)
            self.lm_obs.pop(j, None)
        est = self.smoother.calculateEstimate()
        self.estimates = {k: NavEstimate(est.atPose3(X(k)).matrix(), np.asarray(est.atVector(V(k))).copy(),
                                         est.atConstantBias(B(k))) for k in self.kf_ids}
        # read out once per update: the map copy and the loop closer's refresh both need them
        self.landmarks = self._landmarks_from(est)
        return SmootherUpdate(iterations=iters, time_ms=dt_ms, error=float(result.getError()), landmarks=len(self.lm_key),
                              new_landmarks=new_keys, dropped_observations=dropped, removed_observations=len(remove))

    def _update_with_qr(self):
        """Finish an update whose Cholesky solve failed, with QR.

        Cholesky factorises the normal equations, whose condition number is the square of the
        Jacobian's; after a stretch of weak visual constraints (a window of keyframes that share few
        landmarks) it can fail on a system that is determinate but poorly conditioned ("indeterminate
        linear system"). QR works on the Jacobian itself. It costs about twice as much per update
        (measured on handheld_loop), so it serves only as the fallback. gtsam's
        BatchFixedLagSmoother has already inserted the new factors and values when its
        optimisation or marginalisation throws (the factors are removed only after the marginals
        are computed), so an update without new input finishes the same step.
        """
        params = self.smoother.params()
        params.setLinearSolverType("MULTIFRONTAL_QR")
        try:
            result = self.smoother.update()
        finally:
            params.setLinearSolverType("MULTIFRONTAL_CHOLESKY")
        self.qr_fallbacks += 1
        return result

    def _observations_to_drop(self, seq: int) -> list[int]:
        """Factor slots of the observations that keyframes leaving at this update made of staying landmarks.

        Only with ``leaving_observations: drop``. Marginalising a keyframe together with its
        observations of landmarks that stay in the window joins those landmarks in one dense prior.
        OKVIS drops such observations first to keep that prior sparse; what the keyframe knew about
        the motion then reaches the window through its IMU factor, but what it knew about the
        landmarks is lost, and their depth rests on the window's sightings alone. On the bench
        preset marginalising them lowers the sync live error of handheld_office, drone8_lit and
        spin_hdr_window (the rest level) without a slower update (docs/slam.md, "Leaving
        keyframes' observations"), so it is the default.
        """
        if self.cfg.leaving_observations == "marginalise":
            return []
        horizon = seq - (self.cfg.window_keyframes - 0.5)
        leaving = {X(k) for k in self.kf_ids if self.kf_seq[k] < horizon}
        if not leaving:
            return []
        # a staying landmark must keep two observations (a single ray leaves its depth free)
        staying = {}
        for j, s in self.lm_time.items():
            if s >= horizon and j in self.lm_key:
                kept = [q for q in self.lm_obs.get(j, []) if q >= horizon]
                if len(kept) >= 2:
                    staying[self.lm_key[j]] = j
        graph = self.smoother.getFactors()
        out = []
        for i in range(graph.size()):
            if not graph.exists(i):
                continue
            keys = graph.at(i).keys()
            if len(keys) == 2 and keys[0] in leaving and keys[1] in staying:
                out.append(i)
        for key, j in staying.items():
            self.lm_obs[j] = [q for q in self.lm_obs[j] if q >= horizon]
        return out

    def landmark_estimates(self) -> dict[int, np.ndarray]:
        """World positions (m) of the landmarks in the window after the last update, by landmark id."""
        return self.landmarks

    @property
    def latest(self) -> tuple[int, NavEstimate]:
        k = self.kf_ids[-1]
        return k, self.estimates[k]


@dataclass
class TrackResult:
    """Outcome of :func:`track_frame`: the state, per-observation inlier flags and timing."""

    state: NavEstimate
    inliers: np.ndarray
    iterations: int = 0
    error: float = float("nan")
    extra: dict = field(default_factory=dict)


# Per-frame tracking's priors on the last keyframe's state (rotation rad, position m, velocity m/s):
# about its remaining uncertainty once the smoother has converged.
TRACKING_KF_SIGMAS = (0.003, 0.01, 0.05)


def loose_kf_sigmas(velocity_sigma: float) -> tuple[float, float, float]:
    """Tracking's keyframe priors when the keyframe state is not to be trusted tightly (after a
    restart, and for :func:`track_frame_or_refit`'s second fit): 0.01 rad, 3 cm and
    ``velocity_sigma`` m/s (``tracking.recovery_velocity_sigma``)."""
    return (0.01, 0.03, float(velocity_sigma))


def track_frame(cams: StereoCameras, cfg: BackendConfig, kf_state: NavEstimate,
                pim: gtsam.PreintegratedCombinedMeasurements, guess: NavEstimate, obs: Observations,
                points_world: np.ndarray, *, max_reproj_px: float, kf_sigmas=TRACKING_KF_SIGMAS,
                rotation_prior: tuple[np.ndarray, float] | None = None, use: np.ndarray | None = None) -> TrackResult:
    """Motion-only estimate of the current frame from the IMU and fixed map landmarks.

    Args:
        kf_state: the last keyframe's smoother estimate, held with priors of ``kf_sigmas``
            (rotation rad, position m, velocity m/s: the size of its remaining uncertainty).
        pim: preintegration from the keyframe's time to now (with ``kf_state.bias`` as its bias estimate).
        guess: initial value (the IMU prediction or the RANSAC pose).
        obs: the frame's RANSAC-inlier observations; ``points_world`` (M, 3) their landmarks.
        max_reproj_px: observations with a larger final reprojection error are flagged outliers.
        rotation_prior: optional ``(R_world_body, sigma_rad)`` from the rotation-only 2D-2D model
            (pure rotation: the relative rotation is known, the translation is not).
        use: indices of the observations to optimise with (default all; the cost grows with each
            one); the inlier flags cover all of ``obs``.
    """
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    k0, k1 = 0, 1
    s_rot, s_pos, s_vel = kf_sigmas
    graph.add(gtsam.PriorFactorPose3(X(k0), gtsam.Pose3(kf_state.T_world_body),
                                     gtsam.noiseModel.Diagonal.Sigmas(np.array([s_rot] * 3 + [s_pos] * 3))))
    graph.add(gtsam.PriorFactorVector(V(k0), np.asarray(kf_state.v_world, np.float64), gtsam.noiseModel.Isotropic.Sigma(3, s_vel)))
    graph.add(gtsam.PriorFactorConstantBias(B(k0), kf_state.bias, bias_noise(1e-3, 1e-4)))
    graph.add(gtsam.CombinedImuFactor(X(k0), V(k0), X(k1), V(k1), B(k0), B(k1), pim))
    values.insert(X(k0), gtsam.Pose3(kf_state.T_world_body))
    values.insert(V(k0), np.asarray(kf_state.v_world, np.float64))
    values.insert(B(k0), kf_state.bias)
    values.insert(X(k1), gtsam.Pose3(guess.T_world_body))
    values.insert(V(k1), np.asarray(guess.v_world, np.float64))
    values.insert(B(k1), kf_state.bias)
    if rotation_prior is not None:
        R_wb, sigma = rotation_prior
        big = 1e3  # translation free: only the rotation is constrained
        T = guess.T_world_body.copy()
        T[:3, :3] = R_wb
        graph.add(gtsam.PriorFactorPose3(X(k1), gtsam.Pose3(T), gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma] * 3 + [big] * 3))))
    noise = pixel_noise(cfg)
    # Landmarks are fixed: a tight prior (1 mm) on each keeps them in place while the solver
    # eliminates them cheaply (gtsam's Python API has no pose-only projection factor).
    lm_noise = gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)
    sel = np.arange(len(obs)) if use is None else np.asarray(use, np.int64)
    lm_sel = obs.landmark[sel]
    uniq, first, inv = np.unique(lm_sel, return_index=True, return_inverse=True) if len(sel) else (
        np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
    for u in range(len(uniq)):
        p = np.asarray(points_world[sel[first[u]]], np.float64)
        values.insert(L(u), p)
        graph.add(gtsam.PriorFactorPoint3(L(u), p, lm_noise))
    cal = [c.cal3 for c in cams.cams]
    bps = [c.body_P_sensor for c in cams.cams]
    for k, i in enumerate(sel):
        c = int(obs.cam[i])
        graph.add(gtsam.GenericProjectionFactorCal3_S2(np.asarray(obs.xy[i], np.float64), _noise_for(cfg, obs.shape[i], noise),
                                                       X(k1), L(int(inv[k])), cal[c], False, False, bps[c]))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(cfg.tracking_iterations))
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    est = opt.optimize()
    pose = est.atPose3(X(k1))
    state = NavEstimate(pose.matrix(), np.asarray(est.atVector(V(k1))).copy(), est.atConstantBias(B(k1)))
    inl = np.zeros(len(obs), bool)
    if len(obs):
        T_wb = pose.matrix()
        for c in (0, 1):
            m = obs.cam == c
            if not m.any():
                continue
            T_cw = invert_T(T_wb @ cams.cams[c].T_body_cam)
            inl[m] = reprojection_error(points_world[m], T_cw, cams.cams[c].K, obs.xy[m]) <= max_reproj_px
    return TrackResult(state, inl, iterations=int(opt.iterations()), error=float(opt.error()))


def track_frame_or_refit(cams: StereoCameras, cfg: BackendConfig, kf_state: NavEstimate,
                         pim: gtsam.PreintegratedCombinedMeasurements, guess: NavEstimate, obs: Observations,
                         points_world: np.ndarray, *, max_reproj_px: float, min_inliers: int,
                         loose_kf_sigmas: tuple[float, float, float] | None, kf_sigmas=TRACKING_KF_SIGMAS,
                         rotation_prior: tuple[np.ndarray, float] | None = None,
                         use: np.ndarray | None = None) -> tuple[TrackResult, bool]:
    """:func:`track_frame`, fitted again with the keyframe held by ``loose_kf_sigmas`` when the
    first fit keeps fewer than ``min_inliers`` of at least as many observations (RANSAC found them
    consistent with one pose, the fit did not); the second fit is taken when it keeps
    ``min_inliers``. Returns (result, whether it is the second fit's).

    Vision and the IMU-propagated keyframe state then disagree by more than ``kf_sigmas``
    allow, and one of them is wrong. A keyframe's velocity a few tenths of a m/s off moves the
    prediction by centimetres over the 0.1-0.3 s between frames of a slow machine's async
    processing, and the tight priors reject consistent observations frame after frame until
    tracking is lost (``tracking.refit_on_disagreement``). ``loose_kf_sigmas=None``: no refit.
    """
    tr = track_frame(cams, cfg, kf_state, pim, guess, obs, points_world, max_reproj_px=max_reproj_px, kf_sigmas=kf_sigmas,
                     rotation_prior=rotation_prior, use=use)
    if loose_kf_sigmas is None or len(obs) < min_inliers or int(tr.inliers.sum()) >= min_inliers:
        return tr, False
    loose = track_frame(cams, cfg, kf_state, pim, guess, obs, points_world, max_reproj_px=max_reproj_px,
                        kf_sigmas=loose_kf_sigmas, rotation_prior=rotation_prior, use=use)
    if int(loose.inliers.sum()) >= min_inliers:
        return loose, True
    return tr, False
