"""IMU preintegration (gtsam) and visual-inertial initialisation.

Frames and units: the body frame B is the IMU frame; the world frame W is gravity-aligned with z up
(gravity ``(0, 0, -9.81)`` m/s², gtsam's ``MakeSharedU``); ``T_world_body`` maps body points into the
world. The accelerometer measures specific force ``R_WB^T (a_W - g_W)`` (+9.81 up at rest), the
gyroscope the body angular rate (rad/s); biases are added to both. Times are int64 µs.

Noise: the rig's :class:`~aerovis_slam.calib.ImuNoise` holds continuous-time densities (Kalibr names),
which are exactly what gtsam's covariances expect (``sigma^2`` per unit time; gtsam divides by ``dt``).

Example (noise-free IMU of a constant-acceleration motion, integrated exactly):
    >>> from aerovis_slam.measurements import ImuSamples
    >>> t = np.arange(0, 200_001, 5_000)                      # 0.2 s at 200 Hz
    >>> acc = np.tile([1.0, 0.0, 9.81], (len(t), 1))          # 1 m/s² forward, level
    >>> stream = ImuStream(ImuSamples(t, np.zeros((len(t), 3)), acc))
    >>> pim = new_preintegration(preintegration_params(None))
    >>> stream.integrate(pim, 0, 200_000)
    >>> round(float(pim.deltaPij()[0]), 6), round(pim.deltaTij(), 6)  # 0.5 * 1 * 0.2²
    (0.02, 0.2)
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from ..calib import ImuNoise
from ..geometry import so3_exp
from ..measurements import ImuSamples

GRAVITY = 9.81


def preintegration_params(noise: ImuNoise | None, gravity: float = GRAVITY,
                          integration_sigma: float = 1e-4) -> gtsam.PreintegrationCombinedParams:
    """gtsam combined-IMU parameters for z-up gravity from Kalibr-style noise densities.

    Args:
        noise: the rig's IMU noise (None: :class:`ImuNoise` defaults, a BMI160-like IMU).
        integration_sigma: velocity-integration uncertainty (gtsam's ``integrationCovariance``),
            small: it models the discretisation error of the preintegration itself.
    """
    noise = noise or ImuNoise()
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(gravity)
    I3 = np.eye(3)
    p.setAccelerometerCovariance(I3 * noise.accelerometer_noise_density ** 2)
    p.setGyroscopeCovariance(I3 * noise.gyroscope_noise_density ** 2)
    p.setBiasAccCovariance(I3 * noise.accelerometer_random_walk ** 2)
    p.setBiasOmegaCovariance(I3 * noise.gyroscope_random_walk ** 2)
    p.setIntegrationCovariance(I3 * integration_sigma ** 2)
    return p


def new_preintegration(params: gtsam.PreintegrationCombinedParams,
                       bias: gtsam.imuBias.ConstantBias | None = None) -> gtsam.PreintegratedCombinedMeasurements:
    """An empty preintegration with the given bias estimate (default zero)."""
    return gtsam.PreintegratedCombinedMeasurements(params, bias if bias is not None else gtsam.imuBias.ConstantBias())


class ImuStream:
    """The IMU samples of a sequence with integration between arbitrary times.

    Measurements are linearly interpolated between samples and each integration step uses the mean
    of its two end values (the midpoint rule: second-order accurate, where holding the older sample
    is first-order; it matters at 200 Hz during 700 deg/s shakes). Before the first and after the
    last sample the nearest sample is held.

    Args:
        imu: all samples (sorted, strictly increasing ``t``).
        max_gap_us: spacing above which :meth:`gaps` reports missing samples.
    """

    def __init__(self, imu: ImuSamples, max_gap_us: int = 20_000):
        self.t = np.asarray(imu.t, np.int64)
        self.gyro = np.asarray(imu.gyro, np.float64)
        self.acc = np.asarray(imu.acc, np.float64)
        self.max_gap_us = int(max_gap_us)
        if len(self.t) == 0:
            raise ValueError("ImuStream needs at least one sample")

    @property
    def t_first(self) -> int:
        return int(self.t[0])

    @property
    def t_last(self) -> int:
        return int(self.t[-1])

    def covered_until(self, now_us: int) -> int:
        """Newest sample time at or before ``now_us`` (what a live system has received by then)."""
        i = int(np.searchsorted(self.t, now_us, side="right")) - 1
        return int(self.t[max(i, 0)])

    def sample(self, t_us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Linearly interpolated (acc, gyro) at times (N,) µs, held constant outside the samples."""
        tq = np.asarray(t_us, np.float64)
        acc = np.stack([np.interp(tq, self.t, self.acc[:, k]) for k in range(3)], axis=-1)
        gyro = np.stack([np.interp(tq, self.t, self.gyro[:, k]) for k in range(3)], axis=-1)
        return acc, gyro

    def integrate(self, pim: gtsam.PreintegratedCombinedMeasurements, t0_us: int, t1_us: int) -> None:
        """Add the motion between ``t0_us`` and ``t1_us`` (µs, t1 >= t0) to ``pim``."""
        if t1_us <= t0_us:
            return
        i0 = int(np.searchsorted(self.t, t0_us, side="right"))
        i1 = int(np.searchsorted(self.t, t1_us, side="left"))
        knots = np.concatenate([[t0_us], self.t[i0:i1], [t1_us]]).astype(np.int64)
        acc, gyro = self.sample(knots)
        acc_mid = 0.5 * (acc[1:] + acc[:-1])
        gyro_mid = 0.5 * (gyro[1:] + gyro[:-1])
        dts = np.diff(knots) * 1e-6
        # gtsam rotates each step's acceleration with the attitude at the step's start; handing it the
        # mid-step acceleration expressed in the start frame (rotated by half the step's rotation)
        # makes the step second-order accurate: 12x less position error on a 700 deg/s shake at 200 Hz.
        acc_in = np.einsum("nij,nj->ni", so3_exp(gyro_mid * (0.5 * dts)[:, None]), acc_mid)
        for a, w, dt in zip(acc_in, gyro_mid, dts):
            if dt > 0:
                pim.integrateMeasurement(a, w, dt)

    def gaps(self, t0_us: int, t1_us: int) -> list[tuple[int, int]]:
        """Sample spacings longer than ``max_gap_us`` that overlap ``[t0_us, t1_us]``: (start, end) µs."""
        i0 = max(int(np.searchsorted(self.t, t0_us, side="right")) - 1, 0)
        i1 = min(int(np.searchsorted(self.t, t1_us, side="left")) + 1, len(self.t))
        seg = self.t[i0:i1]
        d = np.diff(seg)
        bad = np.flatnonzero(d > self.max_gap_us)
        return [(int(seg[k]), int(seg[k + 1])) for k in bad]

    def mean_acc(self, t0_us: int, t1_us: int) -> np.ndarray:
        """Mean accelerometer reading over ``[t0_us, t1_us]`` (nearest sample when none inside)."""
        m = (self.t >= t0_us) & (self.t <= t1_us)
        if not m.any():
            return self.sample(np.array([t0_us]))[0][0]
        return self.acc[m].mean(axis=0)


def standstill_chi2(stream: ImuStream, t0_us: int, t1_us: int, gyro_at_rest: np.ndarray, acc_at_rest: np.ndarray,
                    noise: ImuNoise | None, *, gyro_floor_rad_s: float, acc_floor_m_s2: float,
                    reference_window_s: float | None = None) -> tuple[float, np.ndarray, np.ndarray, float]:
    """How well the IMU samples in ``[t0_us, t1_us]`` fit a body at rest: a chi-square statistic with 6
    degrees of freedom (``inf`` without samples).

    At rest the mean gyroscope reading is its bias and the mean specific force is the accelerometer's
    bias plus gravity seen from the body, ``R_world_body^T (0, 0, g)``: the whole vector, not its length,
    so that a horizontal push, which barely changes the length, is caught. Each axis's difference is
    divided by its variance: the white noise averaged over the window (``density^2 / T``, ``T`` the
    samples' count over the IMU rate), the same for a reference that is itself a window's mean, and a
    floor for what the expected readings get wrong (bias and attitude estimates). A constant velocity
    fits as well as rest does: the caller rules it out (the odometry's speed gate).

    Args:
        stream: the IMU samples.
        t0_us, t1_us: the window (µs).
        gyro_at_rest, acc_at_rest: (3,) the readings expected at rest (rad/s, m/s²): from the estimates
            (``b_g`` and ``b_a + R_world_body^T (0, 0, g)``) or an earlier window's means at rest.
        noise: the IMU's noise densities (None: :class:`~aerovis_slam.calib.ImuNoise` defaults).
        gyro_floor_rad_s, acc_floor_m_s2: the floors (1 sigma per axis) in rad/s and m/s².
        reference_window_s: the expected readings are means over a window this long (s; None: exact).
    Returns:
        ``(chi2, gyro_mean, acc_mean, window_s)``: the statistic, this window's mean readings and length.
    """
    noise = noise or ImuNoise()
    m = (stream.t >= t0_us) & (stream.t <= t1_us)
    n = int(m.sum())
    if n == 0:
        return float("inf"), np.full(3, np.nan), np.full(3, np.nan), 0.0
    dt_s = float(np.median(np.diff(stream.t))) * 1e-6 if len(stream.t) > 1 else 1.0 / noise.update_rate
    window_s = n * dt_s  # the noise of a mean of n samples is density / sqrt(n dt)
    gyro_mean, acc_mean = stream.gyro[m].mean(axis=0), stream.acc[m].mean(axis=0)
    d_gyro, d_acc = gyro_mean - np.asarray(gyro_at_rest, np.float64), acc_mean - np.asarray(acc_at_rest, np.float64)
    inv_t = 1.0 / window_s + (1.0 / reference_window_s if reference_window_s else 0.0)
    var_gyro = noise.gyroscope_noise_density ** 2 * inv_t + gyro_floor_rad_s ** 2
    var_acc = noise.accelerometer_noise_density ** 2 * inv_t + acc_floor_m_s2 ** 2
    return float(d_gyro @ d_gyro / var_gyro + d_acc @ d_acc / var_acc), gyro_mean, acc_mean, window_s


def rotation_aligning(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation ``R`` with ``R a/|a| = b/|b|`` (3, 3)."""
    a = np.asarray(a, np.float64) / np.linalg.norm(a)
    b = np.asarray(b, np.float64) / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if c < -1 + 1e-12:  # opposite: rotate by pi about any axis orthogonal to a
        axis = np.cross(a, [1.0, 0, 0]) if abs(a[0]) < 0.9 else np.cross(a, [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def gravity_rotation_from_acc(acc_mean: np.ndarray) -> np.ndarray:
    """``R_world_body`` with zero yaw whose up axis matches a resting accelerometer reading (3, 3).

    At rest the accelerometer reads ``R_WB^T (0, 0, +g)``; the rotation taking that body vector to
    world +z fixes roll and pitch (yaw is unobservable and set by the minimal rotation).
    """
    return rotation_aligning(acc_mean, np.array([0.0, 0.0, 1.0]))


@dataclass
class Alignment:
    """Result of :func:`align_visual_inertial`.

    Attributes:
        R_world_vision: (3, 3) rotation from the vision frame V (first body pose) to the gravity-aligned world.
        velocities: (N, 3) body velocities in the vision frame V (m/s), one per frame.
        gyro_bias: (3,) rad/s.
        gravity_norm: norm of the unconstrained gravity estimate (m/s²; ~9.81 when the motion fits).
        residual_m: RMS position residual of the fit (m).
        tilt_sigma_deg, velocity_sigma: 1-sigma uncertainty of the gravity direction (deg) and of the
            last velocity (m/s, largest axis), from the least-squares covariance with the residual
            as the visual position noise (white noise assumed: a lower bound for correlated errors).
    """

    R_world_vision: np.ndarray
    velocities: np.ndarray
    gyro_bias: np.ndarray
    gravity_norm: float
    residual_m: float
    tilt_sigma_deg: float = float("nan")
    velocity_sigma: float = float("nan")


def _preintegrations(stream: ImuStream, params, starts, ends, bias_gyro):
    """One preintegration per span ``starts[i] -> ends[i]`` (µs) with the gyro bias ``bias_gyro``."""
    bias = gtsam.imuBias.ConstantBias(np.zeros(3), np.asarray(bias_gyro, np.float64))
    pims = []
    for a, b in zip(starts, ends):
        pim = new_preintegration(params, bias)
        stream.integrate(pim, int(a), int(b))
        pims.append(pim)
    return pims


@dataclass
class VelocityChangeGravity:
    """Result of :func:`gravity_from_velocity_change`.

    Attributes:
        gravity_vision: (3,) gravity in the vision frame V (m/s², pointing down; its norm is a check).
        t_start_us, t_end_us: the two frames whose velocities were differenced.
        tilt_sigma_deg: 1-sigma direction error from the two velocity fits' residuals.
    """

    gravity_vision: np.ndarray
    t_start_us: int
    t_end_us: int
    tilt_sigma_deg: float

    @property
    def R_world_vision(self) -> np.ndarray:
        """(3, 3) the smallest rotation taking ``gravity_vision`` to world down (yaw left free), as
        :attr:`Alignment.R_world_vision`."""
        return rotation_aligning(self.gravity_vision, np.array([0.0, 0.0, -1.0]))


def gravity_from_velocity_change(t_us: np.ndarray, T_vision_body: np.ndarray, tracked: np.ndarray, stream: ImuStream,
                                 params: gtsam.PreintegrationCombinedParams, *, end_span_s: float = 0.3,
                                 min_span_s: float = 0.5) -> VelocityChangeGravity | None:
    """Gravity in the vision frame from the velocity change over a stretch of visual tracking.

    Between two frames a and b the body's velocity changes by gravity and by the specific force the
    accelerometer measures, rotated into V with the frames' rotations (before initialisation those
    come from the gyroscope):

        ``v_b - v_a = g_V (t_b - t_a) + sum_k R_k dv_k,k+1``

    (``dv`` is the preintegrated velocity change between consecutive frames, zero bias). The two
    velocities come from the visual positions: a quadratic fit over the tracked frames within
    ``end_span_s / 2`` on either side of a and of b, whose slope at a (b) is that frame's velocity
    (the quadratic term takes the path's curvature). Unlike the
    alignment's double integration over a few tenths of a second (:func:`align_visual_inertial`),
    this uses the whole stretch, and a handheld start's motion, which makes the accelerometer's mean
    direction over the first 0.2 s 1.4-19 deg off gravity on the bench preset, enters only through the
    two end velocities (``v_b - v_a`` over ``t_b - t_a``: 0.1 m/s of velocity error over 1.5 s is
    0.4 deg).

    Args:
        t_us: (N,) frame times (µs, increasing). T_vision_body: (N, 4, 4) poses in V, every frame
            (the rotations of untracked frames are the gyroscope's as well).
        tracked: (N,) bool, whose positions are visual.
        end_span_s: width of the velocity fits (s). min_span_s: shortest ``t_b - t_a`` (s).
    Returns:
        the estimate, or None when the tracked frames do not cover both ends (at least four in each
        fit, on both sides of a and b) or ``t_b - t_a < min_span_s``.
    """
    t_us = np.asarray(t_us, np.int64)
    T = np.asarray(T_vision_body, np.float64)
    tracked = np.asarray(tracked, bool)
    if len(t_us) < 6 or tracked.sum() < 6:
        return None
    half = int(end_span_s * 0.5e6)
    tt = t_us[tracked]
    ia = int(np.searchsorted(t_us, tt[0] + half))          # first frame with half a span of tracking before it
    ib = int(np.searchsorted(t_us, tt[-1] - half, side="right")) - 1  # last with half a span after it
    if ia >= len(t_us) or ib <= ia or (t_us[ib] - t_us[ia]) * 1e-6 < min_span_s:
        return None

    def velocity(i: int) -> tuple[np.ndarray, float] | None:
        sel = tracked & (np.abs(t_us - t_us[i]) <= half)
        if sel.sum() < 4 or not (t_us[sel] < t_us[i]).any() or not (t_us[sel] > t_us[i]).any():
            return None
        dt = (t_us[sel] - t_us[i]) * 1e-6
        # p = p_i + v_i dt + a dt²/2: the quadratic term takes the path's curvature, so the slope at
        # frame i stays unbiased when tracking covers the window unevenly (for an even window it is
        # the straight-line fit's slope, at the same variance)
        A = np.stack([np.ones_like(dt), dt, 0.5 * dt * dt], axis=1)
        x, *_ = np.linalg.lstsq(A, T[sel, :3, 3], rcond=None)
        resid = A @ x - T[sel, :3, 3]
        dof = max(int(sel.sum()) - 3, 1)
        sigma_pos2 = float(np.sum(resid ** 2)) / (3 * dof)  # per axis
        cov = np.linalg.pinv(A.T @ A)
        return x[1], sigma_pos2 * float(cov[1, 1])            # velocity at frame i, its variance per axis

    fa, fb = velocity(ia), velocity(ib)
    if fa is None or fb is None:
        return None
    dv = np.zeros(3)
    zero = gtsam.imuBias.ConstantBias()
    for k in range(ia, ib):
        pim = new_preintegration(params, zero)
        stream.integrate(pim, int(t_us[k]), int(t_us[k + 1]))
        dv += T[k, :3, :3] @ np.asarray(pim.deltaVij())
    span = (t_us[ib] - t_us[ia]) * 1e-6
    g = (fb[0] - fa[0] - dv) / span
    sigma_g = np.sqrt(fa[1] + fb[1]) / span  # per axis (m/s²)
    tilt_sigma = float(np.degrees(sigma_g / max(float(np.linalg.norm(g)), 1e-9)))
    return VelocityChangeGravity(gravity_vision=g, t_start_us=int(t_us[ia]), t_end_us=int(t_us[ib]),
                                 tilt_sigma_deg=tilt_sigma)


def align_visual_inertial(t_us: np.ndarray, T_vision_body: np.ndarray, stream: ImuStream,
                          params: gtsam.PreintegrationCombinedParams, *, gravity: float = GRAVITY) -> Alignment:
    """Gravity direction, velocities and gyroscope bias from metric visual poses and the IMU.

    Stereo gives metric poses ``T_V_B(t_i)`` in the vision frame V, so (unlike monocular VINS) no
    scale is estimated. Steps:

    1. gyro bias: Gauss-Newton on ``sum |Log((R_i dR_ij(b_g))^T R_j)|^2`` (Jacobian by re-integration);
    2. linear least squares for the first velocity ``v_0`` and gravity ``g_V`` from, per frame k,
       ``p_k - p_0 = v_0 dt + g dt²/2 + R_0 dp_0k`` (``dt = t_k - t_0``; ``p_0`` exact), and the
       covariance of the solution (the residual taken as white position noise);
    3. ``g_V`` rescaled to ``gravity``, ``v_0`` re-solved with it fixed, and ``v_k = v_0 + g dt + R_0 dv_0k``;
    4. ``R_world_vision`` is the smallest rotation taking ``g_V`` to ``(0, 0, -gravity)``.

    The accelerometer bias is left at zero (it is not separable from gravity over a short window).

    Args:
        t_us: (N,) frame times, N >= 3. T_vision_body: (N, 4, 4) poses.
    Returns:
        :class:`Alignment` (velocities in V; rotate them with ``R_world_vision``).
    """
    t_us = np.asarray(t_us, np.int64)
    T = np.asarray(T_vision_body, np.float64)
    n = len(t_us)
    if n < 3:
        raise ValueError(f"visual-inertial alignment needs at least 3 frames, got {n}")
    R = T[:, :3, :3]
    p = T[:, :3, 3]
    # 1. gyroscope bias
    bg = np.zeros(3)
    for _ in range(2):
        def residuals(b):
            res = []
            for k, pim in enumerate(_preintegrations(stream, params, t_us[:-1], t_us[1:], b)):
                dR = pim.deltaRij().matrix()
                res.append(gtsam.Rot3.Logmap(gtsam.Rot3((R[k] @ dR).T @ R[k + 1])))
            return np.concatenate(res)

        r0 = residuals(bg)
        eps = 1e-4
        J = np.stack([(residuals(bg + eps * e) - r0) / eps for e in np.eye(3)], axis=1)
        step, *_ = np.linalg.lstsq(J, -r0, rcond=None)
        bg = bg + step
        if np.linalg.norm(step) < 1e-7:
            break
    # 2. v_0 and gravity from the displacements since the first frame (one preintegration t_0 -> t_k
    # per frame): p_k - p_0 - R_0 dp_0k = v_0 dt + g dt²/2. Consecutive pairs 20 ms apart would turn
    # centimetres of visual position noise into metres per second of velocity noise (measured: 0.9
    # m/s off on a slow handheld start); over the whole window the same noise costs a few cm/s.
    # p_0 is taken as exact: the runtime's vision frame is the first tracked pose. (Estimating it
    # too was measured worse on the bench preset: SuperLitE ATE up on 5 of 7 sequences.)
    pims = _preintegrations(stream, params, [t_us[0]] * (n - 1), t_us[1:], bg)
    dts = np.array([pim.deltaTij() for pim in pims])
    I3 = np.eye(3)
    A = np.concatenate([np.hstack([I3 * dt, 0.5 * I3 * dt * dt]) for dt in dts])  # (3(n-1), 6)
    y = np.concatenate([p[k + 1] - p[0] - R[0] @ pim.deltaPij() for k, pim in enumerate(pims)])
    x, *_ = np.linalg.lstsq(A, y, rcond=None)
    g = x[3:]
    g_norm = float(np.linalg.norm(g))
    # covariance of (v_0, g) with the fit's residual as white position noise
    s2 = float(np.sum((A @ x - y) ** 2)) / max(len(y) - 6, 1)
    try:
        cov = s2 * np.linalg.inv(A.T @ A)
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.inf)
    u = g / max(g_norm, 1e-9)
    P = I3 - np.outer(u, u)  # the direction changes with the components across g
    tilt_sigma = float(np.degrees(np.sqrt(max(np.trace(P @ cov[3:, 3:] @ P) / 2.0, 0.0)) / max(g_norm, 1e-9)))
    J = np.hstack([I3, I3 * dts[-1]])  # v_last = v_0 + g T + R_0 dv (dv known)
    vel_sigma = float(np.sqrt(np.max(np.diag(J @ cov @ J.T))))
    # 3. fix |g| and re-solve v_0; every velocity follows from it and the preintegrated dv
    g = g / max(g_norm, 1e-9) * gravity
    y2 = y - A[:, 3:] @ g
    v0, *_ = np.linalg.lstsq(A[:, :3], y2, rcond=None)
    resid = A[:, :3] @ v0 - y2
    v = np.concatenate([v0[None], np.stack([v0 + g * dt + R[0] @ pim.deltaVij() for dt, pim in zip(dts, pims)])])
    return Alignment(R_world_vision=rotation_aligning(g, np.array([0.0, 0.0, -1.0])), velocities=v,
                     gyro_bias=bg, gravity_norm=g_norm, residual_m=float(np.sqrt(np.mean(resid ** 2))),
                     tilt_sigma_deg=tilt_sigma, velocity_sigma=vel_sigma)
