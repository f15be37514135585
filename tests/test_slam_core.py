"""SLAM core: geometry pieces on exact synthetic cases, IMU preintegration against the simulator,
the gtsam estimator on exact data, the whole pipeline (tiny preset and a small simulated flight),
configuration loading and clean shutdown."""

from __future__ import annotations

import threading

import gtsam
import numpy as np
import pytest

from aerovis_slam.errors import DataError
from aerovis_slam.geometry import interpolate_poses, pose7_to_matrix, project, rotation_angle_deg, so3_exp, transform_points
from aerovis_slam.io.sequence import Sequence
from aerovis_slam.keypoints import Keypoints
from aerovis_slam.measurements import ImuSamples, PoseSamples
from aerovis_slam.sim import SequenceSpec, Simulator, write_sequence
from aerovis_slam.sim.cache import ensure_preset
from aerovis_slam.sim.rig import load_rig
from aerovis_slam.slam.backend import (KeyframeSmoother, NavEstimate, Observations, loose_kf_sigmas, track_frame,
                                      track_frame_or_refit)
from aerovis_slam.slam.cameras import StereoCameras
from aerovis_slam.slam.config import SlamConfig, load_config
from aerovis_slam.slam.detectors import StereoClassicalDetector
from aerovis_slam.slam.frontend import project_landmarks
from aerovis_slam.slam.odometry import StereoInertialOdometry
from aerovis_slam.slam.imu import (ImuStream, align_visual_inertial, gravity_from_velocity_change, new_preintegration,
                                  preintegration_params, standstill_chi2)
from aerovis_slam.slam.pipeline import check_frame_slots, run_slam
from aerovis_slam.slam.ransac import (bearings, pnp_ransac, position_given_rotation, project_points, reprojection_error,
                                      rotation_error_deg, rotation_ransac)
from aerovis_slam.slam.stereo import is_rectified, match_stereo, search_disparity, swapped_pair_message, triangulate
from aerovis_slam.slam.trajectory import ate

K = np.array([[200.0, 0.0, 160.0], [0.0, 200.0, 120.0], [0.0, 0.0, 1.0]])


# -- geometry ------------------------------------------------------------------------------------
def test_triangulation_exact_and_validity():
    rng = np.random.default_rng(0)
    T_1_0 = np.eye(4)
    T_1_0[:3, :3] = so3_exp(np.array([0.01, -0.02, 0.005]))  # a slightly verged, unrectified pair
    T_1_0[:3, 3] = [-0.12, 0.003, 0.001]
    p0 = rng.uniform([-2, -1.5, 1.0], [2, 1.5, 8.0], (50, 3))
    xy0 = project_points(p0, np.eye(4), K)
    xy1 = project_points(p0, T_1_0, K)
    pts, ok = triangulate(xy0, xy1, K, K, T_1_0)
    assert ok.all()
    # noise-free DLT is exact up to floating point (conditioning ~ depth / baseline)
    np.testing.assert_allclose(pts, p0, atol=1e-8)
    # a pair whose rays cross behind the cameras, and one off by 5 px, are invalid
    bad1 = xy1.copy()
    bad1[0, 0] = xy0[0, 0] + 30.0  # negative disparity: the point would lie behind the cameras
    bad1[1, 1] += 5.0              # 5 px off the epipolar line: reprojection error > 2 px
    _, ok2 = triangulate(xy0, bad1, K, K, T_1_0)
    assert not ok2[0] and not ok2[1] and ok2[2:].all()


def test_stereo_row_search_recovers_subpixel_disparity():
    # A blurred random texture and the same texture shifted by 6.4 px: the rectified right view of a
    # fronto-parallel plane. Correlation with a parabola fit recovers the fraction; the tolerance
    # (0.15 px) is the peak-interpolation bias of NCC on a 9x9 patch of smooth texture.
    import cv2

    rng = np.random.default_rng(1)
    tex = cv2.GaussianBlur(rng.random((80, 200)).astype(np.float32), (0, 0), 1.2)
    d_true = 6.4
    M = np.float32([[1, 0, -d_true], [0, 1, 0]])
    right = cv2.warpAffine(tex, M, (200, 80), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    xy = np.stack(np.meshgrid(np.arange(40, 180, 12), np.arange(15, 65, 10)), -1).reshape(-1, 2).astype(np.float64)
    # keypoints at sub-pixel positions (as the detectors give them): the disparity of a shifted
    # texture is the same at every position, whatever the fraction of the pixel
    xy += rng.uniform(-0.5, 0.5, xy.shape)
    d, ok = search_disparity(tex, right, xy, min_disparity=1, max_disparity=30, min_support=0.0)
    assert ok.mean() > 0.8
    assert np.abs(d[ok] - d_true).max() < 0.15


def test_a_rectified_pair_with_cam1_on_the_left_is_matched_without_the_row_search():
    """The row search looks for the right view's match left of the left keypoint, so a rectified rig
    whose cam0/cam1 are swapped (cam1 0.1 m to the left) must not take it: it is matched by the
    general epipolar search, which triangulates exact projections exactly, and a warning names the
    swap. The correct layout keeps the row search and gives no warning."""
    K = np.array([[200.0, 0, 120], [0, 200.0, 90], [0, 0, 1]])
    T_right_left = np.eye(4)
    T_right_left[0, 3] = -0.1  # cam1 at +0.1 m along cam0's x: the right camera
    T_swapped = np.linalg.inv(T_right_left)
    assert is_rectified(K, K, T_right_left) and swapped_pair_message(K, K, T_right_left) is None
    assert not is_rectified(K, K, T_swapped)
    assert "swap cam0 and cam1" in swapped_pair_message(K, K, T_swapped)
    rng = np.random.default_rng(0)
    pts0 = np.column_stack([rng.uniform(-1, 1, 30), rng.uniform(-0.7, 0.7, 30), rng.uniform(2, 6, 30)])
    uv0, _ = project(pts0, K)
    uv1, _ = project(transform_points(T_swapped, pts0), K)
    desc = rng.normal(size=(30, 32)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    kp0 = Keypoints(uv0.astype(np.float32), np.ones(30, np.float32), desc)
    kp1 = Keypoints(uv1.astype(np.float32), np.ones(30, np.float32), desc)
    images = (np.zeros((180, 240), np.float32), np.zeros((180, 240), np.float32))  # the row search would find nothing here
    idx, pts, xy1 = match_stereo(kp0, kp1, K, K, T_swapped, min_similarity=0.9, images=images)
    assert len(idx) == 30
    # float32 pixels (~2e-5 px) on disparities of 3.3 px and more: depth exact to ~1e-5 of itself
    assert (np.linalg.norm(pts - pts0[idx], axis=1) < 1e-4 * pts0[idx, 2]).all()


def test_pnp_ransac_rejects_known_outliers():
    rng = np.random.default_rng(2)
    pw = rng.uniform([-2, -1.5, 3], [2, 1.5, 7], (80, 3))
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array([0.05, -0.1, 0.02]))
    T[:3, 3] = [0.2, -0.1, 0.3]
    xy = project_points(pw, T, K)
    outliers = np.zeros(80, bool)
    outliers[rng.choice(80, 24, replace=False)] = True  # 30 % gross outliers, 15-40 px off
    xy[outliers] += rng.uniform(15, 40, (24, 2)) * rng.choice([-1, 1], (24, 2))
    ok, T_est, inl = pnp_ransac(pw, xy, K, reproj_px=2.0, iterations=200)
    assert ok
    np.testing.assert_array_equal(inl, ~outliers)  # every outlier is more than 2 px off any consistent pose
    # the inliers are exact, so the refined pose is exact up to the LM tolerance
    assert np.abs(T_est - T).max() < 1e-6


def test_reprojection_error_is_the_pixel_distance_and_inf_where_undefined():
    T_cam_world = np.eye(4)
    T_cam_world[:3, 3] = [0.0, 0.0, 1.0]  # world origin 1 m in front of the camera
    pw = np.array([[0.0, 0.0, 1.0],  # z = 2 m: projects to the principal point
                   [0.5, 0.0, 1.0],  # z = 2 m: fx * 0.5 / 2 px right of it
                   [0.0, 0.0, -3.0],  # z = -2 m: behind the camera
                   [np.nan, 0.0, 1.0]])
    pp = K[:2, 2]
    xy = np.array([pp + [3.0, 4.0], pp + [K[0, 0] * 0.25, 0.0], pp, pp])
    e = reprojection_error(pw, T_cam_world, K, xy)
    np.testing.assert_allclose(e[:2], [5.0, 0.0], atol=1e-12)  # a 3-4-5 offset; an exact projection
    assert np.isinf(e[2:]).all()  # behind and undefined points are never inliers


def test_rotation_only_model_on_pure_rotation():
    rng = np.random.default_rng(3)
    b0 = bearings(rng.uniform([0, 0], [320, 240], (60, 2)), K)
    R = so3_exp(np.array([0.03, 0.2, -0.05]))  # 12 degrees
    b1 = b0 @ R.T
    outliers = np.zeros(60, bool)
    outliers[:15] = True
    b1[:15] = bearings(rng.uniform([0, 0], [320, 240], (15, 2)), K)  # random directions
    R_est, inl = rotation_ransac(b0, b1, threshold_rad=np.radians(0.2), rng=np.random.default_rng(0))
    assert inl[15:].all() and not inl[:15].any()
    assert rotation_error_deg(R_est, R) < 1e-6  # Kabsch on exact inliers


def test_position_with_known_rotation_two_cameras():
    rig = load_rig("drone424")
    cams = StereoCameras.from_rig(rig, max_width=424, max_height=240, size_multiple=8)
    rng = np.random.default_rng(4)
    R = so3_exp(np.array([0.1, -0.05, 0.8]))
    p = np.array([1.0, -0.5, 1.2])
    T_wb = np.eye(4)
    T_wb[:3, :3], T_wb[:3, 3] = R, p
    pts_cam = rng.uniform([-2, -1, 2], [2, 1, 6], (40, 3))
    pw = (T_wb @ cams.left.T_body_cam)[:3, :3] @ pts_cam.T
    pw = pw.T + (T_wb @ cams.left.T_body_cam)[:3, 3]
    cam_idx = np.arange(40) % 2
    xy = np.zeros((40, 2))
    for c, cam in enumerate(cams.cams):
        uv, vis = project_landmarks(pw, T_wb, cam, margin_px=1e9)
        xy[cam_idx == c] = uv[cam_idx == c]
    p_est, err = position_given_rotation(pw, xy, cam_idx, [cams.left.K, cams.right.K],
                                         [cams.left.T_body_cam, cams.right.T_body_cam], R, p + 0.3)
    np.testing.assert_allclose(p_est, p, atol=1e-9)
    assert err.max() < 1e-6


def test_position_given_rotation_measures_errors_in_pixels_of_each_axis():
    """Non-square pixels (fx = 2 fy): the reported errors are pixel distances, x scaled by fx and y
    by fy, and the fit weighs each axis by its own focal length. Three points seen from the origin
    (identity rotation and extrinsic), the first observed exactly 1 px low: the least-squares
    position trades that pixel among the three, and the reported error of every point must equal
    its pixel distance recomputed at the returned position."""
    K = np.array([[200.0, 0.0, 160.0], [0.0, 100.0, 120.0], [0.0, 0.0, 1.0]])
    pts = np.array([[0.0, 0.0, 2.0], [0.5, 0.2, 3.0], [-0.4, 0.3, 2.5]])
    xy = np.stack([K[0, 0] * pts[:, 0] / pts[:, 2] + K[0, 2], K[1, 1] * pts[:, 1] / pts[:, 2] + K[1, 2]], axis=1)
    xy[0, 1] += 1.0
    p, err = position_given_rotation(pts, xy, np.zeros(3, np.int64), [K], [np.eye(4)], np.eye(3), np.zeros(3),
                                     huber_px=100.0)
    pc = pts - p
    proj = np.stack([K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2], K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]], axis=1)
    np.testing.assert_allclose(err, np.linalg.norm(proj - xy, axis=1), atol=1e-9)
    assert 0.0 < err[0] < 1.0  # the 1 px offset is shared, not reported as 2 px (fx / fy times too large)


# -- IMU -----------------------------------------------------------------------------------------
def _tiny_sim(imu_noise: bool, rate: float = 1000.0) -> Simulator:
    return Simulator(SequenceSpec("imu", rig="tiny_stereo", trajectory="handheld", trajectory_seed=3, scene_seed=3,
                                  duration_s=1.0, imu_noise=imu_noise, imu_rate_hz=rate))


def test_standstill_statistic_is_chi_square_at_rest_and_rejects_motion():
    """At rest the statistic sums six squared standard normals: over 400 windows of 20 ms with the
    floors at zero its mean is 6 (standard error sqrt(12 / 400) = 0.17; the bound is 4.7 of those) and
    about 0.1 % exceed 22.5, whatever the attitude and biases; against a reference that is itself a
    window's mean (``reference_window_s``) as well. Over the default 0.1 s window with the default
    floors (variances 1.1e-4 (rad/s)² and 0.060 (m/s²)² per axis at the DAVIS IMU's densities), 30
    deg/s of rotation gives ~2500 and 3 m/s² of horizontal acceleration ~150, where the specific force's
    length alone (0.45 m/s² longer) would give ~3.4."""
    from aerovis_slam.calib import ImuNoise

    rng = np.random.default_rng(0)
    noise = ImuNoise(accelerometer_noise_density=0.0448, gyroscope_noise_density=0.00314, update_rate=1000.0)
    R_wb = so3_exp(np.array([0.3, -0.2, 1.0]))  # tilted: gravity is not along body z
    b_acc, b_gyro = np.array([0.1, -0.05, 0.2]), np.array([0.01, 0.0, -0.02])
    n = 8000
    t = np.arange(n, dtype=np.int64) * 1000  # 1 kHz
    sd_acc, sd_gyro = noise.accelerometer_noise_density * np.sqrt(1000.0), noise.gyroscope_noise_density * np.sqrt(1000.0)
    f_rest = R_wb.T @ np.array([0.0, 0.0, 9.81])
    acc_at_rest = b_acc + f_rest  # what the estimates predict (tracking: bias + R_world_body^T g)

    def stream(acc, gyro):
        return ImuStream(ImuSamples(t, gyro + b_gyro + rng.normal(0, sd_gyro, (n, 3)), acc + b_acc + rng.normal(0, sd_acc, (n, 3))))

    rest = stream(np.tile(f_rest, (n, 1)), np.zeros((n, 3)))
    # windows of 20 samples: [k * 20 ms, k * 20 ms + 19 ms]
    exact = np.array([standstill_chi2(rest, k * 20_000, k * 20_000 + 19_000, b_gyro, acc_at_rest, noise, gyro_floor_rad_s=0.0,
                                      acc_floor_m_s2=0.0)[0] for k in range(400)])
    assert abs(exact.mean() - 6.0) < 0.8, exact.mean()
    assert (exact > 22.5).mean() < 0.01
    # against the first 0.1 s's means: both windows' noise counts (variance density^2 (1/T + 1/T_ref))
    _, gyro_ref, acc_ref, ref_s = standstill_chi2(rest, 0, 99_000, b_gyro, acc_at_rest, noise, gyro_floor_rad_s=0.0, acc_floor_m_s2=0.0)
    assert ref_s == pytest.approx(0.1)
    relative = np.array([standstill_chi2(rest, k * 20_000, k * 20_000 + 19_000, gyro_ref, acc_ref, noise, gyro_floor_rad_s=0.0,
                                         acc_floor_m_s2=0.0, reference_window_s=ref_s)[0] for k in range(5, 400)])
    assert abs(relative.mean() - 6.0) < 0.8 * 2, relative.mean()  # the windows share one reference: a looser bound
    kw = dict(gyro_floor_rad_s=0.003, acc_floor_m_s2=0.2)  # the defaults (tracking.still_*)
    assert standstill_chi2(rest, 0, 99_000, b_gyro, acc_at_rest, noise, **kw)[0] < 22.5
    turning = stream(np.tile(f_rest, (n, 1)), np.tile(R_wb.T @ np.radians([0.0, 0.0, 30.0]), (n, 1)))
    assert standstill_chi2(turning, 0, 99_000, b_gyro, acc_at_rest, noise, **kw)[0] > 40 * 22.5
    a_world = np.array([3.0, 0.0, 0.0])
    pushed = stream(np.tile(R_wb.T @ (a_world + [0.0, 0.0, 9.81]), (n, 1)), np.zeros((n, 3)))
    assert abs(np.linalg.norm(a_world + [0.0, 0.0, 9.81]) - 9.81) < 0.46  # the length alone would hardly see it
    assert standstill_chi2(pushed, 0, 99_000, b_gyro, acc_at_rest, noise, **kw)[0] > 3 * 22.5
    assert standstill_chi2(rest, 10**9, 10**9 + 1, b_gyro, acc_at_rest, noise, **kw)[0] == np.inf  # no samples: not at rest


@pytest.mark.parametrize("noise", [False, True])
def test_preintegration_matches_simulator_ground_truth(noise):
    sim = _tiny_sim(noise)
    traj = sim.trajectory
    stream = ImuStream(sim.imu())
    params = preintegration_params(sim.rig.imu)
    t0, t1 = 0.2, 0.7
    pim = new_preintegration(params)
    stream.integrate(pim, int(t0 * 1e6), int(t1 * 1e6))
    start = gtsam.NavState(gtsam.Rot3(traj.rotation(np.array([t0]))[0]), traj.position(np.array([t0]))[0],
                           traj.position(np.array([t0]), 1)[0])
    pred = pim.predict(start, gtsam.imuBias.ConstantBias())
    p_err = np.linalg.norm(pred.position() - traj.position(np.array([t1]))[0])
    v_err = np.linalg.norm(pred.velocity() - traj.position(np.array([t1]), 1)[0])
    r_err = np.radians(rotation_angle_deg(pred.attitude().matrix().T @ traj.rotation(np.array([t1]))[0]))
    # Discretisation (noise-free): midpoint steps of 1 ms on a handheld motion leave sub-millimetre
    # errors; 2 mm, 1 cm/s and 0.01 deg bound them with margin. With noise, gtsam's own propagated
    # covariance (from the rig's noise densities) gives sigma per axis; a 3-D error below
    # 5 sigma * sqrt(3) fails with probability < 1e-4, plus the discretisation bound.
    sig = np.sqrt(np.diag(pim.preintMeasCov()))  # [rotation, position, velocity, ...] per axis
    k = 5.0 * np.sqrt(3.0) if noise else 0.0
    assert r_err <= k * sig[0:3].max() + np.radians(0.01)
    assert p_err <= k * sig[3:6].max() + 0.002
    assert v_err <= k * sig[6:9].max() + 0.01


def test_visual_inertial_alignment_recovers_gravity_and_velocity():
    sim = _tiny_sim(imu_noise=False)
    traj = sim.trajectory
    stream = ImuStream(sim.imu())
    params = preintegration_params(sim.rig.imu)
    t = np.arange(0.1, 0.45, 0.02)
    T = traj.pose_matrix(t)
    T_vb = np.linalg.inv(T[0]) @ T  # the vision frame: the first body pose
    al = align_visual_inertial((t * 1e6).astype(np.int64), T_vb, stream, params)
    # noise-free IMU and exact poses: gravity and velocities are exact up to the discretisation
    # of the preintegration (sub-mm over 20 ms steps): 0.05 m/s^2, 0.1 deg and 1 cm/s bound it.
    assert abs(al.gravity_norm - 9.81) < 0.05
    R_wv_true = T[0][:3, :3]  # world = GT world: the yaw is free, the tilt is not
    up_est = al.R_world_vision.T @ np.array([0.0, 0.0, 1.0])
    up_true = R_wv_true.T @ np.array([0.0, 0.0, 1.0])
    assert np.degrees(np.arccos(np.clip(up_est @ up_true, -1, 1))) < 0.1
    v_true_v = (R_wv_true.T @ traj.position(t, 1).T).T
    assert np.abs(al.velocities - v_true_v).max() < 0.01
    assert np.linalg.norm(al.gyro_bias) < 1e-3


def test_alignment_with_noisy_visual_positions_improves_with_the_window():
    """1 cm of white noise on the visual positions (the size of pre-initialisation stereo tracking).
    Gravity is seen through g t²/2 (4.9 m at 1 s, 0.44 m at 0.3 s), so the tilt error shrinks about
    with the window squared: a 1 s window must stay within a 2 deg tilt and 0.1 m/s (median over 30
    noise draws; measured ~0.2 deg and 0.02 m/s) and do clearly better than the default 0.3 s
    (measured ~3.5 deg; the default trades that for less vision-only drift, see InitConfig). The
    alignment's reported tilt sigma, which gates initialisation, must predict the error."""
    sim = _tiny_sim(imu_noise=True)
    traj = sim.trajectory
    stream = ImuStream(sim.imu())
    params = preintegration_params(sim.rig.imu)
    rng = np.random.default_rng(0)

    def errors(window_s):
        t = np.arange(0.05, 0.05 + window_s, 0.02)
        T = traj.pose_matrix(t)
        T_vb = np.linalg.inv(T[0]) @ T
        R_wv = T[0][:3, :3]
        up_true = R_wv.T @ np.array([0.0, 0.0, 1.0])
        v_true = R_wv.T @ traj.position(t[-1:], 1)[0]
        tilt, dv, sig = [], [], []
        for _ in range(30):
            Tn = T_vb.copy()
            Tn[1:, :3, 3] += rng.normal(0.0, 0.01, (len(t) - 1, 3))  # the first pose defines the frame
            al = align_visual_inertial((t * 1e6).astype(np.int64), Tn, stream, params)
            up = al.R_world_vision.T @ np.array([0.0, 0.0, 1.0])
            tilt.append(np.degrees(np.arccos(np.clip(up @ up_true, -1.0, 1.0))))
            dv.append(np.linalg.norm(al.velocities[-1] - v_true))
            sig.append(al.tilt_sigma_deg)
        # the reported tilt sigma is per axis of a 2-D direction error: RMS error = sqrt(2) sigma
        calibration = np.sqrt(np.mean(np.square(tilt))) / (np.sqrt(2) * np.mean(sig))
        return np.median(tilt), np.median(dv), calibration

    tilt_long, dv_long, cal_long = errors(0.94)
    tilt_default, _, cal_default = errors(SlamConfig().init.window_s)
    assert tilt_long < 2.0 and dv_long < 0.1
    assert tilt_long < 0.5 * tilt_default
    # white noise: the alignment's own covariance predicts its error (within 2x; 30 draws)
    assert 0.5 < cal_long < 2.0 and 0.5 < cal_default < 2.0


def test_gravity_from_the_velocity_change_over_a_tracked_stretch():
    """The initialisation's fallback: gravity = (v_b - v_a - sum R dv) / (t_b - t_a), the end
    velocities fitted to the visual positions, over a handheld path whose accelerometer mean over
    the first 0.2 s (the static-start assumption) is ~8 deg off gravity. Exact poses: the error is
    the preintegration's discretisation and the cubic part of the motion within the +-0.15 s fits
    (measured 0.07 deg; 0.2 deg bounds it), also with a gap in the tracking between the ends. With
    1 cm of white position noise (pre-initialisation stereo tracking) each end velocity is off by
    about 0.01 m / sqrt(sum dt²) = 0.03 m/s per axis, so over the 0.62 s between the ends gravity's
    direction by about 0.4 deg per axis: the median over 30 draws stays under 1 deg and the
    reported sigma predicts the error within 2x. Too short a stretch gives no estimate."""
    sim = _tiny_sim(imu_noise=True)
    traj = sim.trajectory
    stream = ImuStream(sim.imu())
    params = preintegration_params(sim.rig.imu)
    t = np.arange(0.02, 0.98, 0.02)
    t_us = (t * 1e6).astype(np.int64)
    T = traj.pose_matrix(t)
    T_vb = np.linalg.inv(T[0]) @ T  # the vision frame: the first body pose
    up_true = T[0][:3, :3].T @ np.array([0.0, 0.0, 1.0])

    def tilt(g):
        return np.degrees(np.arccos(np.clip((-g / np.linalg.norm(g)) @ up_true, -1.0, 1.0)))

    static = stream.mean_acc(int(t_us[0]), int(t_us[0]) + 200_000)
    assert tilt(-static) > 5.0  # the case the fallback is for: the path accelerates at its start
    tracked = np.ones(len(t), bool)
    est = gravity_from_velocity_change(t_us, T_vb, tracked, stream, params)
    assert est is not None and (est.t_start_us, est.t_end_us) == (180_000, 800_000)
    assert tilt(est.gravity_vision) < 0.2 and abs(np.linalg.norm(est.gravity_vision) - 9.81) < 0.05
    gap = tracked.copy()
    gap[10:30] = False  # 0.22-0.60 s untracked: the fits become uneven, the rotations stay the gyro's
    assert tilt(gravity_from_velocity_change(t_us, T_vb, gap, stream, params).gravity_vision) < 0.2
    rng = np.random.default_rng(0)
    errors, sigmas = [], []
    for _ in range(30):
        Tn = T_vb.copy()
        Tn[1:, :3, 3] += rng.normal(0.0, 0.01, (len(t) - 1, 3))
        e = gravity_from_velocity_change(t_us, Tn, tracked, stream, params)
        errors.append(tilt(e.gravity_vision))
        sigmas.append(e.tilt_sigma_deg)
    assert np.median(errors) < 1.0
    # the sigma is per axis of a 2-D direction error: RMS error = sqrt(2) sigma
    assert 0.5 < np.sqrt(np.mean(np.square(errors))) / (np.sqrt(2) * np.mean(sigmas)) < 2.0
    short = t < 0.6  # 0.18 s to 0.42 s between the ends: below min_span_s
    assert gravity_from_velocity_change(t_us[short], T_vb[short], tracked[short], stream, params) is None


@pytest.mark.parametrize("tracked", [True, False])
def test_initialisation_fallback_takes_gravity_from_the_velocity_change(tracked):
    """Without an accepted alignment by ``init.timeout_s`` the odometry initialises with the
    velocity-change gravity of its pre-initialisation frames (vision frame turned 25 deg from the
    world; exact poses: within 0.2 deg), and that estimate's own tilt sigma, floored at
    ``backend.prior_rollpitch_deg``, as the roll and pitch prior; with no tracked frames it falls back
    to the accelerometer's mean (static start: the path accelerates, more than 5 deg off) and the
    static start's 5 deg prior."""
    sim = _tiny_sim(imu_noise=True)
    traj = sim.trajectory
    cfg = SlamConfig()
    cfg.init.timeout_s = 0.9
    cams = StereoCameras.from_rig(sim.rig, max_width=424, max_height=240, size_multiple=1)
    odo = StereoInertialOdometry(cams, ImuStream(sim.imu()), sim.rig.imu, cfg)
    t = np.arange(0.02, 0.98, 0.02)
    T = traj.pose_matrix(t)
    t_us = [int(round(ti * 1e6)) for ti in t]
    odo.t_first = t_us[0]
    odo.preinit_frames = [(ti, Ti, tracked) for ti, Ti in zip(t_us, np.linalg.inv(T[0]) @ T)]
    odo.state = NavEstimate(np.linalg.inv(T[0]) @ T[-1], np.zeros(3), gtsam.imuBias.ConstantBias())
    R_wv, how, sigma = odo._fallback_gravity()
    R_true = T[0][:3, :3]  # world <- vision (up to yaw)
    if tracked:
        assert "velocity change" in how and _tilt_deg(R_wv, R_true) < 0.2
        expected_prior = max(cfg.backend.prior_rollpitch_deg, sigma)
    else:
        assert "static start" in how and sigma is None and _tilt_deg(R_wv, R_true) > 5.0
        expected_prior = 5.0
    priors = []
    initialize = odo.smoother.initialize
    odo.smoother.initialize = lambda *a, **kw: (priors.append(kw["sigma_rollpitch_rad"]), initialize(*a, **kw))
    odo._try_initialize(t_us[-1], None, None)  # no alignment frames: the timeout decides
    assert odo.initialized
    assert _tilt_deg(odo.state.T_world_body[:3, :3], T[-1][:3, :3]) == pytest.approx(_tilt_deg(R_wv, R_true), abs=1e-6)
    assert priors == [pytest.approx(np.radians(expected_prior))]


@pytest.mark.parametrize("span_s,starts", [(0.94, True), (0.6, False)])
def test_velocity_change_initialisation(span_s, starts):
    """``init.gravity: velocity_change``: once tracking spans ``velocity_change_s`` (0.8 s here) the
    smoother starts with that gravity (exact poses: within 0.2 deg, as its unit test) and a roll and
    pitch prior of the estimate's own sigma, floored at ``backend.prior_rollpitch_deg`` (not the
    static start's 5 deg); before, it waits."""
    sim = _tiny_sim(imu_noise=True)
    traj = sim.trajectory
    cfg = SlamConfig()
    cfg.init.gravity = "velocity_change"
    cfg.init.velocity_change_s = 0.8
    cams = StereoCameras.from_rig(sim.rig, max_width=424, max_height=240, size_multiple=1)
    odo = StereoInertialOdometry(cams, ImuStream(sim.imu()), sim.rig.imu, cfg)
    t = np.arange(0.02, 0.02 + span_s + 1e-9, 0.02)
    T = traj.pose_matrix(t)
    T_v = np.linalg.inv(T[0]) @ T
    t_us = [int(round(ti * 1e6)) for ti in t]
    odo.t_first = t_us[0]
    odo.preinit_frames = [(ti, Ti, True) for ti, Ti in zip(t_us, T_v)]
    odo.state = NavEstimate(T_v[-1].copy(), T[0][:3, :3].T @ traj.position(t[-1:], 1)[0], gtsam.imuBias.ConstantBias())
    est = odo._velocity_change_gravity()
    priors = []
    initialize = odo.smoother.initialize
    odo.smoother.initialize = lambda *a, **kw: (priors.append(kw["sigma_rollpitch_rad"]), initialize(*a, **kw))
    odo._try_initialize(t_us[-1], None, None)
    assert odo.initialized is starts
    if starts:
        assert _tilt_deg(odo.state.T_world_body[:3, :3], T[-1][:3, :3]) < 0.2
        assert priors == [pytest.approx(np.radians(max(cfg.backend.prior_rollpitch_deg, est.tilt_sigma_deg)))]


@pytest.mark.parametrize("check", [True, False])
def test_late_alignment_takes_the_more_certain_velocity_change_gravity(monkeypatch, check):
    """``init.velocity_change_check``: an alignment accepted after 0.94 s of tracking, 8 deg off
    gravity with a claimed sigma of 3 deg (its sigma is a lower bound), gives way to the velocity
    change over those frames (exact poses: sigma near 0, within 0.2 deg), its velocities kept; without
    the check the start keeps the 8 deg."""
    import aerovis_slam.slam.odometry as odometry_mod
    from aerovis_slam.slam.imu import Alignment

    sim = _tiny_sim(imu_noise=True)
    traj = sim.trajectory
    cfg = SlamConfig()
    cfg.init.velocity_change_check = check
    cams = StereoCameras.from_rig(sim.rig, max_width=424, max_height=240, size_multiple=1)
    odo = StereoInertialOdometry(cams, ImuStream(sim.imu()), sim.rig.imu, cfg)
    t = np.arange(0.02, 0.96 + 1e-9, 0.02)
    T = traj.pose_matrix(t)
    T_v = np.linalg.inv(T[0]) @ T
    R_wv = T[0][:3, :3]  # world <- vision (up to yaw)
    t_us = [int(round(ti * 1e6)) for ti in t]
    v_v = (R_wv.T @ traj.position(t, 1).T).T
    odo.t_first = t_us[0]
    odo.preinit_frames = [(ti, Ti, True) for ti, Ti in zip(t_us, T_v)]
    odo.init_frames = [(ti, Ti) for ti, Ti in zip(t_us, T_v)]
    odo.state = NavEstimate(T_v[-1].copy(), v_v[-1], gtsam.imuBias.ConstantBias())
    wrong = so3_exp(np.radians([8.0, 0.0, 0.0])) @ R_wv
    monkeypatch.setattr(odometry_mod, "align_visual_inertial", lambda t, T, stream, params: Alignment(
        wrong, v_v.copy(), np.zeros(3), 9.81, 0.01, tilt_sigma_deg=3.0, velocity_sigma=0.1))
    odo._try_initialize(t_us[-1], None, None)
    assert odo.initialized
    tilt = _tilt_deg(odo.state.T_world_body[:3, :3], T[-1][:3, :3])
    if check:
        assert tilt < 0.2
    else:
        assert tilt == pytest.approx(8.0, abs=0.5)


# -- the estimator on exact data -------------------------------------------------------------------
def _handheld_tracking_setup():
    """A 1.2 s handheld trajectory of the DAVIS stereo rig with its noisy IMU, for the tracking tests:
    (trajectory, default SlamConfig, StereoCameras, ImuStream, preintegration params, T_gt(t) -> (4, 4) T_world_body)."""
    spec = SequenceSpec("est", rig="davis240_stereo", trajectory="handheld", trajectory_seed=7, scene_seed=7, duration_s=1.2)
    sim = Simulator(spec)
    traj = sim.trajectory
    cams = StereoCameras.from_rig(sim.rig, max_width=424, max_height=240, size_multiple=1)

    def T_gt(t):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = traj.rotation(np.array([t]))[0], traj.position(np.array([t]))[0]
        return T

    return traj, SlamConfig(), cams, ImuStream(sim.imu()), preintegration_params(sim.rig.imu), T_gt


def test_smoother_and_tracking_on_exact_observations():
    """Exact observations (0.5 px noise) of landmarks that start 5 cm off (as from stereo) and the
    simulator's noisy DAVIS IMU: the keyframe smoother plus the per-frame tracking follow the ground
    truth. Position and yaw are unobservable in visual-inertial odometry, so the estimate drifts:
    measured 1.2 cm (max) and 0.27 deg over this 1 s, 1.5 m handheld path; the bounds (2 cm, 0.5 deg,
    ~1.3 % of the path) fail for a wrong extrinsic, IMU convention or marginalisation (tens of cm)."""
    traj, cfg, cams, stream, params, T_gt = _handheld_tracking_setup()
    rng = np.random.default_rng(0)
    P = traj.position(np.linspace(0, 1.2, 20))
    lms = rng.uniform(P.min(0) - 4, P.max(0) + 4, (2500, 3))

    def observe(T):
        parts = []
        for c, cam in enumerate(cams.cams):
            uv, vis = project_landmarks(lms, T, cam)
            ids = np.flatnonzero(vis)[:120]
            parts.append(Observations(ids, np.full(len(ids), c, np.int8), uv[ids] + rng.normal(0, 0.5, (len(ids), 2))))
        return Observations.concatenate(parts)

    sm = KeyframeSmoother(cfg.backend, cams, params)
    t0 = 0.1
    kf_state = NavEstimate(T_gt(t0), traj.position(np.array([t0]), 1)[0], gtsam.imuBias.ConstantBias())
    sm.initialize(0, t0, kf_state, sigma_rollpitch_rad=0.01, sigma_vel=0.05, sigma_acc_bias=0.1, sigma_gyro_bias=0.01)
    pim = new_preintegration(params)
    t_prev = int(t0 * 1e6)
    est = {}
    errs_p, errs_r = [], []
    for i in range(1, 50):
        t = t0 + 0.02 * i
        tu = int(round(t * 1e6))
        stream.integrate(pim, t_prev, tu)
        t_prev = tu
        pred = NavEstimate.from_navstate(pim.predict(kf_state.navstate(), kf_state.bias), kf_state.bias)
        obs = observe(T_gt(t))
        pts = np.array([est.get(int(j), lms[j]) for j in obs.landmark])
        state = track_frame(cams, cfg.backend, kf_state, pim, pred, obs, pts, max_reproj_px=3.0).state
        if i % 5 == 0:  # keyframes every 0.1 s
            positions = {int(j): est.get(int(j), lms[j] + rng.normal(0, 0.05, 3)) for j in np.unique(obs.landmark)}
            sm.add_keyframe(i, pim, state, obs, positions)
            est.update(sm.landmark_estimates())
            _, kf_state = sm.latest
            state = kf_state
            pim = new_preintegration(params, kf_state.bias)
        errs_p.append(np.linalg.norm(state.T_world_body[:3, 3] - T_gt(t)[:3, 3]))
        errs_r.append(rotation_angle_deg(state.T_world_body[:3, :3].T @ T_gt(t)[:3, :3]))
    assert max(errs_p) < 0.02
    assert max(errs_r) < 0.5
    assert len(sm.kf_ids) <= cfg.backend.window_keyframes  # older keyframes were marginalised


def test_refit_takes_vision_over_an_overconfident_keyframe_prior():
    """``track_frame_or_refit`` (``tracking.refit_on_disagreement``): the keyframe's velocity is
    1.5 m/s off, so after 0.2 s the IMU prediction is 30 cm from the true pose, while the tight
    keyframe priors (1 cm, 5 cm/s) say it is within ~1.5 cm. 20 exact observations (0.5 px noise)
    of landmarks 1.5-3 m away then lose against the priors: the fit stays far from the truth and
    rejects most of them (measured 5 kept, 19.5 cm off). Held as after a restart (3 cm, 0.5 m/s)
    the keyframe gives way and the fit keeps all 20, within 2 cm (0.5 px at 2 m is ~0.5 cm per
    observation). With a consistent prior, or without loose sigmas, there is no second fit."""
    traj, cfg, cams, stream, params, T_gt = _handheld_tracking_setup()
    rng = np.random.default_rng(0)
    t0, t1 = 0.3, 0.5

    T1 = T_gt(t1)
    cam0 = cams.cams[0]
    z = rng.uniform(1.5, 3.0, 400)  # landmarks in front of the left camera at t1, over its whole view
    uv = rng.uniform([0, 0], [cam0.width, cam0.height], (400, 2))
    pc = np.column_stack([(uv - cam0.K[:2, 2]) / np.diag(cam0.K)[:2] * z[:, None], z])
    T_wc = T1 @ cam0.T_body_cam
    lms = pc @ T_wc[:3, :3].T + T_wc[:3, 3]
    parts = []
    for c, cam in enumerate(cams.cams):
        proj, vis = project_landmarks(lms, T1, cam)
        ids = np.flatnonzero(vis)[:10]
        parts.append(Observations(ids, np.full(len(ids), c, np.int8), proj[ids] + rng.normal(0, 0.5, (len(ids), 2))))
    obs = Observations.concatenate(parts)
    assert len(obs) == 20
    pim = new_preintegration(params)
    stream.integrate(pim, int(t0 * 1e6), int(t1 * 1e6))
    loose = loose_kf_sigmas(cfg.tracking.recovery_velocity_sigma)  # what the runtime's refit uses

    def fits(velocity_error):
        kf = NavEstimate(T_gt(t0), traj.position(np.array([t0]), 1)[0] + velocity_error, gtsam.imuBias.ConstantBias())
        pred = NavEstimate.from_navstate(pim.predict(kf.navstate(), kf.bias), kf.bias)
        guess = NavEstimate(T1, pred.v_world, kf.bias)  # RANSAC's pose, the prediction's velocity
        args = (cams, cfg.backend, kf, pim, guess, obs, lms[obs.landmark])
        tight = track_frame(*args, max_reproj_px=3.0)
        return (tight, track_frame_or_refit(*args, max_reproj_px=3.0, min_inliers=12, loose_kf_sigmas=loose),
                track_frame_or_refit(*args, max_reproj_px=3.0, min_inliers=12, loose_kf_sigmas=None))

    def error_m(r):
        return float(np.linalg.norm(r.state.T_world_body[:3, 3] - T1[:3, 3]))

    tight, (refit, refitted), (plain, plain_refitted) = fits(np.array([1.5, 0.0, 0.0]))
    assert tight.inliers.sum() < 12 and error_m(tight) > 0.10  # the prior wins against vision
    assert refitted and refit.inliers.all() and error_m(refit) < 0.02
    assert not plain_refitted and np.array_equal(plain.state.T_world_body, tight.state.T_world_body)
    tight, (same, refitted), _ = fits(np.zeros(3))
    assert not refitted and tight.inliers.all() and np.array_equal(same.state.T_world_body, tight.state.T_world_body)


@pytest.mark.parametrize("disparity_sigma_px", [None, 0.4])
def test_stereo_pair_factor_weighs_the_disparity(disparity_sigma_px):
    """A new landmark's stereo pair from the row search shares the left keypoint's error; only the
    disparity has its own. With ``backend.disparity_sigma_px`` = s_d the pair is one stereo factor
    (u_l, u_r, v) with that correlation, and the landmark's depth sigma is about Z^2 s_d / (f b);
    without it, two independent projection factors give about Z^2 sqrt(2) s / (f b) (s =
    pixel_sigma), 7.5x more at 0.4 px. Checked on the marginal covariance of a point on the
    optical axis at 4 m seen from one keyframe whose pose is held (1e-6 sigmas; exact
    observations, so the robust loss is quadratic there), against the covariance the measurement
    Jacobians and the 5 m landmark prior give, to 0.5 %."""
    rig = load_rig("davis240_stereo")
    cams = StereoCameras.from_rig(rig, max_width=424, max_height=240, size_multiple=1)
    cfg = SlamConfig().backend
    cfg.disparity_sigma_px = disparity_sigma_px
    sm = KeyframeSmoother(cfg, cams, preintegration_params(rig.imu))
    K, b, Z = cams.left.K, -cams.T_right_left[0, 3], 4.0
    f, s = K[0, 0], cfg.pixel_sigma
    p_world = cams.left.T_body_cam[:3, :3] @ [0.0, 0.0, Z] + cams.left.T_body_cam[:3, 3]
    uL = K[:2, 2].copy()
    uR = uL - [f * b / Z, 0.0]
    obs = Observations(np.array([7, 7]), np.array([0, 1], np.int8), np.stack([uL, uR]), None, np.array([True, True]))
    state = NavEstimate(np.eye(4), np.zeros(3), gtsam.imuBias.ConstantBias())
    sm.initialize(0, 0.0, state, sigma_rollpitch_rad=1e-6, sigma_yaw_rad=1e-6, sigma_pos_m=1e-6, sigma_vel=1.0,
                  sigma_acc_bias=0.1, sigma_gyro_bias=0.01, obs=obs, landmark_positions={7: p_world})
    assert sm.stereo_factors == (0 if disparity_sigma_px is None else 1)
    np.testing.assert_allclose(sm.landmark_estimates()[7], p_world, atol=1e-6)
    cov_world = gtsam.Marginals(sm.smoother.getFactors(), sm.smoother.calculateEstimate()).marginalCovariance(sm.lm_key[7])
    R = cams.left.T_body_cam[:3, :3]
    cov_cam = R.T @ cov_world @ R
    # d(u_l, u_r, v) / d(X, Y, Z) at (0, 0, Z) in the left camera; u_r = f (X - b) / Z + c_x
    J_l, J_r, J_v = [f / Z, 0, 0], [f / Z, 0, f * b / Z ** 2], [0, f / Z, 0]
    if disparity_sigma_px is None:  # (u_l, v_l) and (u_r, v_r), four independent measurements
        J, C = np.array([J_l, J_v, J_r, J_v]), s ** 2 * np.eye(4)
    else:
        J = np.array([J_l, J_r, J_v])
        C = np.array([[s ** 2, s ** 2, 0], [s ** 2, s ** 2 + disparity_sigma_px ** 2, 0], [0, 0, s ** 2]])
    expected = np.linalg.inv(J.T @ np.linalg.inv(C) @ J + np.eye(3) / 5.0 ** 2)
    np.testing.assert_allclose(np.sqrt(np.diag(cov_cam)), np.sqrt(np.diag(expected)), rtol=0.005)
    closed_form = Z ** 2 * (np.sqrt(2) * s if disparity_sigma_px is None else disparity_sigma_px) / (f * b)
    assert np.sqrt(cov_cam[2, 2]) == pytest.approx(closed_form, rel=0.05)  # (the prior: 4 % in the weak case)


def test_stereo_pair_covariance_is_that_of_a_shifted_keypoint():
    """(u_l, u_r, v) = (u + e_u, u - d + e_u + e_d, v + e_v): the sample covariance of 200k draws
    matches :func:`stereo_pair_covariance` for an edge-shaped keypoint error, within 3 % of each
    entry's scale (the sampling error of a covariance at this size is ~0.3 %)."""
    from aerovis_slam.slam.backend import stereo_pair_covariance

    cfg = SlamConfig().backend
    cfg.disparity_sigma_px = 0.5
    shape = np.array([[2.0, 0.8], [0.8, 0.6]])
    rng = np.random.default_rng(1)
    e = rng.multivariate_normal(np.zeros(2), cfg.pixel_sigma ** 2 * shape, 200_000)
    ed = rng.normal(0.0, cfg.disparity_sigma_px, 200_000)
    samples = np.stack([e[:, 0], e[:, 0] + ed, e[:, 1]], axis=1)
    C = stereo_pair_covariance(cfg, shape)
    np.testing.assert_allclose(np.cov(samples.T), C, atol=0.03 * np.abs(C).max())


def test_track_age_shapes_are_those_of_a_random_walk_keypoint():
    """A keypoint whose first sighting is off by ``pixel_sigma`` (edge-shaped) and that then wanders
    like a random walk, ``drift`` px^2 per second (the same shape), has at age ``a`` the covariance
    ``(pixel_sigma^2 + drift * a) * shape``: 100k simulated tracks of 20 ms steps match
    ``pixel_sigma^2 * track_age_shapes(...)`` within 3 % of each entry's scale (sampling error ~0.5 %)
    at 0, 0.2 and 1 s; without the option the shapes are returned as they are."""
    from aerovis_slam.slam.backend import track_age_shapes

    cfg = SlamConfig().backend
    shape = np.array([[2.0, 0.8], [0.8, 0.6]])
    np.testing.assert_array_equal(track_age_shapes(cfg, shape[None], np.array([3.0])), shape[None])  # off by default
    cfg.track_drift_px2_per_s = 1.5
    rng = np.random.default_rng(2)
    n, dt = 100_000, 0.02
    err = rng.multivariate_normal(np.zeros(2), cfg.pixel_sigma ** 2 * shape, n)
    checks = {0: 0.0, 10: 0.2, 50: 1.0}
    for step in range(51):
        if step in checks:
            model = cfg.pixel_sigma ** 2 * track_age_shapes(cfg, shape[None], np.array([checks[step]]))[0]
            np.testing.assert_allclose(np.cov(err.T), model, atol=0.03 * np.abs(model).max())
        err += rng.multivariate_normal(np.zeros(2), cfg.track_drift_px2_per_s * dt * shape, n)
    # a sighting before its landmark's birth (clock jitter) counts as new
    np.testing.assert_allclose(track_age_shapes(cfg, shape[None], np.array([-0.1]))[0], shape)


def test_track_drift_must_not_be_negative(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("backend:\n  track_drift_px2_per_s: -1\n")
    with pytest.raises(DataError, match="track_drift_px2_per_s"):
        load_config(bad)


def test_leaving_observations_must_be_a_known_choice(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("backend:\n  leaving_observations: keep\n")
    with pytest.raises(DataError, match="leaving_observations"):
        load_config(bad)


class _RecordingSmoother:
    """Passes updates on to gtsam's smoother and keeps every factor and initial value ever added."""

    def __init__(self, inner, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values):
        self.inner, self.graph, self.values = inner, graph, values

    def update(self, graph=None, values=None, stamps=None, remove=None):
        if graph is None:
            return self.inner.update()
        self.graph.push_back(graph)
        self.values.insert(values)
        return self.inner.update(graph, values, stamps, remove or [])

    def __getattr__(self, name):
        return getattr(self.inner, name)


@pytest.mark.parametrize("leaving", ["marginalise", "drop"])
def test_marginalising_leaving_observations_keeps_the_full_batch_estimate(leaving):
    """A fixed-lag smoother that marginalises everything it lets go keeps the information of the whole
    history: its newest keyframe sits where a batch optimisation of every factor ever added puts it,
    up to the linearisation points frozen in the marginal prior and the bounded LM iterations
    (measured 0.5-1.0 mm over three seeds; bound 3 mm). ``leaving_observations: drop`` (OKVIS's way)
    throws away the leaving keyframes' sightings of landmarks still in the window, so those
    landmarks' depth rests on the window's keyframes: the newest keyframe moves 15-21 mm from the
    batch estimate (bound: more than 10 mm) and twice as far from the truth (12-16 against 5-8 mm).
    20 keyframes 50 ms apart (2.5 windows of 8) over the handheld path, 60 landmarks a camera with
    0.5 px noise, the simulator's noisy IMU."""
    traj, cfg, cams, stream, params, T_gt = _handheld_tracking_setup()
    cfg.backend.leaving_observations = leaving
    rng = np.random.default_rng(0)
    P = traj.position(np.linspace(0, 1.2, 20))
    lms = rng.uniform(P.min(0) - 4, P.max(0) + 4, (2500, 3))
    everything, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()
    sm = KeyframeSmoother(cfg.backend, cams, params)
    dt, t0 = 0.05, 0.05

    def state_at(t):
        return NavEstimate(T_gt(t), traj.position(np.array([t]), 1)[0], gtsam.imuBias.ConstantBias())

    sm.initialize(0, t0, state_at(t0), sigma_rollpitch_rad=0.01, sigma_vel=0.05, sigma_acc_bias=0.1,
                  sigma_gyro_bias=0.01)
    everything.push_back(sm.smoother.getFactors())  # the priors of the first keyframe
    initial.insert(sm.smoother.calculateEstimate())
    sm.smoother = _RecordingSmoother(sm.smoother, everything, initial)
    for k in range(1, 20):
        pim = new_preintegration(params, sm.latest[1].bias)
        stream.integrate(pim, int(round((t0 + dt * (k - 1)) * 1e6)), int(round((t0 + dt * k) * 1e6)))
        parts = []
        for c, cam in enumerate(cams.cams):
            uv, vis = project_landmarks(lms, T_gt(t0 + dt * k), cam)
            ids = np.flatnonzero(vis)[:60]
            parts.append(Observations(ids, np.full(len(ids), c, np.int8), uv[ids] + rng.normal(0, 0.5, (len(ids), 2))))
        obs = Observations.concatenate(parts)
        positions = {int(j): lms[j] + rng.normal(0, 0.05, 3) for j in np.unique(obs.landmark)}
        sm.add_keyframe(k, pim, state_at(t0 + dt * k), obs, positions)
    assert len(sm.kf_ids) == cfg.backend.window_keyframes  # 11 keyframes and their sightings have left
    batch = gtsam.LevenbergMarquardtOptimizer(everything, initial).optimize()
    k = sm.kf_ids[-1]
    p_window = sm.estimates[k].T_world_body[:3, 3]
    p_batch = batch.atPose3(gtsam.symbol_shorthand.X(k)).translation()
    p_true = T_gt(t0 + dt * k)[:3, 3]
    from_batch = np.linalg.norm(p_window - p_batch)
    if leaving == "marginalise":
        assert from_batch < 0.003
        assert np.linalg.norm(p_window - p_true) < 1.5 * np.linalg.norm(p_batch - p_true)
    else:
        assert from_batch > 0.010


def _tilt_deg(R_est: np.ndarray, R_true: np.ndarray) -> float:
    """Angle (deg) between the estimated and the true gravity direction in the body frame (yaw-free)."""
    return float(np.degrees(np.arccos(np.clip(R_est[2] @ R_true[2], -1.0, 1.0))))


@pytest.mark.parametrize("bundle_adjustment,start", [(True, "alignment"), (True, "static"), (False, "alignment")])
def test_initialisation_bundle_adjustment_corrects_the_alignments_gravity(bundle_adjustment, start):
    """The visual-inertial alignment hands over gravity 8 deg off (as on the bench preset's starts:
    1.7-17 deg). Eight keyframes of vision-only tracking over 0.84 s of a handheld path (vision
    frame = the world turned by 25 deg; poses 1 cm off, landmarks 2 cm off, 0.5 px observations; the
    simulator's noisy DAVIS IMU; the alignment's velocities only for the newest three keyframes) hold
    gravity: with ``init.bundle_adjustment`` the smoother starts with them and the newest state's
    tilt comes within 1 deg of the truth (measured 0.3-0.7 deg over four noise seeds: the prior on
    the oldest keyframe, no tighter than the alignment's 6 deg sigma, still pulls), the keyframes
    are the window and the landmarks move with the estimate. Without it the window is the newest
    frame alone, which keeps the 8 deg. The static-start fallback (gravity from the accelerometer's
    mean, no alignment velocities: all from the keyframe positions' slope, a 10 deg tilt prior) is
    corrected the same way.

    The keyframes before the initialisation then go to the loop closer with the window's poses; the
    first frame's keyframe, which the adjustment leaves out, goes with its vision-only pose turned
    into the world and marked unrefined (the loop closer's setting ``unrefined_start_keyframes``
    decides on it, test_keyframes_before_initialisation_reach_the_loop_closer). Without the
    adjustment every keyframe keeps such a pose, and none is marked."""
    from aerovis_slam.keypoints import Keypoints
    from aerovis_slam.slam.loop import DEFAULT_CONFIG

    class RecordingCloser:  # what the odometry hands the loop closer (it takes every keyframe)
        def __init__(self):
            self.config = dict(DEFAULT_CONFIG)
            self.keyframes, self.unrefined = {}, set()

        def add_keyframe(self, kf_id, t_us, T_world_body, *rest, unrefined=False):
            self.keyframes[kf_id] = T_world_body.copy()
            if unrefined:
                self.unrefined.add(kf_id)
            return True

        def add_odometry(self, *edge):
            pass

    spec = SequenceSpec("ba", rig="davis240_stereo", trajectory="handheld", trajectory_seed=7, scene_seed=7, duration_s=1.2)
    sim = Simulator(spec)
    traj = sim.trajectory
    cfg = SlamConfig()
    cfg.init.bundle_adjustment = bundle_adjustment
    cams = StereoCameras.from_rig(sim.rig, max_width=424, max_height=240, size_multiple=1)
    closer = RecordingCloser()
    odo = StereoInertialOdometry(cams, ImuStream(sim.imu()), sim.rig.imu, cfg, loop_closer=closer)
    rng = np.random.default_rng(1)
    R_wv = so3_exp(np.radians([20.0, -10.0, 5.0]))  # the vision frame V (first body pose) in the world
    Rv = np.eye(4)
    Rv[:3, :3] = R_wv.T
    P = traj.position(np.linspace(0, 1.2, 20))
    lms = rng.uniform(P.min(0) - 4, P.max(0) + 4, (2500, 3))
    odo.lmap.add((lms + rng.normal(0, 0.02, lms.shape)) @ R_wv, np.zeros((len(lms), 8), np.float32), 0, 0)
    t_kf = [int(round((0.1 + 0.12 * k) * 1e6)) for k in range(8)]
    for k, t in enumerate(t_kf):
        T = traj.pose_matrix(np.array([t * 1e-6]))[0]
        parts = []
        for c, cam in enumerate(cams.cams):
            uv, vis = project_landmarks(lms, T, cam)
            ids = np.flatnonzero(vis)[:100]
            parts.append(Observations(ids, np.full(len(ids), c, np.int8), uv[ids] + rng.normal(0, 0.5, (len(ids), 2))))
        T_v = Rv @ T
        T_v[:3, 3] += rng.normal(0, 0.01, 3)
        odo.preinit_window.append((k, t, T_v, Observations.concatenate(parts)))
    odo.kf_id = 7
    odo.t_first = t_kf[0] - 20_000  # the first frame's keyframe (not in the window) came before
    T_first_v = Rv @ traj.pose_matrix(np.array([odo.t_first * 1e-6]))[0]
    no_points = (Keypoints(np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros((0, 8), np.float32)),
                 np.zeros((0, 3)), np.zeros(0, bool))
    odo.preinit_kfs = [(-1, odo.t_first, T_first_v, *no_points)] + [(k, t, T_v, *no_points) for k, t, T_v, _ in odo.preinit_window]
    tau = t_kf[-1]
    v_v = {t: R_wv.T @ traj.position(np.array([t * 1e-6]), 1)[0] for t in t_kf[-3:]}
    odo.state = NavEstimate(odo.preinit_window[-1][2].copy(), v_v[tau], gtsam.imuBias.ConstantBias())
    R_wrong = so3_exp(np.radians([8.0, 0.0, 0.0])) @ R_wv
    pos_before = odo.lmap.pos[:len(lms)].copy()
    if start == "alignment":
        odo._start(tau, R_wrong, R_wrong @ v_v[tau], gtsam.imuBias.ConstantBias(), None, None, tilt_sigma_deg=6.0,
                   velocity_sigma=0.1, velocities=v_v)
    else:
        odo._start(tau, R_wrong, R_wrong @ v_v[tau], gtsam.imuBias.ConstantBias(), None, None)
    R_true = traj.rotation(np.array([tau * 1e-6]))[0]
    tilt = _tilt_deg(odo.state.T_world_body[:3, :3], R_true)
    if bundle_adjustment:
        assert tilt < 1.0
        assert odo.smoother.kf_ids == list(range(8))
        assert not np.allclose(odo.lmap.pos[:len(lms)], pos_before @ R_wrong.T)
        assert closer.unrefined == {-1}
        for k in range(8):
            assert np.array_equal(closer.keyframes[k], odo.smoother.estimates[k].T_world_body)
    else:
        assert tilt == pytest.approx(8.0, abs=0.5)
        assert odo.smoother.kf_ids == [8]
        assert closer.unrefined == set()
    assert sorted(closer.keyframes) == [-1] + list(range(8))
    # the first frame's keyframe: the vision-only pose, turned by the initialisation's gravity
    assert np.allclose(closer.keyframes[-1][:3, :3], R_wrong @ T_first_v[:3, :3])


def test_initialisation_window_velocity_prior_fits_its_centre():
    """The initialisation's window starts at keyframes tracked before the aligned stretch, whose
    velocity (the prior's centre) is the slope of the keyframe positions, not the alignment's: its
    prior must not take the alignment's sigma (here 0.1 m/s) but ``UNALIGNED_VELOCITY_SIGMA`` (0.5).
    The same handheld setup as the test above, with the correct gravity, 1 cm pose noise and the
    oldest keyframe's positions 4 cm further apart (a slope 0.33 m/s off, as tracking noise makes
    it): the window still fits, its path length within 3 % of the truth and its oldest velocity
    within 0.15 m/s (measured 0.2 % and 0.03 m/s; with the 0.1 m/s prior 0.5 % and 0.04 m/s: with
    100 observations of 0.5 px per camera vision holds the scale either way, unlike the office
    start at 240x180 px, docs/slam.md)."""
    from aerovis_slam.slam.backend import V as V_key
    from aerovis_slam.slam.odometry import UNALIGNED_VELOCITY_SIGMA

    spec = SequenceSpec("ba", rig="davis240_stereo", trajectory="handheld", trajectory_seed=7, scene_seed=7, duration_s=1.2)
    sim = Simulator(spec)
    traj = sim.trajectory
    cfg = SlamConfig()
    cams = StereoCameras.from_rig(sim.rig, max_width=424, max_height=240, size_multiple=1)
    odo = StereoInertialOdometry(cams, ImuStream(sim.imu()), sim.rig.imu, cfg)
    rng = np.random.default_rng(2)
    P = traj.position(np.linspace(0, 1.2, 20))
    lms = rng.uniform(P.min(0) - 4, P.max(0) + 4, (2500, 3))
    odo.lmap.add(lms + rng.normal(0, 0.02, lms.shape), np.zeros((len(lms), 8), np.float32), 0, 0)
    t_kf = [int(round((0.1 + 0.12 * k) * 1e6)) for k in range(8)]
    T_true = []
    for k, t in enumerate(t_kf):
        T = traj.pose_matrix(np.array([t * 1e-6]))[0]
        T_true.append(T)
        parts = []
        for c, cam in enumerate(cams.cams):
            uv, vis = project_landmarks(lms, T, cam)
            ids = np.flatnonzero(vis)[:100]
            parts.append(Observations(ids, np.full(len(ids), c, np.int8), uv[ids] + rng.normal(0, 0.5, (len(ids), 2))))
        T_v = T.copy()
        T_v[:3, 3] += rng.normal(0, 0.01, 3)
        odo.preinit_window.append((k, t, T_v, Observations.concatenate(parts)))
    # the oldest keyframe's slope 0.33 m/s off: 4 cm along the first step's direction
    step = T_true[1][:3, 3] - T_true[0][:3, 3]
    odo.preinit_window[0][2][:3, 3] -= 0.04 * step / np.linalg.norm(step)
    odo.kf_id = 7
    odo.t_first = t_kf[0] - 20_000
    tau = t_kf[-1]
    v_true = {t: traj.position(np.array([t * 1e-6]), 1)[0] for t in t_kf}
    v_aligned = {t: v_true[t] for t in t_kf[-3:]}
    odo.state = NavEstimate(odo.preinit_window[-1][2].copy(), v_aligned[tau], gtsam.imuBias.ConstantBias())
    odo._start(tau, np.eye(3), v_aligned[tau], gtsam.imuBias.ConstantBias(), None, None, tilt_sigma_deg=2.0,
               velocity_sigma=0.1, velocities=v_aligned)
    assert odo.smoother.kf_ids == list(range(8))
    graph = odo.smoother.smoother.getFactors()
    sigmas = [graph.at(i).noiseModel().sigmas() for i in range(graph.size())
              if graph.exists(i) and list(graph.at(i).keys()) == [V_key(0)]]
    # the fallback's 0.5 m/s, not the alignment's 0.1 that this window's newest keyframes have
    assert UNALIGNED_VELOCITY_SIGMA == 0.5 and len(sigmas) == 1 and np.allclose(sigmas[0], 0.5)
    est = odo.smoother.estimates
    length = sum(np.linalg.norm(est[k + 1].T_world_body[:3, 3] - est[k].T_world_body[:3, 3]) for k in range(7))
    true_length = sum(np.linalg.norm(T_true[k + 1][:3, 3] - T_true[k][:3, 3]) for k in range(7))
    assert length == pytest.approx(true_length, rel=0.03)
    assert np.linalg.norm(est[0].v_world - v_true[t_kf[0]]) < 0.15


def test_keyframe_in_the_frame_of_a_restart_takes_its_place():
    """A tracking loss restarts the smoother at that frame; when the same frame re-initialises from
    stereo, its keyframe would be joined by a zero-length IMU factor, which gtsam cannot solve
    ("indeterminate linear system"). The keyframe must take the restart's place instead: no backend
    reset, the new keyframe newest in the window, with the restart's velocity prior."""
    from aerovis_slam.slam.odometry import StereoInertialOdometry

    sim = _tiny_sim(imu_noise=False)
    cams = StereoCameras.from_rig(sim.rig, max_width=424, max_height=240, size_multiple=1)
    odo = StereoInertialOdometry(cams, ImuStream(sim.imu()), sim.rig.imu, SlamConfig())
    T = sim.trajectory.pose_matrix(np.array([0.5]))[0]
    state = NavEstimate(T, sim.trajectory.position(np.array([0.5]), 1)[0], gtsam.imuBias.ConstantBias())
    tau = 500_000
    odo.kf_id = 1
    odo._restart_smoother(1, tau, state, sigma_vel=0.5)  # what a tracking loss does at this frame
    odo.pim = new_preintegration(odo.params, state.bias)
    # the degenerate factor, as it was added before
    with pytest.raises(RuntimeError, match="ndeterminate"):
        odo.smoother.add_keyframe(2, odo.pim, state, Observations.empty(), {})
    odo._restart_smoother(1, tau, state, sigma_vel=0.5)
    est = odo._smoother_keyframe(2, tau, state, Observations.empty(), {})
    assert not any("smoother update failed" in w for w in odo.log.as_list())
    assert odo.smoother.latest[0] == 2 and odo.smoother.kf_ids == [2]
    np.testing.assert_allclose(est.T_world_body, T)
    assert odo._restart_sigma_vel == 0.5 and odo.pim.deltaTij() == 0.0


def test_smoother_finishes_an_ill_conditioned_update_with_qr():
    """Cholesky factorises the normal equations and squares their condition number. Two extra
    points tied by a 1e-6 m between factor (0.5 m apart), each with only a 1e8 m prior (both at
    the same place, so that there is something to solve), make it ~1e28: gtsam's
    Cholesky reports an "indeterminate linear system" although the system is determinate (QR on the
    Jacobian, condition ~1e14, solves it). ``add_keyframe`` must finish that update with QR in place
    (the keyframe and the points are in the window, the tie holds to the solver's precision) and
    try Cholesky first again at the next update, counting the fallbacks."""
    sim = _tiny_sim(imu_noise=False)
    cams = StereoCameras.from_rig(sim.rig, max_width=424, max_height=240, size_multiple=1)
    params = preintegration_params(sim.rig.imu)
    sm = KeyframeSmoother(SlamConfig().backend, cams, params)
    T = sim.trajectory.pose_matrix(np.array([0.5]))[0]
    state = NavEstimate(T, sim.trajectory.position(np.array([0.5]), 1)[0], gtsam.imuBias.ConstantBias())
    sm.initialize(0, 0.5, state, sigma_rollpitch_rad=0.01, sigma_vel=0.05, sigma_acc_bias=0.1, sigma_gyro_bias=0.01)
    P = gtsam.symbol_shorthand.P
    real = sm.smoother

    class IllConditioned:  # the real smoother, with the ill-conditioned pair added to one update
        def __init__(self):
            self.armed = True

        def update(self, graph=None, values=None, stamps=None, remove=None):
            if graph is None:
                return real.update()
            if self.armed:
                self.armed = False
                for i, x in enumerate((1.0, 1.5)):
                    values.insert(P(i), np.array([x, 0.0, 0.0]))
                    graph.add(gtsam.PriorFactorPoint3(P(i), np.array([1.0, 0.0, 0.0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e8)))
                    stamps[P(i)] = max(stamps.values())
                graph.add(gtsam.BetweenFactorPoint3(P(0), P(1), np.array([0.5, 0, 0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
            return real.update(graph, values, stamps, remove)

        def __getattr__(self, name):
            return getattr(real, name)

    sm.smoother = IllConditioned()
    with pytest.raises(RuntimeError, match="ndetermina"):  # what Cholesky alone does with it
        lm = gtsam.LevenbergMarquardtParams()
        alone = gtsam.BatchFixedLagSmoother(5.0, lm)
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for i, x in enumerate((1.0, 1.5)):
            v.insert(P(i), np.array([x, 0.0, 0.0]))
            g.add(gtsam.PriorFactorPoint3(P(i), np.array([1.0, 0.0, 0.0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e8)))
        g.add(gtsam.BetweenFactorPoint3(P(0), P(1), np.array([0.5, 0, 0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
        alone.update(g, v, {P(0): 0.0, P(1): 0.0})
    pim = new_preintegration(params)
    ImuStream(sim.imu()).integrate(pim, 500_000, 600_000)
    guess = NavEstimate.from_navstate(pim.predict(state.navstate(), state.bias), state.bias)
    sm.add_keyframe(1, pim, guess, Observations.empty(), {})
    assert sm.qr_fallbacks == 1 and sm.kf_ids == [0, 1]
    assert real.params().getLinearSolverType() == "MULTIFRONTAL_CHOLESKY"
    est = real.calculateEstimate()
    np.testing.assert_allclose(est.atPoint3(P(1)) - est.atPoint3(P(0)), [0.5, 0, 0], atol=1e-6)
    # noise-free IMU over 0.1 s from the true state: the new keyframe where the trajectory is
    T1 = sim.trajectory.pose_matrix(np.array([0.6]))[0]
    np.testing.assert_allclose(sm.latest[1].T_world_body[:3, 3], T1[:3, 3], atol=1e-3)
    # the next update tries Cholesky again; the pair is still in the window, so QR finishes it again
    sm.add_keyframe(2, pim, guess, Observations.empty(), {})
    assert sm.qr_fallbacks == 2 and real.params().getLinearSolverType() == "MULTIFRONTAL_CHOLESKY"


# -- the pipeline ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_preset():
    return ensure_preset("tiny", progress=False)


def test_pipeline_on_tiny_preset(tiny_preset):
    """The tiny rig (64x48 px, 10 cm baseline: about 1.3 px of disparity at the scene's 2.4 m) cannot
    triangulate, so the run exercises the IMU path: it must complete, output at 50 Hz, warn about
    the untracked frames and keep the orientation at gyroscope accuracy (BMI160 noise 1.6e-4
    rad/s/sqrt(Hz): 0.01 deg over 1 s; 0.5 deg covers the first-frame offset). The ATE bound: the
    spin is a rotation in place with a hover wobble, so a trajectory standing still at the start
    has an ATE equal to the wobble's RMS spread about its start; IMU-only propagation may not do
    worse than that plus 2 cm (accelerometer noise 2e-3 m/s^2/sqrt(Hz) integrates to millimetres)."""
    path = tiny_preset / "tiny_spin_hdr.h5"
    cfg = load_config("accurate")
    cfg.detector.observation_lag_events_per_px = 0.0  # outputs on the processing grid (the lag's own tests below)
    res = run_slam(path, StereoClassicalDetector("sift", 200), cfg, mode="sync", progress=False)
    assert res.status == "ok" and res.complete
    # every 20 ms slot from the first frame (after the MCTS warm-up) to the end
    t0, t_end = res.info["t_first_frame_us"], res.info["t_end_us"]
    assert res.t_us[0] == t0 and len(res.t_us) == (t_end - t0) // 20_000 + 1
    assert np.all(np.diff(res.t_us) == 20_000)
    assert any("IMU only" in w for w in res.warnings)
    with Sequence(path) as s:
        gt = s.gt
    r = ate(gt, PoseSamples(res.t_us, res.pose7), align="se3")
    g = r["ref_pose"][:, :3]
    spread = np.sqrt(np.mean(np.sum((g - g[0]) ** 2, axis=1)))
    assert r["ate_rmse_m"] <= spread + 0.02
    T_est = pose7_to_matrix(res.pose7)
    T_gt = pose7_to_matrix(interpolate_poses(res.t_us, gt.t, gt.pose))
    rel_est = np.einsum("ji,njk->nik", T_est[0, :3, :3], T_est[:, :3, :3])
    rel_gt = np.einsum("ji,njk->nik", T_gt[0, :3, :3], T_gt[:, :3, :3])
    assert rotation_angle_deg(np.einsum("nji,njk->nik", rel_est, rel_gt)).max() < 0.5


@pytest.fixture(scope="module")
def small_flight(tmp_path_factory):
    """A 2 s figure-eight flight of the drone rig at half resolution (212x120): simulated in ~2 s."""
    spec = SequenceSpec("flight", rig="drone424", rig_scale=0.5, trajectory="drone8", trajectory_seed=5, scene_seed=5,
                        duration_s=2.0, frame_rate_hz=0, gt_rate_hz=200)
    path = tmp_path_factory.mktemp("slam") / "flight.h5"
    write_sequence(spec, path)
    return path


@pytest.fixture(scope="module")
def small_flight_orb(small_flight):
    """The small flight's run with ORB (300 keypoints) and the ``accurate`` config, sync: the
    reference that several tests compare their variant with (sync runs are deterministic)."""
    return run_slam(small_flight, StereoClassicalDetector("orb", 300), load_config("accurate"), mode="sync", progress=False)


def test_pipeline_tracks_a_small_flight(small_flight):
    """Stereo visual-inertial tracking with ORB on the same time surfaces. At 212x120 the stereo
    disparity at the scene's ~2.7 m is ~2 px, so single landmarks carry ~25 % depth noise; the
    bound (6 % of the 2.3 m path, i.e. ~14 cm) is what a visually tracked estimate must meet, while
    IMU-only propagation from the unknown 1.7 m/s start velocity drifts by metres within 2 s.
    Without the MCTS warm-up (``input.warm_up``, tested on its own below): the checks of the final
    trajectory need several keyframes before the initialisation, and the flight's first 0.4 s
    (incomplete surfaces) give them."""
    cfg = load_config("accurate")
    cfg.input.warm_up = False
    res = run_slam(small_flight, StereoClassicalDetector("orb", 300), cfg, mode="sync", progress=False)
    assert res.status == "ok" and res.complete
    assert res.info["initialized"]
    assert res.info["pose_refits"] == 0  # tracking.refit_on_disagreement is off in `accurate`
    # the simulated rig is rectified with cam1 on the right: row search, pairs as stereo factors
    assert res.info["stereo_row_search"] and res.info["backend_stereo_factors"] > 0
    # the alignment needs init.window_s (0.3 s) of tracked frames; by init.timeout_s (1.5 s) the
    # static-start fallback takes over (one 20 ms frame of slack); both from the first output, whose
    # frame the warm-up (input.warm_up) may delay by up to input.max_warm_up_s
    assert 0 <= res.info["t_first_frame_us"] - res.info["t_begin_us"] <= 0.5e6
    init_after_s = (res.info["t_initialized_us"] - res.t_us[0]) * 1e-6
    assert 0.3 <= init_after_s <= 1.5 + 0.02 + 1e-6
    assert res.tracked.mean() > 0.8
    with Sequence(small_flight) as s:
        gt = s.gt
    r = ate(gt, PoseSamples(res.t_us, res.pose7), align="se3")
    assert r["ate_rmse_m"] < 0.06 * r["path_length_m"]
    assert res.keyframes >= 5 and res.tracking_losses == 0
    # the final trajectory: same times; every output moved with its keyframe (the smoother refines
    # a keyframe after its frames were output), the vision-only ones before the initialisation
    # with the keyframes the initialisation's window re-estimated: rigidly per keyframe, so the
    # transforms they move by form runs in time, more than one (the window moved its keyframes
    # differently) and at most one per keyframe before the initialisation (plus the first
    # frame's, which follows the window's oldest keyframe); all meet the same bound
    assert res.pose7_final is not None and res.pose7_final.shape == res.pose7.shape
    pre = res.t_us < res.info["t_initialized_us"]
    L, F = pose7_to_matrix(res.pose7), pose7_to_matrix(res.pose7_final)
    C = F[pre] @ np.linalg.inv(L[pre])
    new_run = np.r_[True, [not np.allclose(a, b, atol=1e-6) for a, b in zip(C[1:], C[:-1])]]
    runs = C[new_run]
    assert 2 <= len(runs) <= res.keyframes
    assert all(not np.allclose(a, b, atol=1e-6) for i, a in enumerate(runs) for b in runs[i + 1:])  # no run comes back
    assert not np.allclose(res.pose7_final[~pre], res.pose7[~pre])
    # and their attitude: the live ones carry the alignment's gravity, the final ones the window's
    G = pose7_to_matrix(interpolate_poses(res.t_us, gt.t, gt.pose))
    tilt_live = [_tilt_deg(a[:3, :3], b[:3, :3]) for a, b in zip(L[pre], G[pre])]
    tilt_final = [_tilt_deg(a[:3, :3], b[:3, :3]) for a, b in zip(F[pre], G[pre])]
    assert max(tilt_final) < max(tilt_live)
    rf = ate(gt, PoseSamples(res.t_us, res.pose7_final), align="se3")
    assert rf["ate_rmse_m"] < 0.06 * rf["path_length_m"]
    for stage in ("mcts", "detector", "matching", "tracking", "backend", "total"):
        assert len(res.stage_ms[stage]) == len(res.t_us)


def _flight_cams(path):
    with Sequence(path) as seq:
        calib = seq.calib
    return StereoCameras.from_rig(calib, max_width=424, max_height=240, size_multiple=8)


def test_oracle_projects_the_scene_point_of_a_keypoint(small_flight):
    """The perfect-tracks oracle (oracle.py): a pixel back-projected with the rendered depth projects
    back onto itself at the same time (the same ray: exact to float precision), and 0.2 s later
    into the right camera where that camera's own rendered depth agrees with the point's depth. The
    depth map is sampled at the nearest pixel, so agreement is required to within the depth change
    across one pixel, and only where no depth edge is there (at one the nearest pixel may see the
    occluding surface: a change of more than 10 % across one pixel)."""
    from aerovis_slam.slam.oracle import ObservationOracle

    cams = _flight_cams(small_flight)
    oracle = ObservationOracle(small_flight, cams, 0.0)
    u, v = np.meshgrid(np.arange(8, cams.left.width - 8, 16), np.arange(8, cams.left.height - 8, 16))
    xy = np.c_[u.ravel(), v.ravel()].astype(np.float64) + 0.3
    pts = oracle.back_project(500_000, 0, xy)
    assert np.isfinite(pts).all()  # the room has no open side
    np.testing.assert_allclose(oracle.projections(500_000, 0, pts), xy, atol=1e-6)
    uv = oracle.projections(700_000, 1, pts)
    seen = np.isfinite(uv).all(axis=1)
    assert seen.mean() > 0.5
    T_cw = np.linalg.inv(oracle.T_world_body(700_000) @ cams.right.T_body_cam)
    z_point = (pts[seen] @ T_cw[:3, :3].T + T_cw[:3, 3])[:, 2]
    depth = oracle._depth(700_000, 1)
    c, r = np.round(uv[seen, 0]).astype(int), np.round(uv[seen, 1]).astype(int)
    pad = np.pad(depth, 1, mode="edge")
    window = np.stack([pad[r + 1 + dr, c + 1 + dc] for dr in (-1, 0, 1) for dc in (-1, 0, 1)])
    step = np.abs(window - depth[r, c]).max(axis=0)  # depth change across one pixel
    smooth = step < 0.1 * depth[r, c]  # slanted surfaces change a few % per pixel, depth edges far more
    assert smooth.sum() > 0.5 * len(smooth)
    assert np.all(np.abs(z_point - depth[r, c])[smooth] <= step[smooth] + 1e-4)


def test_keypoint_errors_are_measured_without_changing_the_run(small_flight, small_flight_orb):
    """``detector.measure_keypoint_errors`` (``run --keypoint-errors``): the trajectory is the plain
    run's to the last digit (observations are only compared, never replaced), and the distances by
    track age add up to all measured observations. With track refinement off the same keypoints lie
    farther from their scene points (refinement aligns each to its landmark's first view)."""
    results = {(True, False): small_flight_orb}  # refinement is on in `accurate`
    for refine in (True, False):
        for measure in (False, True):
            if (refine, measure) in results:
                continue
            cfg = load_config("accurate")
            cfg.refinement.enabled = refine
            cfg.detector.measure_keypoint_errors = measure
            results[refine, measure] = run_slam(small_flight, StereoClassicalDetector("orb", 300), cfg, mode="sync", progress=False)
    for refine in (True, False):
        np.testing.assert_array_equal(results[refine, True].pose7, results[refine, False].pose7)
        assert "keypoint_errors" not in results[refine, False].info
        ke = results[refine, True].info["keypoint_errors"]
        assert ke["observations"] > 500
        assert sum(b["observations"] for b in ke["by_track_age_s"].values()) == ke["observations"]
    assert results[True, True].info["refinement"]["observations_refined"] > 0 and results[False, True].info["refinement"] is None
    assert results[True, True].info["keypoint_errors"]["median_px"] < results[False, True].info["keypoint_errors"]["median_px"]


def test_oracle_refuses_a_sequence_without_a_simulator_spec(small_flight, tmp_path):
    import shutil

    import h5py

    from aerovis_slam.slam.oracle import ObservationOracle

    copy = tmp_path / "recording.h5"
    shutil.copy(small_flight, copy)
    with h5py.File(copy, "r+") as f:
        f.attrs["meta"] = "{}"
    with pytest.raises(DataError, match="meta.spec") as err:
        ObservationOracle(copy, _flight_cams(copy), 0.5)
    assert str(copy) in str(err.value)


def test_pipeline_with_exact_tracks_recovers_the_trajectory(small_flight):
    """With every observation replaced by the exact projection of its landmark's scene point
    (oracle noise 0), what is left is the IMU noise and the solver: the estimate must stay well
    inside the footprint of one pixel at the scene depth (~2.7 m / fx), the error one pixel of
    keypoint offset would cause; the bound is half of it. With ORB's own keypoints the same run
    is about 5 % of the path off (the bound of the test above is 6 %)."""
    cfg = load_config("accurate")
    cfg.detector.oracle_noise_px = 0.0
    res = run_slam(small_flight, StereoClassicalDetector("orb", 300), cfg, mode="sync", progress=False)
    assert res.status == "ok" and res.complete
    stats = res.info["oracle"]
    assert stats["noise_px"] == 0.0 and stats["observations_replaced"] > 1000 and stats["landmarks"] > 100
    with Sequence(small_flight) as s:
        gt = s.gt
    fx = _flight_cams(small_flight).left.K[0, 0]
    r = ate(gt, PoseSamples(res.t_us, res.pose7), align="se3")
    assert r["ate_rmse_m"] < 0.5 * 2.7 / fx


def test_calibrated_camera_clock_offset_is_undone(small_flight, small_flight_orb, tmp_path, camera_clock_copy):
    """Cameras 30 ms late on the IMU's clock (t_imu = t_cam - 30 ms, Kalibr's timeshift_cam_imu):
    with the offset in the calibration the runtime moves the events back onto the IMU clock and
    the run is the original one, output for output (sync mode is deterministic); without it the
    events are taken 30 ms late and the run differs."""
    late = 30_000
    cfg = load_config("accurate")
    ref = small_flight_orb
    fixed = camera_clock_copy(small_flight, tmp_path / "late_calibrated.h5", late, -late)
    res = run_slam(fixed, StereoClassicalDetector("orb", 300), cfg, mode="sync", progress=False)
    assert res.status == ref.status == "ok"
    np.testing.assert_array_equal(res.t_us, ref.t_us)
    np.testing.assert_array_equal(res.pose7, ref.pose7)
    wrong = camera_clock_copy(small_flight, tmp_path / "late_uncalibrated.h5", late, 0.0)
    off = run_slam(wrong, StereoClassicalDetector("orb", 300), cfg, mode="sync", progress=False)
    assert off.status == "ok"
    assert len(off.t_us) != len(ref.t_us) or not np.array_equal(off.pose7, ref.pose7)

def test_observation_time_is_the_nth_newest_event_averaged_and_bounded():
    """N = 0.5 events/px x 100 px = 50: the 50th event before the newest. cam0 fires every 100 µs,
    cam1 every 200 µs (200 events each, the newest at 19,900 and 39,800 µs)."""
    from aerovis_slam.events import EventArray
    from aerovis_slam.mcts import TimestampBuffer
    from aerovis_slam.slam.preprocessing import MAX_OBSERVATION_LAG_US, observation_time

    bufs = []
    for spacing in (100, 200):
        b = TimestampBuffer(10, 10, events_per_px=(0.5,))
        i = np.arange(200)
        b.ingest(EventArray(i * spacing, i % 10, (i // 10) % 10, i % 2))
        bufs.append(b)
    # events 149: cam0 at 14,900, cam1 at 29,800; at tau = 40,000 the lags are 25,100 and 10,200 µs
    assert observation_time(bufs, 40_000, 0.5) == 40_000 - (25_100 + 10_200) // 2
    # lags of 85,100 and 70,200 µs are bounded
    assert observation_time(bufs, 100_000, 0.5) == 100_000 - MAX_OBSERVATION_LAG_US == 50_000
    # off, or a camera without N events yet: the surfaces' own time
    assert observation_time(bufs, 40_000, 0.0) == 40_000
    assert observation_time(bufs, 40_000, 2.0) == 40_000  # N = 200: as many events as cam0 holds


def test_observation_lag_moves_frames_to_the_time_their_keypoints_show(small_flight):
    """With ``detector.observation_lag_events_per_px`` each frame is estimated and output at the
    time of the N-th newest event (here N = 0.03 x 212 x 120 = 763 per camera): outputs strictly
    increase, each lies 0-50 ms before its slot on the 50 Hz grid, the median lag is N over the
    sequence's mean event rate per camera to within a factor of two (the rate varies along the
    flight), and the frames are tracked as without the lag (more than 80 %)."""
    cfg = load_config("accurate")
    cfg.detector.observation_lag_events_per_px = 0.03
    res = run_slam(small_flight, StereoClassicalDetector("orb", 300), cfg, mode="sync", progress=False)
    assert res.status == "ok" and res.complete and res.info["initialized"]
    slots = res.info["t_first_frame_us"] + 20_000 * np.arange(len(res.t_us))
    lag = slots - res.t_us
    assert np.all(np.diff(res.t_us) > 0)
    assert np.all((lag >= 0) & (lag <= 50_000))
    with Sequence(small_flight) as s:
        rate = np.mean([s.num_events(c) / ((s.time_range(c)[1] - s.time_range(c)[0]) * 1e-6) for c in ("cam0", "cam1")])
    expected_us = round(0.03 * 212 * 120) / rate * 1e6
    assert expected_us / 2 < np.median(lag[1:]) < expected_us * 2
    assert res.info["observation_lag_ms"]["median"] == pytest.approx(np.median(lag) / 1000, abs=1e-6)
    assert res.tracked.mean() > 0.8 and res.tracking_losses == 0


def test_warm_up_starts_when_both_time_surfaces_are_complete(small_flight):
    """``input.warm_up``: the first frame processed (and output) is the first 50 Hz slot at which
    both cameras' longest MCTS_Ne window is full (it reaches N = 1.0 x 212 x 120 = 25,440 events
    back from the newest: the (N+1)-th event of each camera, read from the file); ``max_warm_up_s``
    caps the wait, the first slot then being t_begin plus the cap."""
    from aerovis_slam.mcts import events_per_window

    det = StereoClassicalDetector("orb", 300)
    cfg = load_config("accurate")
    cfg.detector.observation_lag_events_per_px = 0.0  # outputs on the slots
    cfg.input.warm_up, cfg.input.max_warm_up_s = True, None
    res = run_slam(small_flight, det, cfg, mode="sync", progress=False)
    assert res.status == "ok" and res.complete and res.info["initialized"]
    with Sequence(small_flight) as s:
        n = int(events_per_window(det.mcts_params, *s.sensor_size("cam0")).max())
        t_full = max(int(s.events_by_index(c, n, n + 1).t[0]) for c in ("cam0", "cam1"))
    t_begin = res.info["t_begin_us"]
    expected = t_begin + 20_000 * int(np.ceil((t_full - t_begin) / 20_000))
    assert expected > t_begin + 20_000  # the test means something: the warm-up is longer than a frame
    assert res.t_us[0] == expected == res.info["t_first_frame_us"]
    assert np.all(np.diff(res.t_us) == 20_000) and res.tracked.mean() > 0.8
    with Sequence(small_flight) as s:
        r = ate(s.gt, PoseSamples(res.t_us, res.pose7), align="se3")
    assert r["ate_rmse_m"] < 0.06 * r["path_length_m"]  # the bound of the small-flight test above
    cfg.input.max_warm_up_s = 0.02
    capped = run_slam(small_flight, det, cfg, mode="sync", progress=False)
    assert capped.t_us[0] == t_begin + 20_000 == capped.info["t_first_frame_us"]


def test_observation_lag_in_async_mode_keeps_outputs_ordered(small_flight):
    """Async frames come at the times the processing clock reaches (not on a grid); with the
    observation lag each output still lies 0-50 ms before the newest IMU-covered time it was made
    at, after the previous output, and the latency is counted from that newest time (>= processing)."""
    cfg = load_config("realtime")
    cfg.detector.observation_lag_events_per_px = 0.03
    res = run_slam(small_flight, StereoClassicalDetector("orb", 200), cfg, mode="async", progress=False)
    assert res.status == "ok" and res.complete and res.mode == "async"
    assert np.all(np.diff(res.t_us) > 0)
    lag = res.info["observation_lag_ms"]
    assert 0.0 < lag["median"] <= lag["max"] <= 50.0
    assert np.all(res.latency_ms >= np.asarray(res.stage_ms["total"]) - 1e-6)


@pytest.mark.parametrize("unrefined", [0, 1])
def test_keyframes_before_initialisation_reach_the_loop_closer(small_flight, unrefined):
    """A sequence that ends where it began can only close its loop against its first keyframes,
    which are made before gravity is known: they wait and reach the loop closer at the
    initialisation, in the world frame, at the initialisation window's re-estimate of their pose:
    moved from what was output at their time, but by no more than the pre-initialisation outputs'
    error (the 14 cm bound of the small-flight test, and the alignment's few degrees). The first
    frame's keyframe, which that window leaves out, keeps a vision-only pose and is no candidate
    (loop setting ``unrefined_start_keyframes`` 0); with 1 it is in the database too, at exactly the
    pose that was output at its time (both are the vision-frame pose turned by the same gravity
    rotation). Every other keyframe of the frontend is in the loop closer's database."""
    from aerovis_slam.slam.loop import LoopCloser

    with LoopCloser(config={"unrefined_start_keyframes": unrefined}) as closer:
        res = run_slam(small_flight, StereoClassicalDetector("orb", 300), load_config("accurate"), mode="sync",
                       loop_closer=closer, progress=False)
        kfs = [closer._keyframes[i] for i in closer._order]
        assert res.status == "ok" and closer.summary()["keyframes"] == res.keyframes - (1 - unrefined)
    t_init = res.info["t_initialized_us"]
    t_first = int(res.t_us[0])  # the first output is the first frame's
    pre = [k for k in kfs if k.t_us < t_init]
    assert pre and [k.t_us for k in kfs] == sorted(k.t_us for k in kfs)
    assert (pre[0].t_us == t_first) == bool(unrefined)
    assert len([k for k in pre if k.t_us != t_first]) >= 1  # and at least one later keyframe
    for k in pre:
        T_out = pose7_to_matrix(res.pose7[int(np.flatnonzero(res.t_us == k.t_us)[0])])
        if k.t_us == t_first:
            np.testing.assert_allclose(k.T_odom, T_out, atol=1e-9)
        else:
            assert not np.allclose(k.T_odom, T_out, atol=1e-6)
            assert np.linalg.norm(k.T_odom[:3, 3] - T_out[:3, 3]) < 0.14
            assert rotation_angle_deg(k.T_odom[:3, :3].T @ T_out[:3, :3]) < 10.0


def _with_gaps(src, dst, *, imu_gap_s=(0.8, 0.9), no_events_s=(1.0, 1.3)):
    """Copy of a sequence with an IMU gap (missing samples) and a stretch without events."""
    from aerovis_slam.events import EventArray
    from aerovis_slam.io.sequence import SequenceWriter
    from aerovis_slam.measurements import ImuSamples

    with Sequence(src) as s, SequenceWriter(dst, s.calib) as w:
        for cam in s.cameras:
            ev = s.events(cam)
            keep = (ev.t < no_events_s[0] * 1e6) | (ev.t >= no_events_s[1] * 1e6)
            w.add_events(cam, EventArray(ev.t[keep], ev.x[keep], ev.y[keep], ev.p[keep]))
        imu = s.imu
        keep = (imu.t < imu_gap_s[0] * 1e6) | (imu.t >= imu_gap_s[1] * 1e6)
        w.set_imu(ImuSamples(imu.t[keep], imu.gyro[keep], imu.acc[keep]))
        w.set_gt(s.gt)
    return dst


@pytest.mark.parametrize("dark_s, losses", [(0.3, 0), (0.6, 1)])
def test_pipeline_survives_imu_gap_and_missing_events(small_flight, tmp_path, dark_s, losses):
    """100 ms without IMU samples and a stretch without any event while flying (a dark stretch): the
    run warns, propagates with the IMU (interpolated across the gap), tracks again and ends complete.
    Frames without new events count towards ``tracking.loss_time_s`` (0.5 s) only, not towards
    ``loss_frames``: after 300 ms (15 frames at 50 Hz) the map is kept and tracking resumes on it;
    after 600 ms tracking is lost once, the backend restarts from the last tracked velocity and a new
    stereo map, and no second loss follows. The IMU says the drone moves throughout, so it is never
    taken for a standstill. The bound is twice the one of the undisturbed flight: the IMU-only
    propagation at the BMI160's noise adds millimetres, the re-acquired map the rest."""
    end_s = 1.0 + dark_s
    path = _with_gaps(small_flight, tmp_path / "gaps.h5", no_events_s=(1.0, end_s))
    res = run_slam(path, StereoClassicalDetector("orb", 300), load_config("accurate"), mode="sync", progress=False)
    assert res.status == "ok" and res.complete
    assert any("IMU gap" in w for w in res.warnings)
    assert any("IMU only" in w for w in res.warnings)
    assert not any("at rest" in w for w in res.warnings)
    t = res.t_us
    dark = (t >= 1.05e6) & (t < end_s * 1e6)
    assert not res.tracked[dark].any() and res.tracked[t > (end_s + 0.3) * 1e6].mean() > 0.8  # tracked again afterwards
    assert res.tracking_losses == losses and any("tracking lost" in w for w in res.warnings) == bool(losses)
    with Sequence(path) as s:
        gt = s.gt
    r = ate(gt, PoseSamples(res.t_us, res.pose7), align="se3")
    assert r["ate_rmse_m"] < 0.12 * r["path_length_m"]
    # the dark frames were propagated from a keyframe of the smoother, which later keyframes refine:
    # in the final trajectory they move with it as the tracked frames do, not stay where they were
    assert not np.allclose(res.pose7_final[dark], res.pose7[dark])
    rf = ate(gt, PoseSamples(res.t_us, res.pose7_final), align="se3")
    assert rf["ate_rmse_m"] < 0.12 * rf["path_length_m"]


@pytest.fixture(scope="module")
def flight_with_a_stop(tmp_path_factory):
    """The small flight's drone comes to rest at 2.5 s for 1 s and flies on, on a quiet sensor (0.02
    Hz/px of noise events: under ``input.min_new_events_per_px`` while it stands); ~4 s to simulate."""
    from aerovis_slam.sim.events import EventConfig

    spec = SequenceSpec("stop", rig="drone424", rig_scale=0.5, trajectory="drone8", trajectory_seed=5, scene_seed=5,
                        duration_s=4.9, frame_rate_hz=0, gt_rate_hz=200, pauses=[(2.5, 1.0)],
                        events=EventConfig(leak_hz=0.01, shot_noise_hz=0.01))
    path = tmp_path_factory.mktemp("slam") / "stop.h5"
    write_sequence(spec, path)
    return path


@pytest.mark.parametrize("zero_velocity", [True, False])
def test_a_camera_at_rest_keeps_its_map(flight_with_a_stop, zero_velocity):
    """A drone that lands for a second sends (almost) no events. With ``tracking.zero_velocity`` the
    IMU test finds it at rest within a few frames of the halt; from then on its pose is held, so it
    moves by less than 1 cm while it stands (the smoother's update at the rest keyframe moves it by
    millimetres), nothing counts towards a tracking loss, and it tracks on the same map when it
    flies on. Without it, the IMU-only propagation carries the estimate's bias error: the standing
    drone drifts by centimetres and after ``loss_time_s`` the map is dropped."""
    cfg = load_config("accurate")
    cfg.tracking.zero_velocity = zero_velocity
    res = run_slam(flight_with_a_stop, StereoClassicalDetector("orb", 300), cfg, mode="sync", progress=False)
    assert res.status == "ok" and res.complete
    t = res.t_us
    standing = (t >= 2.6e6) & (t <= 3.5e6)  # the halt's first 0.1 s is the IMU test's window
    drift_m = np.linalg.norm(res.pose7[standing, :3] - res.pose7[standing, :3][0], axis=1).max()
    with Sequence(flight_with_a_stop) as s:
        gt = s.gt
    r = ate(gt, PoseSamples(res.t_us, res.pose7), align="se3")
    if zero_velocity:
        assert any("at rest" in w for w in res.warnings)
        assert drift_m < 0.01 and res.tracking_losses == 0
        assert res.tracked[t > 4.0e6].mean() > 0.8
        assert r["ate_rmse_m"] < 0.06 * r["path_length_m"]  # the undisturbed flight's bound
    else:
        assert not any("at rest" in w for w in res.warnings)
        assert drift_m > 0.03 and res.tracking_losses == 1


def test_event_bursts_above_the_rate_cap_warn_and_the_run_continues(small_flight):
    """``input.rate_cap_mev_s`` below the flight's own event rate (a burst for the whole run): the
    cap's token bucket accepts at most ``cap * (span + 10 ms)`` events per camera, so at least the
    rest of what the run read is dropped; the run says so once, with the count, records it in
    ``info`` and still completes and initialises on the thinned events."""
    with Sequence(small_flight) as s:
        spans = []
        for c in ("cam0", "cam1"):
            t = s.events(c).t
            spans.append(((int(t[-1]) - int(t[0])) * 1e-6, len(t)))
    rate = min(n / span for span, n in spans)  # ev/s of the quieter camera
    cfg = load_config("accurate")
    cfg.input.rate_cap_mev_s = 0.3 * rate / 1e6
    res = run_slam(small_flight, StereoClassicalDetector("orb", 300), cfg, mode="sync", progress=False)
    assert res.status == "ok" and res.complete and res.info["initialized"]
    cap = cfg.input.rate_cap_mev_s * 1e6
    most_accepted = sum(cap * (span + 0.01) for span, _ in spans)
    dropped = res.info["dropped_rate_cap"]
    assert res.info["events"] - most_accepted <= dropped < res.info["events"]
    rate_cap_warnings = [w for w in res.warnings if "event-rate cap" in w]
    assert len(rate_cap_warnings) == 1 and f"dropped {dropped} of {res.info['events']} events" in rate_cap_warnings[0]


def test_async_mode_processes_newest_state(small_flight):
    """async: frames follow the simulated clock (spacing >= the 100 Hz cap), latency >= processing.
    (Without the observation lag, which moves each output to when its keypoints show the scene:
    test_observation_lag_in_async_mode_keeps_outputs_ordered.)"""
    cfg = load_config("realtime")
    cfg.detector.observation_lag_events_per_px = 0.0
    res = run_slam(small_flight, StereoClassicalDetector("orb", 200), cfg, mode="async", progress=False)
    assert res.status == "ok" and res.complete and res.mode == "async"
    assert np.all(np.diff(res.t_us) >= 10_000)
    assert np.all(res.latency_ms >= np.asarray(res.stage_ms["total"]) - 1e-6)


def test_noise_filter_in_the_pipeline(small_flight):
    """``input.noise_filter_ms``: each camera's events pass the background-activity filter on the
    sensor grid before they reach the buffers; the run reports how many it dropped, and tracks the
    flight within the bound of the unfiltered run (test_pipeline_tracks_a_small_flight)."""
    from aerovis_slam.noise_filter import BackgroundActivityFilter

    with Sequence(small_flight) as s:
        streams = {c: s.events(c) for c in ("cam0", "cam1")}
        sizes = {c: s.sensor_size(c) for c in streams}
    dt_ms = 10.0
    expected = 0
    for c, ev in streams.items():
        f = BackgroundActivityFilter(*sizes[c], dt_us=int(dt_ms * 1000))
        f(ev)
        expected += f.removed
    assert 0 < expected < sum(len(ev) for ev in streams.values())
    cfg = load_config("accurate")
    cfg.input.noise_filter_ms = dt_ms
    res = run_slam(small_flight, StereoClassicalDetector("orb", 300), cfg, mode="sync", progress=False)
    assert res.status == "ok" and res.complete and res.info["initialized"]
    # the run ingests every event up to its last frame; the stream's last events after it are not read
    assert 0.95 * expected <= res.info["dropped_noise_filter"] <= expected
    with Sequence(small_flight) as s:
        gt = s.gt
    r = ate(gt, PoseSamples(res.t_us, res.pose7), align="se3")
    assert r["ate_rmse_m"] < 0.06 * r["path_length_m"]


def test_async_run_replays_exactly_from_its_frame_slots(small_flight):
    """An async run's frames, and under ``backend.time_budget_ms`` its backend's iteration caps,
    depend on this machine's timing; given its ``slot_us`` and ``iteration_caps`` back the run
    processes the same frames with the same caps and returns the same trajectory to the bit. A
    budget of 0.01 ms makes every cap 1 here, and the replay imposes other caps (the maximum)
    where told to. Slots outside the recording are refused."""
    cfg = load_config("realtime")
    det = StereoClassicalDetector("orb", 200)
    cfg.backend.time_budget_ms = 0.01  # every update cut to one iteration (a very slow machine)
    first = run_slam(small_flight, det, cfg, mode="async", progress=False)
    assert first.status == "ok" and len(first.slot_us) == len(first.t_us) == len(first.iteration_caps) > 20
    flat = [c for caps in first.iteration_caps for c in caps]
    assert len(flat) >= 5 and set(flat) == {1} and first.info["backend_budget_cuts"] == len(flat)
    # the same machine state is not needed: a replay with the budget off imposes the logged caps
    cfg.backend.time_budget_ms = None
    again = run_slam(small_flight, det, cfg, mode="async", progress=False, frame_slots=first.slot_us,
                     frame_caps=first.iteration_caps)
    assert again.status == "ok" and again.complete and again.info["replay_cap_mismatches"] == 0
    assert np.array_equal(again.slot_us, first.slot_us) and np.array_equal(again.t_us, first.t_us)
    assert again.iteration_caps == first.iteration_caps
    assert np.array_equal(again.pose7, first.pose7) and np.array_equal(again.tracked, first.tracked)
    assert np.all(again.latency_ms >= np.asarray(again.stage_ms["total"]) - 1e-6)
    # the slots alone, budget off: the same frames, the caps the configuration's maximum, another estimate
    free = run_slam(small_flight, det, cfg, mode="async", progress=False, frame_slots=first.slot_us)
    assert np.array_equal(free.slot_us, first.slot_us) and free.info["replay_cap_mismatches"] is None
    assert {c for caps in free.iteration_caps for c in caps} == {cfg.backend.max_iterations}
    assert not np.array_equal(free.pose7, first.pose7)
    with pytest.raises(DataError, match="outside this recording"):
        run_slam(small_flight, det, cfg, mode="async", progress=False, frame_slots=first.slot_us + 10**9)
    with pytest.raises(DataError, match="async"):
        run_slam(small_flight, det, cfg, mode="sync", progress=False, frame_slots=first.slot_us)
    # async's first slot is the newest IMU sample at or before t_begin: with 200 Hz IMU samples at
    # multiples of 5000 µs and t_begin = 20029 µs that is 20000, which a replay must accept; 19999 is
    # one the run could not have taken (the bench's spin_hdr_window replay was refused this way)
    t = np.arange(0, 100_001, 5000)
    stream = ImuStream(ImuSamples(t, np.zeros((len(t), 3)), np.tile([0.0, 0.0, 9.81], (len(t), 1))))
    check_frame_slots(np.array([20000, 30000, 100_000]), stream, 20029, 100_000)
    for bad in ([19999, 30000], [20000, 100_001]):
        with pytest.raises(DataError, match="outside this recording's frames 20000..100000"):
            check_frame_slots(np.array(bad), stream, 20029, 100_000)
    with pytest.raises(DataError, match="same length"):
        run_slam(small_flight, det, cfg, mode="async", progress=False, frame_slots=first.slot_us,
                 frame_caps=first.iteration_caps[:-1])


def test_event_reader_cameras_do_not_block_each_other(tiny_preset):
    """Consuming one camera's whole stream before the other's must not stall the reader (a full
    queue of one camera once blocked the reads of the other: a deadlock in async mode)."""
    from aerovis_slam.slam.preprocessing import EventReader

    path = tiny_preset / "tiny_handheld.h5"
    with Sequence(path) as s:
        n = {c: s.num_events(c) for c in ("cam0", "cam1")}
    reader = EventReader(path, chunk_events=1000, prefetch=1)
    try:
        for cam in ("cam0", "cam1"):
            got = 0
            while (chunk := reader.get(cam, timeout=0.05)) is not None:
                got += len(chunk)
            assert got == n[cam]
    finally:
        reader.close()
    assert not reader.alive


def test_stop_event_ends_threads_and_marks_partial(tiny_preset):
    """A stop request from another thread (here the detector's, at its 5th frame, so that the test
    does not depend on the machine's speed) ends a live replay after that frame; the reader and
    preprocessing threads end with it and the result says it is partial."""
    before = {t.ident for t in threading.enumerate()}
    stop = threading.Event()

    class Stopping(StereoClassicalDetector):
        calls = 0

        def detect(self, batch, **kw):
            self.calls += 1
            if self.calls == 5:
                threading.Thread(target=stop.set).start()
            return super().detect(batch, **kw)

    res = run_slam(tiny_preset / "tiny_handheld.h5", Stopping("sift", 100), load_config("accurate"),
                   mode="live", progress=False, stop_event=stop)
    assert not res.complete and res.status.startswith("stopped")
    assert len(res.t_us) == 5 and res.t_us[-1] < 0.9e6
    assert res.pose7_final is None  # no final trajectory of a run that did not finish
    leftover = [t for t in threading.enumerate() if t.ident not in before and t.name.startswith("aerovis")]
    assert leftover == []


def test_keyboard_interrupt_ends_cleanly(tiny_preset):
    class Interrupting(StereoClassicalDetector):
        calls = 0

        def detect(self, batch, **kw):
            self.calls += 1
            if self.calls == 5:
                raise KeyboardInterrupt
            return super().detect(batch, **kw)

    res = run_slam(tiny_preset / "tiny_handheld.h5", Interrupting("sift", 100), load_config("accurate"), progress=False)
    assert not res.complete and "KeyboardInterrupt" in res.status and len(res.t_us) == 4
    assert not [t for t in threading.enumerate() if t.name.startswith("aerovis")]


# -- configuration -------------------------------------------------------------------------------------
def test_configs_load_and_reject_unknown_keys(tmp_path):
    rt, acc = load_config("realtime"), load_config("accurate")
    assert rt.mode == "async" and acc.mode == "sync" and acc.rate_hz == 50.0
    assert rt.input.max_width <= 424 and rt.input.max_height <= 240
    assert rt.detector.top_k < acc.detector.top_k and acc.backend.time_budget_ms is None
    f = tmp_path / "mine.yaml"
    f.write_text("mode: sync\nbackend:\n  window_keyframes: 5\n")
    cfg = load_config(f)
    assert cfg.name == "mine" and cfg.backend.window_keyframes == 5 and cfg.backend.pixel_sigma == SlamConfig().backend.pixel_sigma
    f.write_text("backend:\n  windw_keyframes: 5\n")
    with pytest.raises(DataError, match="backend.windw_keyframes"):
        load_config(f)
    f.write_text("mode: fast\n")
    with pytest.raises(DataError, match="mode"):
        load_config(f)
    f.write_text("init:\n  min_position_inliers: 2\n")  # 4 equations for 3 unknowns leave no outlier check
    with pytest.raises(DataError, match="init.min_position_inliers"):
        load_config(f)
    for bad in ("window_px: 12", "max_fb_px: 0", "max_anchor_age_s: -1"):
        f.write_text(f"refinement:\n  {bad}\n")
        with pytest.raises(DataError, match="refinement." + bad.split(":")[0]):
            load_config(f)
    f.write_text("input:\n  max_warm_up_s: -0.1\n")
    with pytest.raises(DataError, match="input.max_warm_up_s"):
        load_config(f)
    for bad in ("0", "-5", "2000"):
        f.write_text(f"input:\n  noise_filter_ms: {bad}\n")
        with pytest.raises(DataError, match="input.noise_filter_ms"):
            load_config(f)
    for bad, key in (("gravity: accelerometer", "init.gravity"), ("velocity_change_s: 0.5", "init.velocity_change_s")):
        f.write_text(f"init:\n  {bad}\n")
        with pytest.raises(DataError, match=key):
            load_config(f)
    with pytest.raises(DataError, match="unknown SLAM config"):
        load_config("nonexistent")


def test_config_loop_section_reaches_the_loop_closer(tmp_path):
    """``loop:`` in a SLAM config overrides the loop closer's settings (what ``run`` and ``bench`` build
    through ``make_loop_closer``), whole-number settings stay whole, and a misspelt key, a fraction
    where a count belongs, a negative value or an unsupported pose-graph size is refused naming it."""
    from aerovis_slam.slam.bench import make_loop_closer
    from aerovis_slam.slam.loop import DEFAULT_CONFIG

    # the shipped accurate setting widens the loop edges' translation floor and refits loops to every landmark
    # near its projection (docs/slam.md); realtime keeps the defaults
    accurate_loop = {"loop_sigma_trans_m": 0.03, "rematch_window_px": 4.0}
    assert load_config("accurate").loop == accurate_loop and load_config("realtime").loop == {}
    f = tmp_path / "strict_loops.yaml"
    f.write_text("loop:\n  min_inliers: 15.0\n  drift_fraction: 0.02\n")
    cfg = load_config(f)
    assert cfg.loop == {"min_inliers": 15, "drift_fraction": 0.02} and type(cfg.loop["min_inliers"]) is int
    with make_loop_closer(object(), cfg) as closer:
        assert closer.config["min_inliers"] == 15 and closer.config["drift_fraction"] == 0.02
        assert closer.config["ransac_px"] == DEFAULT_CONFIG["ransac_px"]
    with make_loop_closer(object(), load_config("accurate")) as closer:
        assert closer.config == {**DEFAULT_CONFIG, **accurate_loop}
    with make_loop_closer(object(), load_config("realtime")) as closer:
        assert closer.config == DEFAULT_CONFIG
    for bad, match in (("min_inlier: 12", "loop.min_inlier'"), ("min_inliers: 12.5", "loop.min_inliers must be a whole"),
                       ("drift_fraction: -0.1", "loop.drift_fraction must be >= 0"), ("min_score: high", "loop.min_score must be a number"),
                       ("pose_graph_dof: 5", "loop.pose_graph_dof")):
        f.write_text(f"loop:\n  {bad}\n")
        with pytest.raises(DataError, match=match):
            load_config(f)
    f.write_text("loop: [10]\n")
    with pytest.raises(DataError, match="loop must be a mapping"):
        load_config(f)


def test_event_support_counts_the_window_and_drops_lone_events(tmp_path, tiny_preset):
    """``event_support``: pixels with an event of either polarity in one window of the MCTS, over the
    5x5 around a keypoint. An edge (a line of fresh events) has five in its window, a fresh lone
    noise event one, and a noise event that only a long window still holds none in the shortest;
    ``detector.min_event_support: 3`` keeps the edge's keypoint alone, with its score and descriptor."""
    from aerovis_slam.keypoints import Keypoints
    from aerovis_slam.slam.frontend import event_support, supported_keypoints

    K = 4
    surfaces = np.zeros((2 * K, 40, 60), np.float32)
    surfaces[0, 5:16, 10] = 0.9        # OFF, shortest window: a vertical edge
    surfaces[K + 0, 20, 30] = 0.8      # ON, shortest window: a fresh lone event
    surfaces[3, 20, 45] = 0.4          # OFF, longest window only: a noise event 0.6 of that window ago
    surfaces[K + 3, 20, 30] = 0.95     # (the fresh event is in every window)
    xy = np.array([[10.0, 10.2], [30.0, 20.0], [45.0, 20.0], [58.6, 39.4]])
    assert event_support(surfaces, 0, xy).tolist() == [5, 1, 0, 0]
    assert event_support(surfaces, 3, xy).tolist() == [0, 1, 1, 0]
    with pytest.raises(ValueError, match="support window 4"):
        event_support(surfaces, 4, xy)
    kp = Keypoints(xy.astype(np.float32), np.array([0.1, 0.2, 0.3, 0.4], np.float32), np.eye(4, dtype=np.float32))
    kept = supported_keypoints(kp, surfaces, 0, 3)
    assert kept.xy.tolist() == [[10.0, np.float32(10.2)]] and kept.scores.tolist() == [np.float32(0.1)]
    assert kept.descriptors.tolist() == [[1.0, 0.0, 0.0, 0.0]]
    # the settings are checked: in the file, and the window against the detector's MCTS before a run
    f = tmp_path / "s.yaml"
    f.write_text("detector:\n  min_event_support: 26\n")
    with pytest.raises(DataError, match="detector.min_event_support"):
        load_config(f)
    cfg = load_config("accurate")
    cfg.detector.min_event_support, cfg.detector.support_window = 3, 4  # MCTS_Ne has windows 0..3
    with pytest.raises(DataError, match="support_window 4"):
        run_slam(tiny_preset / "tiny_handheld.h5", StereoClassicalDetector("orb", 100), cfg, progress=False)


def test_vision_velocity_needs_a_time_baseline():
    """Before the initialisation the velocity comes from tracked positions. Two frames 1 µs apart (the
    observation lag clamps a frame's time to just after the previous one) carry no velocity: 2 cm of
    position noise over 1 µs would be 20 km/s. Over 20 ms the same 2 cm are 1 m/s, averaged half and
    half with the previous estimate."""
    from aerovis_slam.slam.odometry import vision_velocity

    v_old = np.array([0.4, -0.2, 0.0])
    p0, p1 = np.array([1.0, 2.0, 3.0]), np.array([1.02, 2.0, 3.0])
    assert vision_velocity(p1, p0, v_old, 1e-6, 0.005).tolist() == v_old.tolist()
    np.testing.assert_allclose(vision_velocity(p1, p0, v_old, 0.02, 0.005), [0.5 * 1.0 + 0.2, -0.1, 0.0], atol=1e-12)


def _texture(shape=(120, 160), seed=0) -> np.ndarray:
    """A smooth random texture in [0, 1] (noise blurred over ~2 px, as a time surface's edges are)."""
    import cv2

    img = cv2.GaussianBlur(np.random.default_rng(seed).random(shape).astype(np.float32), (0, 0), 2.0)
    return (img - img.min()) / (img.max() - img.min())


def _shifted(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``img`` moved by (dx, dy) px: the content at x appears at x + dx (bicubic resampling)."""
    import cv2

    M = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(img, M, img.shape[::-1], flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


def test_track_refiner_aligns_observations_to_their_anchor():
    """A textured image moved by a known sub-pixel shift; the detections scatter +-2 px around the true
    positions. Aligned to the anchors of the first frame, every observation lands on its anchor's
    point moved by the shift. The bound, 0.1 px, is what the 8-bit images allow (a quantisation step
    of 1/255 over gradients of ~0.02 per px reads as ~0.05 px in the worst window) plus the
    tracker's stopping threshold (0.01 px)."""
    from aerovis_slam.slam.refine import TrackRefiner

    ref = TrackRefiner()
    img0 = _texture()
    rng = np.random.default_rng(1)
    anchors = np.c_[rng.uniform(20, 140, 30), rng.uniform(20, 100, 30)]
    first = Observations(np.arange(30), np.zeros(30, np.int8), anchors.copy())
    ref.begin_frame(0, [img0, img0])
    assert ref.refine(first).xy.tolist() == anchors.tolist()  # no anchors yet: these become them
    shift = np.array([2.3, -1.6])
    img1 = _shifted(img0, *shift)
    detected = anchors + shift + rng.uniform(-2, 2, anchors.shape)
    ref.begin_frame(20_000, [img1, img1])
    out = ref.refine(Observations(np.arange(30), np.zeros(30, np.int8), detected.copy()))
    assert ref.stats.refined == 30 and ref.stats.rejected == 0
    np.testing.assert_allclose(out.xy, anchors + shift, atol=0.1)
    # the right camera has no anchors of these landmarks: its observation becomes one, unchanged
    right = ref.refine(Observations(np.arange(3), np.ones(3, np.int8), detected[:3].copy()))
    assert right.xy.tolist() == detected[:3].tolist() and (0, 1) in ref.anchors
    # images are kept while an anchor uses them: the first frame's left image (30 anchors) and this
    # frame's right one (3); this frame's left image goes at the next frame
    ref.begin_frame(40_000, [img1, img1])
    ref.refine(Observations(np.arange(30), np.zeros(30, np.int8), detected.copy()))
    assert sorted(t for t, _ in ref.images.values()) == [0, 20_000, 40_000]
    assert len(ref.images) == 3 and {a[0] for a in ref.anchors.values()} <= set(ref.images)


def test_alignment_images_average_the_shortest_windows_of_both_polarities(tmp_path):
    """``refinement.windows``: the refinement's image is the mean of the ``windows`` shortest windows
    of each polarity (channel = p * K + k); None or K and more: every channel, as the default run
    computes it. A value below 1 is refused, in the settings file by name."""
    from aerovis_slam.slam.refine import alignment_images

    K, H, W = 4, 3, 5
    surfaces = np.zeros((2, 2 * K, H, W), np.float32)
    for c in range(2 * K):
        surfaces[:, c] = c + 1  # channel c holds the value c + 1 (both cameras)
    surfaces[1] *= 10
    two = alignment_images(surfaces, 2)  # OFF k = 0, 1 (1, 2) and ON k = 0, 1 (5, 6)
    assert two.shape == (2, H, W) and two.dtype == np.float32
    np.testing.assert_array_equal(two[0], np.full((H, W), (1 + 2 + 5 + 6) / 4))
    np.testing.assert_array_equal(two[1], np.full((H, W), 10 * (1 + 2 + 5 + 6) / 4))
    np.testing.assert_array_equal(alignment_images(surfaces, 1)[0], np.full((H, W), (1 + 5) / 2))
    for every in (None, K, K + 3):
        np.testing.assert_array_equal(alignment_images(surfaces, every), surfaces.mean(axis=1))
    with pytest.raises(ValueError, match="windows must be >= 1"):
        alignment_images(surfaces, 0)
    f = tmp_path / "short.yaml"
    f.write_text("refinement:\n  windows: 2\n")
    assert load_config(f).refinement.windows == 2
    assert load_config("accurate").refinement.windows == 3 and load_config("realtime").refinement.windows == 3
    f.write_text("refinement:\n  windows: 0\n")
    with pytest.raises(DataError, match="refinement.windows"):
        load_config(f)


def test_track_refiner_keeps_the_detection_where_the_anchor_is_not_found():
    """Where the current image holds no structure (no events around the keypoints: no gradient, so
    the tracker's 2x2 system is singular), the observations keep their detected positions; anchors
    older than max_anchor_age_s are replaced by the current observation."""
    from aerovis_slam.slam.refine import TrackRefiner

    ref = TrackRefiner(max_anchor_age_s=0.5)
    xy = np.array([[40.0, 40.0], [80.0, 60.0], [120.0, 80.0]])
    ref.begin_frame(0, [_texture()] * 2)
    ref.refine(Observations(np.arange(3), np.zeros(3, np.int8), xy.copy()))
    blank = np.full((120, 160), 0.3, np.float32)
    ref.begin_frame(20_000, [blank, blank])
    out = ref.refine(Observations(np.arange(3), np.zeros(3, np.int8), xy + 1.0))
    assert ref.stats.refined == 0 and ref.stats.rejected == 3
    np.testing.assert_array_equal(out.xy, xy + 1.0)
    assert all(ref.anchors[(i, 0)][1].tolist() == xy[i].tolist() for i in range(3))  # the anchors stay
    ref.begin_frame(600_000, [_texture(seed=5)] * 2)
    ref.refine(Observations(np.arange(3), np.zeros(3, np.int8), xy + 2.0))
    assert ref.stats.rejected == 3  # the old anchors expired: nothing aligned, three new anchors
    assert all(ref.anchors[(i, 0)][1].tolist() == (xy[i] + 2.0).tolist() for i in range(3))


def test_a_run_holds_numpy_blas_at_its_configured_threads(small_flight, tmp_path):
    """``blas_threads`` (default 1) holds every loaded BLAS at that many threads while the run
    lasts, the detector's thread included, and the setting is restored afterwards; null leaves it
    alone. (Why: OpenBLAS workers busy-wait after a product and take the cores ONNX Runtime needs.)"""
    from threadpoolctl import threadpool_info

    def blas_threads():
        return {i["filepath"]: i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}

    before = blas_threads()
    assert before  # numpy's OpenBLAS is loaded, so the check below means something

    class Recording(StereoClassicalDetector):
        def detect(self, batch, **kw):
            seen.append(blas_threads())
            stop.set()  # one frame is enough
            return super().detect(batch, **kw)

    for setting, expected in ((1, {k: 1 for k in before}), (None, before)):
        seen, stop = [], threading.Event()
        cfg = load_config("accurate")
        cfg.blas_threads = setting
        res = run_slam(small_flight, Recording("orb", 100), cfg, mode="sync", progress=False, stop_event=stop)
        assert not res.complete and res.status.startswith("stopped")
        assert seen and all({k: v[k] for k in before} == expected for v in seen)
        assert blas_threads() == before
    bad = tmp_path / "bad.yaml"
    bad.write_text("blas_threads: 0\n")
    with pytest.raises(DataError, match="blas_threads"):
        load_config(bad)
    bad.write_text("blas_threads: null\n")
    assert load_config(bad).blas_threads is None
