"""Tests of the SLAM tools: TUM files and ATE/RPE (evo), loop closure, reports and the ``aerovis-slam`` CLI.

Trajectory metrics are checked on cases with a known answer (a ground truth moved by a known
SE(3)/Sim(3) plus noise of known size); loop closure on a synthetic keyframe set with known
odometry drift; the CLI's writing side with a stand-in for the pipeline (its result is known), and
once end to end on the ``tiny`` preset with the real pipeline.
"""

from __future__ import annotations

import json
import types
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import REPO_ROOT

from aerovis_slam.errors import DataError
from aerovis_slam.geometry import invert_T, matrix_to_pose7, pose7_to_matrix, project, so3_exp, transform_points
from aerovis_slam.keypoints import Keypoints
from aerovis_slam.measurements import PoseSamples
from aerovis_slam.slam import bench as bench_mod
from aerovis_slam.slam.cli import main
from aerovis_slam.slam.config import load_config
from aerovis_slam.slam.loop import DEFAULT_CONFIG, LoopCloser, LoopClosure, _HeldLoop, _Snapshot, descriptor_vectors, split_yaw, train_vocabulary, vlad
from aerovis_slam.slam.trajectory import ate, end_error, final_trajectory, is_partial, read_tum, rpe, write_tum


# -- helpers -----------------------------------------------------------------------------------
def helix(t_us: np.ndarray, r: float = 1.0, omega: float = 1.0, vz: float = 0.1) -> PoseSamples:
    """A helix (radius r, yaw rate omega rad/s, climb vz m/s), body x along the tangent."""
    s = np.asarray(t_us, np.float64) / 1e6
    a = omega * s
    T = np.zeros((len(s), 4, 4))
    T[:, :3, :3] = so3_exp(np.stack([np.zeros_like(a), np.zeros_like(a), a + np.pi / 2], axis=1))
    T[:, :3, 3] = np.stack([r * np.cos(a), r * np.sin(a), vz * s], axis=1)
    T[:, 3, 3] = 1
    return PoseSamples(np.asarray(t_us, np.int64), matrix_to_pose7(T))


def transformed(traj: PoseSamples, T: np.ndarray, scale: float = 1.0, noise: np.ndarray | None = None) -> PoseSamples:
    """``scale * (T @ pose)`` (positions scaled, rotations rotated) plus position noise."""
    M = T @ pose7_to_matrix(traj.pose)
    M[:, :3, 3] *= scale
    if noise is not None:
        M[:, :3, 3] += noise
    return PoseSamples(traj.t.copy(), matrix_to_pose7(M))


def rigid(axis, angle_deg: float, t) -> np.ndarray:
    T = np.eye(4)
    a = np.asarray(axis, float)
    T[:3, :3] = so3_exp(a / np.linalg.norm(a) * np.radians(angle_deg))
    T[:3, 3] = t
    return T


# -- TUM files ---------------------------------------------------------------------------------
def test_tum_round_trip_is_exact_atomic_and_flags_partial(tmp_path):
    t = 1_700_000_000_000_000 + np.array([0, 1, 20_000, 1_000_003])  # epoch-scale µs: float64 seconds would lose them
    traj = helix(t - t[0])
    traj = PoseSamples(t, traj.pose)
    path = write_tum(tmp_path / "a.txt", traj.t, traj.pose, comments=["hello"])
    back = read_tum(path)
    assert back.t.tolist() == t.tolist()
    np.testing.assert_allclose(back.pose[:, :3], traj.pose[:, :3], atol=1e-7)  # written with 7 decimals (0.1 µm)
    np.testing.assert_allclose(back.pose[:, 3:], traj.pose[:, 3:], atol=1e-8)
    assert not is_partial(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]  # no temporary left behind
    write_tum(tmp_path / "b.txt", traj.t, traj.pose, partial=True)
    assert is_partial(tmp_path / "b.txt")


@pytest.mark.parametrize("body, where", [
    ("0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 1\n", "line 2: expected 8 values"),
    ("# c\n0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 x 1\n", "line 3: values must be numbers"),
    ("0 0 0 0 0 0 0 1\n0.2 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0 1\n", "line 3: time 0.1 s does not increase"),
    ("0 0 0 0 0 0 0 2\n", "line 1: quaternion"),
    ("0 0 0 nan 0 0 0 1\n", "line 1: non-finite"),
    ("# only a comment\n", "no poses"),
])
def test_read_tum_names_file_and_line(tmp_path, body, where):
    path = tmp_path / "bad.txt"
    path.write_text(body)
    with pytest.raises(DataError) as e:
        read_tum(path)
    assert str(path) in str(e.value) and where in str(e.value)


# -- ATE / RPE with known answers ---------------------------------------------------------------------
def test_ate_se3_recovers_known_transform_and_noise():
    t = np.arange(2000) * 5000  # 10 s at 200 Hz
    gt = helix(t)
    sigma = 0.01
    noise = np.random.default_rng(0).normal(0, sigma, (len(t), 3))
    est = transformed(gt, rigid([1, 2, 3], 30, [5, -2, 1]), noise=noise)
    r = ate(gt, est, align="se3")
    # E[RMSE^2] = sigma^2 (3N - 6) / N (6 parameters fitted to 3N residuals); the sample RMSE of
    # 3N = 6000 squared normals has a relative spread of sqrt(2 / 6000) / 2 = 0.9 %: 4 % is > 4 sigma.
    expected = sigma * np.sqrt((3 * len(t) - 6) / len(t))
    assert r["pairs"] == len(t) and r["align"] == "se3" and r["scale"] == 1.0
    assert abs(r["ate_rmse_m"] - expected) < 0.04 * expected
    # helix arc length 10 s * sqrt((r omega)^2 + vz^2); chords are shorter by ~(omega dt)^2 / 24 = 1e-6
    length = (t[-1] / 1e6) * np.sqrt(1 + 0.1**2)
    assert abs(r["path_length_m"] - length) < 1e-4 * length
    assert r["ate_pct"] == pytest.approx(100 * r["ate_rmse_m"] / r["path_length_m"])
    # without alignment the 5.5 m offset dominates
    assert ate(gt, est, align="none")["ate_rmse_m"] > 4.0


def test_ate_sim3_recovers_scale():
    t = np.arange(2000) * 5000
    gt = helix(t)
    sigma, s = 0.01, 2.5
    noise = np.random.default_rng(1).normal(0, sigma, (len(t), 3))
    est = transformed(gt, rigid([0, 1, 1], -50, [1, 2, 3]), scale=s, noise=noise)
    r = ate(gt, est, align="sim3")
    # alignment divides the estimate (and its noise) by s: ATE = sigma / s * sqrt((3N - 7) / N)
    expected = sigma / s * np.sqrt((3 * len(t) - 7) / len(t))
    assert abs(r["ate_rmse_m"] - expected) < 0.04 * expected
    # the scale's error is ~ noise / (spread * sqrt(N)) ~ 1e-4 relative
    assert r["scale"] == pytest.approx(1 / s, rel=1e-3)
    assert ate(gt, est, align="se3")["ate_rmse_m"] > 0.5  # SE(3) cannot undo a 2.5x scale


def test_ate_of_a_straight_line_uses_orientations():
    # collinear positions: evo's Umeyama refuses them; the orientation-aware fallback still finds
    # the exact transform, so a rigidly moved copy has zero error
    t = np.arange(500) * 10_000
    pose = np.zeros((len(t), 7))
    pose[:, 0] = t / 1e6
    pose[:, 3:] = matrix_to_pose7(rigid([0, 0, 1], 10, [0, 0, 0]))[3:]
    gt = PoseSamples(t, pose)
    est = transformed(gt, rigid([1, 1, 0], 40, [3, 0, -1]))
    assert ate(gt, est, align="se3")["ate_rmse_m"] < 1e-9
    assert ate(gt, transformed(gt, np.eye(4), scale=1.5), align="sim3")["scale"] == pytest.approx(1 / 1.5, rel=1e-9)


def test_end_error_aligns_the_start_and_measures_the_end():
    """An estimate in another world frame that follows the truth for 1.5 s and then drifts along x by
    0.1 m per second: aligned on its first 1.5 s, its last pose (5 s) is off by exactly 0.35 m, while
    the whole-run ATE alignment spreads that drift over both ends."""
    t = np.arange(0, 5_000_001, 10_000)
    gt = helix(t)
    drift = np.zeros((len(t), 3))
    drift[:, 0] = 0.1 * np.clip(t / 1e6 - 1.5, 0.0, None)
    est = transformed(gt, rigid([1, 2, 3], 40.0, [3.0, -1.0, 0.5]), noise=None)
    est = PoseSamples(est.t, np.concatenate([est.pose[:, :3] + drift @ rigid([1, 2, 3], 40.0, [0, 0, 0])[:3, :3].T,
                                             est.pose[:, 3:]], axis=1))
    r = end_error(gt, est)
    assert r["end_error_m"] == pytest.approx(0.35, abs=1e-6)
    assert r["end_error_align_s"] == 1.5 and r["end_error_t_s"] == pytest.approx(5.0)
    assert ate(gt, est, interpolate=True)["ate_max_m"] < 0.3  # the whole-run alignment halves it at the ends
    # a straight line (a slider's start): positions alone leave the roll about it open, the
    # orientations fix it; the estimate runs 2 % long after 1.5 s, so 2 % of the 2 m that follow
    line = PoseSamples(t, np.concatenate([np.stack([0.5 * t / 1e6, 0 * t, 0 * t], 1), np.tile([0, 0, 0, 1.0], (len(t), 1))], 1))
    long = line.pose.copy()
    long[:, 0] += 0.02 * 0.5 * np.clip(t / 1e6 - 1.5, 0.0, None)
    assert end_error(line, transformed(PoseSamples(t, long), rigid([0, 0, 1], 30.0, [1, 1, 0])))["end_error_m"] == pytest.approx(0.035, abs=1e-6)
    with pytest.raises(DataError, match="2 pose pair.* in the first 1.5 s"):
        end_error(gt, PoseSamples(t[[0, 100, 300, 400]], gt.pose[[0, 100, 300, 400]]))


def test_association_nearest_and_interpolated():
    gt = helix(np.arange(1000) * 10_000)  # 100 Hz
    t_est = np.arange(1, 190) * 50_000 + 1000  # 20 Hz, 1 ms after GT samples
    est = helix(t_est)
    # nearest pairs are 1 ms apart: unaligned error = speed * 1 ms = sqrt(1 + 0.01) mm exactly
    r = ate(gt, est, align="none", max_diff_s=0.002)
    assert r["pairs"] == len(t_est)
    assert r["ate_rmse_m"] == pytest.approx(np.sqrt(1.01) * 1e-3, rel=1e-6)
    # interpolating GT at the estimate times leaves the chord's sagitta r (omega dt)^2 / 8 = 1.25e-5 m
    assert ate(gt, est, align="none", interpolate=True)["ate_rmse_m"] < 1.3e-5
    with pytest.raises(DataError, match="no pose pairs"):
        ate(gt, est, max_diff_s=0.0005)


def test_final_trajectory_moves_outputs_with_their_keyframes():
    """Outputs keep their pose relative to their keyframe: when the smoother moves keyframe 1 by D
    and the pose graph corrects keyframe 2 by C, an output anchored to 1 becomes D-moved exactly,
    one anchored to 2 becomes C @ K2' @ rel, and an output without keyframe stays as it was."""
    K1, K2 = rigid([0, 0, 1], 6, [1, 0, 0]), rigid([1, 0, 6], 17, [2, 1, 0])
    rel_a, rel_b, rel_c = rigid([0, 1, 0], 1, [0.1, 0, 0]), rigid([1, 0, 0], 0.5, [0.3, 0.05, 0]), rigid([0, 0, 1], -1, [0.2, 0, 0.01])
    Tc_live = rigid([0, 0, 1], 0.5, [0.02, 0, 0])
    live = np.stack([rigid([0, 0, 1], 30, [9, 9, 9]), Tc_live @ K1 @ rel_a, Tc_live @ K1 @ rel_b, Tc_live @ K2 @ rel_c])
    D = rigid([0, 1, 2], 1.3, [0.03, -0.02, 0.01])
    K1_final, K2_final = D @ K1, rigid([1, 0, 6], 17.5, [2.02, 1, 0])
    C = rigid([0, 0, 1], -3, [-0.1, 0.2, 0])
    out = final_trajectory(live, np.array([-1, 1, 1, 2]), np.stack([np.eye(4), rel_a, rel_b, rel_c]), np.stack([Tc_live] * 4),
                           {1: K1_final, 2: K2_final}, {2: C})
    np.testing.assert_array_equal(out[0], live[0])
    np.testing.assert_allclose(out[1], Tc_live @ D @ K1 @ rel_a, atol=1e-12)  # keyframe 1: no pose-graph correction, the live one
    np.testing.assert_allclose(invert_T(out[1]) @ out[2], invert_T(rel_a) @ rel_b, atol=1e-12)  # rigid within a keyframe
    np.testing.assert_allclose(out[3], C @ K2_final @ rel_c, atol=1e-12)
    # a keyframe the smoother never reported: the output stays live
    np.testing.assert_array_equal(final_trajectory(live, np.array([-1, 1, 1, 3]), np.stack([np.eye(4), rel_a, rel_b, rel_c]),
                                                   np.stack([Tc_live] * 4), {1: K1_final})[3], live[3])


def test_rpe_known_velocity_and_yaw_rate_errors():
    t = np.arange(500) * 10_000  # 5 s at 100 Hz
    line = np.zeros((len(t), 7))
    line[:, 0], line[:, 6] = t / 1e6, 1.0  # 1 m/s along x
    fast = line.copy()
    fast[:, 0] *= 1.1  # 1.1 m/s: every 1 s the estimate moves 0.1 m too far
    r = rpe(PoseSamples(t, line), PoseSamples(t, fast), delta_s=1.0)
    # grid 0 .. 4.95 s every 50 ms = 100 points; pairs 20 steps apart: 80
    assert r["rpe_pairs"] == 80 and r["rpe_delta_s"] == 1.0
    assert r["rpe_trans_rmse_m"] == pytest.approx(0.1, abs=1e-9) and r["rpe_rot_rmse_deg"] == pytest.approx(0.0, abs=1e-6)
    yaw = lambda rate: matrix_to_pose7(np.stack([rigid([0, 0, 1], np.degrees(rate * s), [0, 0, 0]) for s in t / 1e6]))
    r = rpe(PoseSamples(t, yaw(0.2)), PoseSamples(t, yaw(0.22)), delta_s=1.0)
    assert r["rpe_rot_rmse_deg"] == pytest.approx(np.degrees(0.02), rel=1e-6) and r["rpe_trans_rmse_m"] < 1e-12


# -- loop closure -------------------------------------------------------------------------------------
W, H, F = 320, 240, 200.0
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])
T_BODY_CAM = np.eye(4)
T_BODY_CAM[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # camera looks along body x


def landmark_world(seed: int = 0, n: int = 3000, dim: int = 64):
    """Landmarks on a cylinder (radius 5 m) around the path, each with its own random descriptor."""
    rng = np.random.default_rng(seed)
    a, z = rng.uniform(0, 2 * np.pi, n), rng.uniform(-1.5, 1.5, n)
    desc = rng.normal(size=(n, dim))
    return np.stack([5 * np.cos(a), 5 * np.sin(a), z], 1), (desc / np.linalg.norm(desc, axis=1, keepdims=True)).astype(np.float32)


def circle_pose(theta: float, r: float = 2.0) -> np.ndarray:
    """On a circle of radius r, looking outwards."""
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array([0, 0, theta]))
    T[:3, 3] = [r * np.cos(theta), r * np.sin(theta), 0]
    return T


def observe(T_world_body, points, desc, rng, scramble: bool = False, confuse: bool = False):
    """Keypoints (0.5 px noise), descriptors (noisy copies) and body-frame landmarks (1 % depth noise
    along the ray, as stereo triangulation errs) of the visible landmarks. ``confuse``: each descriptor
    becomes ``0.6 d_i + 0.8 d_j`` of another visible landmark j (appearance changed with the motion:
    the global nearest neighbour is the wrong landmark, the right one still agrees at cosine 0.6)."""
    pc = transform_points(invert_T(T_world_body @ T_BODY_CAM), points)
    uv, z = project(pc, K)
    idx = np.flatnonzero((z > 0.1) & (uv[:, 0] >= 4) & (uv[:, 0] < W - 4) & (uv[:, 1] >= 4) & (uv[:, 1] < H - 4))
    xy = (uv[idx] + rng.normal(0, 0.5, (len(idx), 2))).astype(np.float32)
    d = desc[idx] + rng.normal(0, 0.05, (len(idx), desc.shape[1]))
    if confuse:
        d = 0.6 * d + 0.8 * d[rng.permutation(len(idx))]
    pts_body = transform_points(T_BODY_CAM, pc[idx] * (1 + rng.normal(0, 0.01, (len(idx), 1))))
    if scramble:  # same appearance, wrong geometry: keypoints where other landmarks are
        xy = xy[rng.permutation(len(idx))]
    return Keypoints(xy, np.ones(len(idx), np.float32), (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)), pts_body


def drive(closer: LoopCloser | None, n_kf: int = 66, step_deg: float = 6.0, yaw_drift: float = 0.002, side_drift: float = 0.005,
          seed: int = 0, scramble_from: int | None = None, confuse_from: int | None = None):
    """Keyframes every 6 deg around the circle with drifting odometry (yaw and sideways bias per step),
    fed as the SLAM backend does (odometry poses, never corrected ones). Returns (gt poses, the
    best estimates: the closer's corrected poses, or the odometry without a closer)."""
    points, desc = landmark_world(seed)
    rng = np.random.default_rng(seed + 1)
    E = np.eye(4)
    E[:3, :3] = so3_exp(np.array([0, 0, yaw_drift]))
    E[:3, 3] = [0, side_drift, 0]
    gt = [circle_pose(np.radians(step_deg * i)) for i in range(n_kf)]
    odom: list[np.ndarray] = []
    corrected: dict[int, np.ndarray] = {}
    for i in range(n_kf):
        odom.append(gt[0].copy() if i == 0 else odom[-1] @ (invert_T(gt[i - 1]) @ gt[i]) @ E)
        if closer is None:
            continue
        kp, pts = observe(gt[i], points, desc, rng, scramble=scramble_from is not None and i >= scramble_from,
                          confuse=confuse_from is not None and i >= confuse_from)
        closer.add_keyframe(i, i * 200_000, odom[i], kp, pts, np.ones(len(kp), bool), K, T_BODY_CAM)
        if i:
            closer.add_odometry(i - 1, i, invert_T(odom[i - 1]) @ odom[i])
        corrected.update(closer.poll() or {})  # never blocks
    if closer is None:
        return gt, odom
    assert closer.wait_idle(30)
    corrected.update(closer.poll() or {})
    return gt, [corrected.get(i, closer.last_correction @ odom[i]) for i in range(n_kf)]


@pytest.fixture(scope="module")
def vocabulary():
    """Words learnt from a different landmark set (the 'training data')."""
    return train_vocabulary(descriptor_vectors(landmark_world(seed=99)[1]), 32)


def test_loop_closure_corrects_drift_in_background(vocabulary):
    gt, open_loop = drive(None)
    drift = np.linalg.norm(open_loop[-1][:3, 3] - gt[-1][:3, 3])
    path = 66 * 2 * 2 * np.sin(np.radians(3))
    assert 0.02 * path > drift > 0.15  # ~2 % of the 13.8 m path: a real drift, inside the 5 % drift bound
    closer = LoopCloser(vocabulary=vocabulary)
    gt, est = drive(closer)
    assert closer.n_closures >= 1 and closer.stats["optimisations"] >= 1
    assert closer.closures[0].match < 10 and closer.closures[0].query > 50  # the revisit of the start
    final = np.linalg.norm(est[-1][:3, 3] - gt[-1][:3, 3])
    # The loop edge pins the revisit to the PnP accuracy (a few mm here, floors of 5 mm / 0.1 deg),
    # while the odometry chain's uncertainty is ~7 cm: the corrected end should sit within a few cm,
    # far below the 27 cm of open-loop drift (measured 3 cm; 25 % leaves room for noise).
    assert final < 0.25 * drift
    # per-keyframe corrections (the final trajectory's): applied to the odometry they give the corrected
    # poses, the loop's correction reaching back to keyframes before it (halfway round: moved too)
    corr = closer.corrections()
    _, odom = drive(None)
    assert sorted(corr) == list(range(66))
    np.testing.assert_allclose(corr[65] @ odom[65], est[65], atol=1e-9)
    np.testing.assert_allclose(corr[33] @ odom[33], est[33], atol=1e-9)
    assert np.linalg.norm(corr[33][:3, 3]) > 0.01
    thread = closer._thread
    closer.close()
    closer.close()  # idempotent
    assert thread is not None and not thread.is_alive()
    with pytest.raises(RuntimeError, match="closed"):
        closer.add_keyframe(999, 0, np.eye(4), Keypoints(np.zeros((0, 2)), np.zeros(0), np.zeros((0, 64))), np.zeros((0, 3)),
                            np.zeros(0, bool), K, T_BODY_CAM)


@pytest.mark.parametrize("setting", [0, 1])
def test_unrefined_keyframes_follow_the_loop_setting(setting):
    """A keyframe the caller marks ``unrefined`` (a vision-only pose beside a re-estimated map) is
    added only with ``unrefined_start_keyframes`` 1; ``add_keyframe`` says whether it was, and an
    ordinary keyframe is added either way."""
    empty = (Keypoints(np.zeros((0, 2)), np.zeros(0), np.zeros((0, 64))), np.zeros((0, 3)), np.zeros(0, bool), K, T_BODY_CAM)
    with LoopCloser(config={"unrefined_start_keyframes": setting}) as closer:
        assert closer.add_keyframe(0, 0, np.eye(4), *empty, unrefined=True) is bool(setting)
        assert closer.add_keyframe(1, 100_000, np.eye(4), *empty) is True
        assert closer._order == ([0] if setting else []) + [1]


def test_split_yaw_keeps_gravity_direction_for_any_mounting():
    rng = np.random.default_rng(3)
    x_up = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])  # body x along world z (EuRoC's IMU): no yaw-pitch-roll yaw
    for R in [so3_exp(rng.normal(size=3)) for _ in range(20)] + [x_up, so3_exp(np.array([0, 0, 2.5])) @ x_up]:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, rng.normal(size=3)
        Y, S = split_yaw(T)
        np.testing.assert_allclose(Y @ S, T, atol=1e-12)
        np.testing.assert_allclose(Y[:3, 2], [0, 0, 1], atol=1e-12)  # Y turns about world z only
        assert abs(S[:3, 3]).max() == 0 and abs(np.trace(S[:3, :3]) - 1 - 2 * S[2, 2]) < 1e-9  # S: about a horizontal axis
    # a turn about z alone is all yaw
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array([0, 0, -1.2]))
    np.testing.assert_allclose(split_yaw(T)[1], np.eye(4), atol=1e-12)


def test_pose_graph_moves_position_and_yaw_only():
    """A loop measured with a 5 deg roll error on a circle whose odometry drifted in yaw and sideways:
    the default 4-DoF graph removes the drift and leaves every keyframe's gravity direction as the
    odometry had it (an IMU observes roll and pitch); a 6-DoF graph tilts the map with the loop."""
    gt = [circle_pose(np.radians(12.0 * i)) for i in range(30)]
    E = np.eye(4)
    E[:3, :3] = so3_exp(np.array([0, 0, 0.004]))
    E[:3, 3] = [0, 0.005, 0]
    odom = [gt[0]]
    for i in range(1, 30):
        odom.append(odom[-1] @ (invert_T(gt[i - 1]) @ gt[i]) @ E)
    roll = np.eye(4)
    roll[:3, :3] = so3_exp(np.array([np.radians(5.0), 0, 0]))
    T_loop = invert_T(gt[0]) @ gt[29] @ roll  # rotation off by 5 deg of roll, translation exact
    cov = np.diag([1e-4] * 3 + [1e-4] * 3)
    edges = [(i - 1, i, invert_T(odom[i - 1]) @ odom[i], None) for i in range(1, 30)] + [(0, 29, T_loop, (1.0, cov))]
    snap = _Snapshot(list(range(30)), [T.copy() for T in odom], edges)

    def tilt_change_deg(poses):  # angle between the body-frame up directions of each pose and its odometry
        return max(np.degrees(np.arccos(np.clip(poses[i][:3, :3].T[:, 2] @ odom[i][:3, :3].T[:, 2], -1, 1))) for i in range(30))

    res4 = LoopCloser()._optimise(snap)
    res6 = LoopCloser(config={"pose_graph_dof": 6})._optimise(snap)
    drift = np.linalg.norm(odom[29][:3, 3] - gt[29][:3, 3])
    assert drift > 0.15  # 29 steps of 5 mm sideways and 0.23 deg of yaw
    # the attitude factors hold the tilt to their 1e-6 rad sigma against a 5 deg (0.087 rad) pull
    assert tilt_change_deg(res4.poses) < 1e-3
    assert tilt_change_deg(res6.poses) > 1.0
    # the loop's translation is exact, its yaw too: the 4-DoF graph pulls the end to within the
    # loop's 1 cm sigma (measured ~2 mm), as the 6-DoF graph would without the roll error
    assert np.linalg.norm(res4.poses[29][:3, 3] - gt[29][:3, 3]) < 0.1 * drift
    # corrections turn about the vertical only: gravity stays where it was
    for i in range(30):
        C = res4.poses[i] @ invert_T(odom[i])
        np.testing.assert_allclose(C[:3, 2], [0, 0, 1], atol=1e-5)
    with pytest.raises(ValueError, match="pose_graph_dof must be 4"):
        LoopCloser(config={"pose_graph_dof": 5})


def test_place_recognition_finds_revisit_rejects_non_revisit(vocabulary):
    points, desc = landmark_world(0)
    rng = np.random.default_rng(5)
    views = {deg: observe(circle_pose(np.radians(deg)), points, desc, rng)[0] for deg in (0, 3, 90, 180)}
    v = {deg: vlad(descriptor_vectors(kp.descriptors), vocabulary) for deg, kp in views.items()}
    min_score = LoopCloser().config["min_score"]
    # the same place seen again (3 deg apart, as the previous keyframe) scores high; the score is
    # normalised by it, and other places stay far below min_score times that reference
    ref = v[0] @ v[3]
    assert ref > 0.4
    assert max(v[0] @ v[90], v[0] @ v[180]) < 0.5 * min_score * ref
    # a 240-degree arc never comes back: no candidate, no closure
    closer = LoopCloser(vocabulary=vocabulary)
    drive(closer, n_kf=40)
    assert closer.n_closures == 0 and closer.stats["candidates"] == 0
    closer.close()


def test_verification_rejects_wrong_geometry_and_excess_drift(vocabulary):
    # same appearance, shuffled landmarks at the revisit: place recognition proposes, PnP refuses
    closer = LoopCloser(vocabulary=vocabulary)
    drive(closer, scramble_from=50)
    assert closer.stats["candidates"] > 0 and closer.stats["rejected_inliers"] == closer.stats["candidates"]
    assert closer.n_closures == 0
    closer.close()
    # 3x the drift (~0.8 m of correction and 20 deg of yaw after 13 m): beyond the bounds, refused,
    # even though every revisit keyframe agrees (no confirmation beyond max_rotation_drift_deg)
    closer = LoopCloser(vocabulary=vocabulary)
    drive(closer, yaw_drift=0.006, side_drift=0.015)
    assert closer.stats["rejected_drift"] > 0 and closer.n_closures == 0 and closer.stats["confirmed"] == 0
    closer.close()


def test_agreeing_keyframes_confirm_a_loop_beyond_the_drift_bound(vocabulary):
    """Odometry that drifted more than the drift bound allows (here a bound of 0.5 % + 5 cm against
    ~2 % of drift; in a run, a stretch of IMU-only propagation): each revisit keyframe alone is beyond
    it, three in a row imply the same correction, so the closer keeps them and the corrected end lies
    near the truth. Without confirmation, or beyond the confirmed bound, nothing is closed."""
    gt, open_loop = drive(None)
    drift = np.linalg.norm(open_loop[-1][:3, 3] - gt[-1][:3, 3])
    assert drift > 0.2
    tight = {"drift_fraction": 0.005}
    closer = LoopCloser(config=tight, vocabulary=vocabulary)
    gt, est = drive(closer)
    confirmed = [c for c in closer.closures if c.confirmed_by > 1]
    assert closer.stats["confirmed"] == len(confirmed) == 3
    assert [c.confirmed_by for c in confirmed] == [3, 3, 3] and closer.closures[0].to_dict()["confirmed_by"] == 3
    assert all(c.match < 10 and c.query > 50 for c in confirmed)  # revisits of the start, in keyframe order
    assert [c.query for c in confirmed] == sorted({c.query for c in confirmed})
    for c in confirmed:  # each beyond its own bound; the pose graph trusts it up to the confirmed one
        assert c.drift_m > closer._drift_bound(c.travelled_m)
        assert c.bound_m == pytest.approx(0.2 * c.travelled_m + 0.05)
    # the loops pin the revisit to the PnP accuracy (a few mm; 1 % depth noise on the landmarks) and
    # the keyframes after it drift by a few cm more: well below the open-loop drift (measured 3 cm)
    assert np.linalg.norm(est[-1][:3, 3] - gt[-1][:3, 3]) < 0.25 * drift
    closer.close()
    for off in ({"confirmations": 0}, {"confirm_drift_fraction": 0.01}):
        closer = LoopCloser(config=dict(tight, **off), vocabulary=vocabulary)
        _, est = drive(closer)
        assert closer.n_closures == 0 and closer.stats["rejected_drift"] > 0, off
        assert np.linalg.norm(est[-1][:3, 3] - gt[-1][:3, 3]) == pytest.approx(drift)
        closer.close()


def test_held_loops_need_agreeing_corrections():
    """The confirmation rule on its own: held loops (beyond the drift bound) of three keyframes are
    kept when their implied corrections agree within drift_min_m + 25 % of their size and 3 deg and
    reach two old keyframes; one disagreeing correction, a too old one, a rotation apart or a single
    old keyframe (whose landmark errors bias every loop to it alike) is not enough."""
    closer = LoopCloser()
    closer._order = list(range(20))

    def held(query, shift, yaw_deg=0.0, inliers=12, match=None):
        match = query - 15 if match is None else match  # the revisit of keyframes 0-4
        loop = LoopClosure(query, match, 0.9, inliers, np.eye(4), np.eye(4), 5.0, np.eye(6), query * 100_000, 0, bound_m=1.05)
        return _HeldLoop(loop, np.asarray(shift, float), so3_exp(np.array([0.0, 0.0, np.radians(yaw_deg)])))

    def confirm(items, newest=19):
        closer._held = list(items)
        return closer._confirm(types.SimpleNamespace(kf_id=newest))

    # 0.5 m corrections: tolerance 0.05 + 0.125 m around the newest; two loops of keyframe 18, the best kept
    agree = [held(17, [0.5, 0.0, 0.0]), held(18, [0.45, 0.1, 0.0], inliers=10), held(18, [0.55, -0.05, 0.0], inliers=15),
             held(19, [0.5, 0.05, 0.02], yaw_deg=2.0)]
    kept = confirm(agree)
    assert [(c.query, c.inliers, c.confirmed_by) for c in kept] == [(17, 12, 3), (18, 15, 3), (19, 12, 3)]
    assert len(closer._held) == 4  # nothing dropped until accepted
    # keyframe 18's corrections 0.2 m away from the newest's (tolerance 0.175 m): two keyframes are not three
    assert confirm([held(17, [0.5, 0, 0]), held(18, [0.7, 0.0, 0.0]), held(19, [0.5, 0, 0])]) == []
    # a correction turned 4 deg from the others' (limit 3 deg)
    assert confirm([held(17, [0.5, 0, 0], yaw_deg=4.0), held(18, [0.5, 0, 0]), held(19, [0.5, 0, 0])]) == []
    # keyframe 12 is more than 6 keyframes back: forgotten
    assert confirm([held(12, [0.5, 0, 0]), held(18, [0.5, 0, 0]), held(19, [0.5, 0, 0])]) == []
    assert [h.loop.query for h in closer._held] == [18, 19]
    # three keyframes agree, but all through old keyframe 3
    assert confirm([held(17, [0.5, 0, 0], match=3), held(18, [0.5, 0, 0], match=3), held(19, [0.5, 0, 0], match=3)]) == []
    assert len(confirm([held(17, [0.5, 0, 0], match=3), held(18, [0.5, 0, 0], match=3), held(19, [0.5, 0, 0], match=4)])) == 3
    # nothing held for the newest keyframe: no new evidence, no decision
    assert confirm([held(16, [0.5, 0, 0]), held(17, [0.5, 0, 0]), held(18, [0.5, 0, 0])]) == []


class _RefinedLater(LoopCloser):
    """A closer fed wrong landmarks for the first ``n_bad`` keyframes (each keypoint paired with
    another's point: a broken triangulation), then, at keyframe ``refine_at``, the right ones
    through :meth:`LoopCloser.update_points` (as the odometry does once its smoother refined them)."""

    def __init__(self, *args, n_bad: int = 10, refine_at: int | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        self.n_bad, self.refine_at, self.true_points = n_bad, refine_at, {}

    def add_keyframe(self, kf_id, t_us, T_world_body, keypoints, points_body, point_valid, K_, T_body_cam, **kw):
        if kf_id < self.n_bad:
            self.true_points[kf_id] = points_body.copy()
            points_body = np.roll(points_body, 7, axis=0)
        if kf_id == self.refine_at:
            for k, pts in self.true_points.items():
                self.update_points(k, np.arange(len(pts)), pts)
        return super().add_keyframe(kf_id, t_us, T_world_body, keypoints, points_body, point_valid, K_, T_body_cam, **kw)


def test_update_points_feeds_loop_verification(vocabulary):
    # the start's keyframes hold wrong landmarks: the revisit is proposed but PnP refuses it
    closer = _RefinedLater(vocabulary=vocabulary)
    drive(closer)
    assert closer.stats["rejected_inliers"] > 0 and closer.n_closures == 0
    closer.close()
    # the same, but refined before the revisit: the loop to the start closes
    closer = _RefinedLater(vocabulary=vocabulary, refine_at=12)
    drive(closer)
    assert closer.n_closures >= 1 and closer.closures[0].match < 10
    with pytest.raises(ValueError, match="rows must lie in"):
        closer.update_points(3, np.array([10_000]), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="1 rows but 2 points"):
        closer.update_points(3, np.array([0]), np.zeros((2, 3)))
    with pytest.raises(KeyError, match="never added"):
        closer.update_points(12345, np.array([0]), np.zeros((1, 3)))
    closer.update_points(3, np.array([0]), np.full((1, 3), np.nan))  # a lost estimate invalidates the point
    assert not closer._keyframes[3].point_valid[0]
    closer.close()


def test_odometry_refreshes_loop_points_from_the_smoother_window():
    """Keyframes in the smoother's window get its landmarks in the body frame of its own estimate of
    their pose; landmarks that left the window keep their points; keyframes out of the window are forgotten."""
    from aerovis_slam.slam.odometry import StereoInertialOdometry
    rng = np.random.default_rng(3)
    poses = {k: circle_pose(np.radians(10.0 * k)) for k in (4, 5, 6)}
    landmarks = {j: rng.normal(0, 2, 3) for j in (10, 11, 12)}  # 13 has left the window
    smoother = types.SimpleNamespace(kf_ids=[5, 6], landmark_estimates=lambda: landmarks,
                                     estimates={k: types.SimpleNamespace(T_world_body=T) for k, T in poses.items()})
    calls = []
    closer = types.SimpleNamespace(update_points=lambda k, rows, pts: calls.append((k, rows, pts)))
    odo = types.SimpleNamespace(smoother=smoother, loop_closer=closer, kf_loop_rows={
        4: (np.array([0]), np.array([10])), 5: (np.array([2, 7, 9]), np.array([13, 11, 10])), 6: (np.array([1]), np.array([13]))})
    StereoInertialOdometry._refresh_loop_points(odo)
    assert set(odo.kf_loop_rows) == {5, 6} and len(calls) == 1
    k, rows, pts = calls[0]
    assert k == 5 and rows.tolist() == [7, 9]
    expected = transform_points(invert_T(poses[5]), np.stack([landmarks[11], landmarks[10]]))
    np.testing.assert_allclose(pts, expected, atol=1e-12)


def test_guided_matching_closes_a_loop_whose_appearance_changed(vocabulary):
    """At the revisit every descriptor's global nearest neighbour is another landmark, so global
    matching gives a wrong geometry; matching within 40 px of the odometry's projection (the drift
    here is ~20 cm at ~5 m: ~8 px) finds the right landmarks and closes the loop. Without the guided
    fallback the same run closes nothing."""
    gt, open_loop = drive(None)
    drift = np.linalg.norm(open_loop[-1][:3, 3] - gt[-1][:3, 3])
    closer = LoopCloser(config={"guided_window_px": 0.0}, vocabulary=vocabulary)
    drive(closer, confuse_from=50)
    assert closer.n_closures == 0 and closer.stats["rejected_inliers"] > 0
    closer.close()
    closer = LoopCloser(vocabulary=vocabulary)
    gt, est = drive(closer, confuse_from=50)
    assert closer.n_closures >= 1 and closer.closures[0].query >= 50 and closer.closures[0].match < 10
    assert np.linalg.norm(est[-1][:3, 3] - gt[-1][:3, 3]) < 0.25 * drift
    closer.close()


def test_rematch_measures_a_loop_with_every_landmark_it_can_see():
    """A loop found through a dozen descriptor matches, while the match keyframe sees hundreds of
    landmarks the query sees too: projecting all of them with the PnP pose and matching near the
    projection (``rematch_window_px``) fits the pose to all, as the verification could not. With
    independent landmark errors (1 % of depth) and 0.5 px keypoint noise, the error of a pose from n
    points falls as 1/sqrt(n): from 12 to ~370 pairs, to ~0.18x; asserted below 0.4x over 20 loops
    (the mean of 20 errors scatters by ~20 %), and the fits' pair counts at least 10x."""
    from aerovis_slam.geometry import pose_difference
    from aerovis_slam.keypoints import match_keypoints

    points, desc = landmark_world(seed=5)
    errors = {0.0: [], 4.0: []}
    counts = {0.0: [], 4.0: []}
    for trial in range(20):
        rng = np.random.default_rng(100 + trial)
        T_match = circle_pose(np.radians(rng.uniform(0, 360)))
        T_query = T_match @ rigid([0, 0, 1], rng.uniform(-4, 4), [rng.uniform(-0.2, 0.2), rng.uniform(-0.3, 0.3), 0])
        kp_m, pts_m = observe(T_match, points, desc, rng)
        kp_q, pts_q = observe(T_query, points, desc, rng)
        pairs = match_keypoints(kp_q, kp_m)
        few = pairs[rng.choice(len(pairs), 12, replace=False)]
        for window in errors:
            closer = LoopCloser(config={"rematch_window_px": window})
            closer.add_keyframe(0, 0, T_match, kp_m, pts_m, np.ones(len(kp_m), bool), K, T_BODY_CAM)
            closer.add_keyframe(30, 6_000_000, T_query, kp_q, pts_q, np.ones(len(kp_q), bool), K, T_BODY_CAM)
            loop, reason = closer._verify_pairs(closer._keyframes[30], closer._keyframes[0], few, 1.0)
            assert reason is None, reason
            errors[window].append(pose_difference(invert_T(T_match) @ T_query, loop.T_match_query)[0])
            counts[window].append(loop.inliers)
            closer.close()
    assert min(counts[0.0]) >= 10 and max(counts[0.0]) <= 12
    assert np.min(np.array(counts[4.0]) / np.array(counts[0.0])) >= 10
    assert np.mean(errors[4.0]) < 0.4 * np.mean(errors[0.0])


def test_online_vocabulary_when_none_fits():
    # 10-D words cannot serve 64-D descriptors; one candidate per keyframe keeps the test short
    closer = LoopCloser(config={"online_vocabulary_keyframes": 8, "max_candidates": 1}, vocabulary=np.zeros((16, 10), np.float32))
    gt, est = drive(closer)
    assert any("online" in w for w in closer.warnings) and closer.vocabulary.shape[1] == 64
    assert closer.n_closures >= 1
    closer.close()


def test_binary_descriptors_unpack_so_that_l2_is_hamming():
    rng = np.random.default_rng(0)
    d = rng.integers(0, 256, (5, 32), dtype=np.uint8)
    v = descriptor_vectors(d)
    ham = np.unpackbits(d[:, None] ^ d[None], axis=2).sum(2)
    np.testing.assert_array_equal(((v[:, None] - v[None]) ** 2).sum(2), ham)


# -- the CLI ------------------------------------------------------------------------------------------------
def test_cli_eval_prints_json(tmp_path, capsys):
    t = np.arange(1000) * 10_000
    gt = helix(t)
    est = transformed(gt, rigid([0, 0, 1], 20, [1, 0, 0]), scale=2.0)
    write_tum(tmp_path / "gt.txt", gt.t, gt.pose)
    write_tum(tmp_path / "est.txt", est.t, est.pose)
    assert main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--align", "sim3"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["pairs"] == 1000 and r["align"] == "sim3" and r["ate_rmse_m"] < 1e-6 and r["scale"] == pytest.approx(0.5)
    assert r["partial"] is False and r["rpe_pairs"] > 0
    (tmp_path / "bad.txt").write_text("0 0 0 0 0 0 0 1\n0.5 1 2 3\n")
    assert main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "bad.txt")]) == 2
    err = capsys.readouterr().err
    assert "bad.txt" in err and "line 2" in err


def _tiny_sequence(path):
    """A canonical file with a few events and 2 s of helix ground truth at 200 Hz."""
    from aerovis_slam.events import EventArray
    from aerovis_slam.io.sequence import SequenceWriter

    with SequenceWriter(path, sensor_sizes={"cam0": (64, 48), "cam1": (64, 48)}) as w:
        for cam in ("cam0", "cam1"):
            w.add_events(cam, EventArray([0, 1000, 2_000_000], [1, 2, 3], [1, 2, 3], [1, 0, 1]))
        w.set_gt(helix(np.arange(401) * 5000))
    return path


def _fake_runner(delta: float = 0.01, complete: bool = True, status: str = "ok", seen: dict | None = None):
    """A stand-in for run_slam with a known result: the GT at 50 Hz with z alternating by +-delta;
    a complete run's final trajectory is the GT itself."""
    def run(sequence, detector, config, *, mode, loop_closer, progress, stop_event, frame_slots=None, frame_caps=None):
        if seen is not None:
            seen.update(mode=mode, loop_closer=loop_closer, detector=detector, frame_slots=frame_slots, frame_caps=frame_caps)
        t = np.arange(2, 98) * 20_000  # 96 poses
        pose = helix(t).pose.copy()
        pose[:, 2] += delta * (-1.0) ** np.arange(len(t))
        return types.SimpleNamespace(t_us=t, pose7=pose, latency_ms=np.arange(len(t), dtype=float), wall_s=2.0,
                                     slot_us=t + 5_000, tracked=np.arange(len(t)) % 3 > 0,
                                     iteration_caps=[[4, 2] if i % 10 == 0 else [] for i in range(len(t))],
                                     sequence_duration_s=2.0, stage_ms={"detector": [1.0, 2.0, 3.0], "backend": [],
                                                                        "total": [0.5] * len(t)},
                                     loop_closures=1, tracking_losses=2, warnings=["burst"], status=status, complete=complete,
                                     pose7_final=helix(t).pose.copy() if complete else None)
    return run


def test_pose_rate_counts_the_data_after_the_warm_up():
    """``pose_rate_hz`` is per second of data from the warm-up's first frame on (no pose is due
    before it); ``real_time_factor`` keeps the whole replayed span, whose events were all ingested."""
    from aerovis_slam.slam.report import compute_metrics
    t = 500_000 + np.arange(100) * 20_000  # 100 poses at 50 Hz from 0.5 s to 2.5 s
    result = types.SimpleNamespace(t_us=t, pose7=helix(t).pose, latency_ms=np.zeros(100), wall_s=5.0,
                                   sequence_duration_s=2.5, stage_ms={}, loop_closures=0, tracking_losses=0,
                                   warnings=[], status="ok", complete=True,
                                   info={"t_begin_us": 0, "t_first_frame_us": 500_000})
    m, _, _ = compute_metrics(result, None)
    assert m["pose_rate_hz"] == pytest.approx(100 / 2.0)
    assert m["real_time_factor"] == pytest.approx(5.0 / 2.5) and m["rate_hz"] == pytest.approx(100 / 5.0)
    result.info = {}  # no warm-up information (e.g. a result from elsewhere): the whole span
    assert compute_metrics(result, None)[0]["pose_rate_hz"] == pytest.approx(100 / 2.5)


@pytest.fixture()
def empty_config(tmp_path):
    p = tmp_path / "defaults.yaml"
    p.write_text("{}\n")
    return p


def test_cli_run_writes_outputs(tmp_path, capsys, monkeypatch, empty_config):
    seq = _tiny_sequence(tmp_path / "seq.h5")
    seen: dict = {}
    monkeypatch.setattr(bench_mod, "_run_slam", _fake_runner(seen=seen))
    plotted: dict = {}
    draw = bench_mod.plot_trajectory
    monkeypatch.setattr(bench_mod, "plot_trajectory", lambda *a, **k: (plotted.update(k), draw(*a, **k))[1])
    out = tmp_path / "out"
    rc = main(["run", str(seq), "--detector", "orb", "--config", str(empty_config), "--mode", "async", "--out", str(out), "--quiet"])
    assert rc == 0
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert isinstance(seen["loop_closer"], LoopCloser) and seen["mode"] == "async" and seen["detector"].name == "classical-orb"
    m = json.loads((out / "metrics.json").read_text())
    # +-delta alternating in z: SE(3) alignment cannot absorb it (zero mean, no rigid pattern), ATE = delta
    assert m["ate_rmse_m"] == pytest.approx(0.01, rel=0.02) and line["ate_rmse_m"] == m["ate_rmse_m"]
    assert m["poses"] == 96 and m["rate_hz"] == pytest.approx(48.0) and m["real_time_factor"] == pytest.approx(1.0)
    assert m["latency_ms_p50"] == pytest.approx(47.5) and m["latency_ms_p90"] == pytest.approx(np.percentile(np.arange(96), 90))
    assert m["stages"]["detector"]["p50_ms"] == 2.0 and m["stages"]["backend"]["count"] == 0
    assert m["loop_closures"] == 1 and m["tracking_losses"] == 2 and "burst" in m["warnings"] and m["complete"] is True
    assert m["rpe_trans_rmse_m"] is not None and m["path_length_m"] > 0
    assert m["settings"] == load_config(empty_config).to_dict()  # every value, not only the file's name
    back = read_tum(out / "traj.txt")
    assert len(back) == 96 and not is_partial(out / "traj.txt")
    # the final trajectory (the GT itself here): its own file and an ATE of zero
    final = read_tum(out / "traj_final.txt")
    assert np.array_equal(final.t, back.t) and m["final_trajectory_file"] == "traj_final.txt"
    assert m["final"]["ate_rmse_m"] < 1e-6 and line["ate_pct_final"] == m["final"]["ate_pct"]
    assert (out / "traj.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert plotted["final_result"]["ate_rmse_m"] < 1e-6  # traj.png draws the final trajectory too
    # a partial run: flagged file name and header, the old complete trajectory removed
    monkeypatch.setattr(bench_mod, "_run_slam", _fake_runner(complete=False, status="ok", seen=seen))
    assert main(["run", str(seq), "--detector", "orb", "--config", str(empty_config), "--no-loop", "--out", str(out), "--quiet"]) == 0
    assert seen["loop_closer"] is None
    assert not (out / "traj.txt").exists() and is_partial(out / "traj.partial.txt")
    assert not (out / "traj_final.txt").exists()  # no final trajectory of an unfinished run, none left from before
    assert json.loads((out / "metrics.json").read_text())["complete"] is False
    assert json.loads((out / "metrics.json").read_text())["final"] is None
    # a failed run still writes its outputs and exits 1
    monkeypatch.setattr(bench_mod, "_run_slam", _fake_runner(status="failed: diverged"))
    assert main(["run", str(seq), "--detector", "orb", "--config", str(empty_config), "--out", str(out), "--quiet"]) == 1
    capsys.readouterr()
    # bad input: exit 2 and the message names the file
    assert main(["run", str(tmp_path / "missing.h5"), "--detector", "orb", "--out", str(out)]) == 2
    assert "missing.h5" in capsys.readouterr().err


def test_cli_run_frames_file_and_replay(tmp_path, capsys, monkeypatch, empty_config):
    """``frames.txt`` holds each output's slot, time, latency, processing time, tracking flag and
    backend iteration caps; ``--frame-slots`` reads slots and caps back into the run (async only),
    takes a plain list of slots too, and refuses bad files."""
    seq = _tiny_sequence(tmp_path / "seq.h5")
    seen: dict = {}
    monkeypatch.setattr(bench_mod, "_run_slam", _fake_runner(seen=seen))
    out = tmp_path / "out"
    assert main(["run", str(seq), "--detector", "orb", "--config", str(empty_config), "--mode", "async", "--out", str(out),
                 "--quiet"]) == 0
    assert seen["frame_slots"] is None and seen["frame_caps"] is None
    lines = [ln.split() for ln in (out / "frames.txt").read_text().splitlines() if not ln.startswith("#")]
    t = np.arange(2, 98) * 20_000
    caps = [[4, 2] if i % 10 == 0 else [] for i in range(96)]
    assert len(lines) == 96 and all(len(f) == 6 for f in lines)
    rows = np.array([[float(x) for x in f[:5]] for f in lines])
    assert np.array_equal(rows[:, 0], t + 5_000) and np.array_equal(rows[:, 1], t)
    assert np.array_equal(rows[:, 2], np.arange(96)) and np.all(rows[:, 3] == 0.5)
    assert np.array_equal(rows[:, 4], np.arange(96) % 3 > 0)
    assert lines[0][5] == "4,2" and lines[1][5] == "-"
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames_file"] == "frames.txt" and m["frame_slots_replayed"] is False
    # replay: slots and caps go to the run, in async mode (the default for --frame-slots)
    assert main(["run", str(seq), "--detector", "orb", "--config", str(empty_config), "--frame-slots",
                 str(out / "frames.txt"), "--out", str(tmp_path / "replay"), "--quiet"]) == 0
    assert seen["mode"] == "async" and np.array_equal(seen["frame_slots"], t + 5_000) and seen["frame_caps"] == caps
    assert json.loads((tmp_path / "replay" / "metrics.json").read_text())["frame_slots_replayed"] is True
    plain = tmp_path / "slots.txt"  # one slot per line: slots without caps
    plain.write_text("# hand-made\n100000\n150000\n")
    assert main(["run", str(seq), "--detector", "orb", "--frame-slots", str(plain), "--out", str(tmp_path / "p"), "--quiet"]) == 0
    assert seen["frame_slots"].tolist() == [100000, 150000] and seen["frame_caps"] is None
    capsys.readouterr()
    # bad input: exit 2, the message names the file and what is wrong
    bad = tmp_path / "bad.txt"
    for text, expect in (("# only a comment\n", "no frame slots"), ("100\n90\n", "increase strictly"),
                         ("100\nabc 1\n", "line 2"), ("1 1 0 0 1 4,x\n", "iteration caps"),
                         ("1 1 0 0 1 4\n2\n", "all or none")):
        bad.write_text(text)
        assert main(["run", str(seq), "--detector", "orb", "--frame-slots", str(bad), "--out", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert "bad.txt" in err and expect in err
    assert main(["run", str(seq), "--detector", "orb", "--mode", "sync", "--frame-slots", str(out / "frames.txt"),
                 "--out", str(out), "--quiet"]) == 2
    assert "async" in capsys.readouterr().err


def test_bench_table_and_json(tmp_path, monkeypatch, empty_config):
    seq = _tiny_sequence(tmp_path / "tiny_a.h5")
    calls = []

    def runner(sequence, detector, config, **kw):
        calls.append((detector.name, kw["mode"]))
        if detector.name == "classical-orb" and kw["mode"] == "async":
            raise RuntimeError("boom")  # a crashing run is a failed cell, not the end of the benchmark
        return _fake_runner(delta=0.01 if detector.name == "learned" else 0.03)(sequence, detector, config, **kw)

    monkeypatch.setattr(bench_mod, "_run_slam", runner)
    dets = [types.SimpleNamespace(name="learned"), types.SimpleNamespace(name="classical-orb")]
    rows = bench_mod.run_bench([seq], dets, tmp_path / "b", config=str(empty_config), loop=False, progress=False)
    assert len(calls) == 4 and len(rows) == 4
    assert json.loads((tmp_path / "b" / "bench.json").read_text()) == rows
    assert set(rows[0]) == set(bench_mod.BENCH_FIELDS)
    status = {(r["detector"], r["mode"]): r["status"] for r in rows}
    assert status == {("learned", "sync"): "ok", ("learned", "async"): "ok", ("classical-orb", "sync"): "ok",
                      ("classical-orb", "async"): "failed"}
    table = (tmp_path / "b" / "table.md").read_text()
    assert "| tiny_a |" in table and "failed" in table and "**1.00" in table  # the best ATE (learned, 1 cm) in bold
    assert "Final trajectory" in table and "| tiny_a | 0.00 % | 0.00 % | 0.00 % |  |" in table
    assert [r["ate_pct_final"] for r in rows if r["status"] == "ok"] == pytest.approx([0.0] * 3, abs=1e-9)
    # end error: the estimate's z alternates by +-delta, so once its first 1.5 s are aligned (where the
    # alternation averages out) the last pose is delta off; the final trajectory is the GT itself
    ends = {(r["detector"], r["mode"]): (r["end_error_m"], r["end_error_m_final"]) for r in rows if r["status"] == "ok"}
    assert ends[("learned", "sync")][0] == pytest.approx(0.01, abs=1e-3) and ends[("classical-orb", "sync")][0] == pytest.approx(0.03, abs=3e-3)
    assert [e[1] for e in ends.values()] == pytest.approx([0.0] * 3, abs=1e-9)
    cells = [f"{100 * ends[k][0]:.1f} (0.0)" for k in [("learned", "sync"), ("learned", "async"), ("classical-orb", "sync")]]
    assert "End error [cm]" in table and f"| tiny_a | {' | '.join(cells)} |  |" in table and cells[0] == "1.0 (0.0)"
    s = bench_mod.summarize(rows)
    assert s["learned/sync"]["best_on"] == 1 and s["classical-orb/async"]["ok"] == 0
    # loops judged by the ground truth: counted where the loop's error is below the drift it corrected
    m = {"loop_closures": 3, "loop": {"closures": [{"error_m": 0.05, "true_drift_m": 0.12}, {"error_m": 0.2, "true_drift_m": 0.1},
                                                    {"error_m": 0.01, "true_drift_m": 0.02}]}, "rate_hz": 10.0}
    assert bench_mod.bench_row("s", "sync", "d", m, "ok")["loops_better_than_drift"] == 2
    assert rows[0]["loops_better_than_drift"] is None  # no closure judged (the fake runs have no loop records)
    assert "| 48.0 (1 LC) |" in table and "better)" not in table
    assert "(3 LC, 2 better)" in bench_mod.format_table([dict(rows[0], loop_closures=3, loops_better_than_drift=2)])
    # what the figures were measured with: beside bench.json, in the table's footer and in every run's metrics.json
    import numpy

    env = json.loads((tmp_path / "b" / "environment.json").read_text())
    assert env["packages"]["numpy"] == numpy.__version__
    assert f"numpy {numpy.__version__}" in table.splitlines()[-1]
    run_env = json.loads((tmp_path / "b" / "tiny_a" / "learned-sync" / "metrics.json").read_text())["environment"]
    assert run_env == env
    # a diverged run is marked as such
    assert bench_mod.classify({"status": "ok", "complete": True, "ate_rmse_m": 0.5, "path_length_m": 1.0}) == "diverged"


def test_bench_runs_each_oracle_noise_as_a_variant(tmp_path, monkeypatch, empty_config):
    """``bench --oracle-noise-px 0 0.5``: every detector runs at each noise (the runner sees it in its
    config), as ``<detector>+oracle<X>px`` in folders, rows and one table; metrics.json records it."""
    import aerovis_slam.slam.oracle as oracle_mod

    seq = _tiny_sequence(tmp_path / "tiny_a.h5")
    monkeypatch.setattr(oracle_mod, "oracle_spec", lambda sequence, noise_px=0.0: None)  # not a simulated file
    seen = []

    def runner(sequence, detector, config, **kw):
        seen.append((detector.name, config.detector.oracle_noise_px))
        return _fake_runner()(sequence, detector, config, **kw)

    monkeypatch.setattr(bench_mod, "_run_slam", runner)
    dets = [types.SimpleNamespace(name="learned"), types.SimpleNamespace(name="classical-orb")]
    rows = bench_mod.run_bench([seq], dets, tmp_path / "b", modes=("sync",), config=str(empty_config), loop=False,
                               progress=False, oracle_noise_px=[0.0, 0.5])
    assert seen == [("learned", 0.0), ("learned", 0.5), ("classical-orb", 0.0), ("classical-orb", 0.5)]
    names = ["learned+oracle0px", "learned+oracle0.5px", "classical-orb+oracle0px", "classical-orb+oracle0.5px"]
    assert [r["detector"] for r in rows] == names
    m = json.loads((tmp_path / "b" / "tiny_a" / "learned+oracle0.5px-sync" / "metrics.json").read_text())
    assert m["oracle_noise_px"] == 0.5
    header = (tmp_path / "b" / "table.md").read_text().split("| Sequence | path [m] |")[1].splitlines()[0]
    assert all(f"{n} sync" in header for n in names)


def test_bench_keypoint_errors_reach_every_run_and_the_table(tmp_path, monkeypatch, empty_config):
    """``bench --keypoint-errors``: every run measures (the runner sees it in its config), each row
    carries the run's median keypoint distance and the table adds a table of them; refused together
    with oracle noise."""
    import aerovis_slam.slam.oracle as oracle_mod

    seq = _tiny_sequence(tmp_path / "tiny_a.h5")
    monkeypatch.setattr(oracle_mod, "oracle_spec", lambda sequence, noise_px=0.0: None)  # not a simulated file
    medians = {"learned": 0.8125, "classical-orb": 1.25}

    def runner(sequence, detector, config, **kw):
        assert config.detector.measure_keypoint_errors
        res = _fake_runner()(sequence, detector, config, **kw)
        res.info = {"keypoint_errors": {"observations": 10, "median_px": medians[detector.name], "p90_px": 2.0}}
        return res

    monkeypatch.setattr(bench_mod, "_run_slam", runner)
    dets = [types.SimpleNamespace(name="learned"), types.SimpleNamespace(name="classical-orb")]
    rows = bench_mod.run_bench([seq], dets, tmp_path / "b", modes=("sync",), config=str(empty_config), loop=False,
                               progress=False, keypoint_errors=True)
    assert [r["keypoint_error_px"] for r in rows] == [0.8125, 1.25]
    table = (tmp_path / "b" / "table.md").read_text()
    assert "Keypoint error" in table and "| tiny_a | 0.81 | 1.25 |" in table
    with pytest.raises(ValueError, match="exclude each other"):
        bench_mod.run_bench([seq], dets, tmp_path / "c", modes=("sync",), progress=False, keypoint_errors=True,
                            oracle_noise_px=0.5)


def test_bench_repeats_perturb_and_aggregate(tmp_path, monkeypatch, empty_config, capsys):
    """Repeat i >= 1 runs with keypoint noise seeded i (seen in the config the runner gets); the
    spread table and ``best_on_mean`` aggregate exactly the runs' ATE."""
    seq = _tiny_sequence(tmp_path / "tiny_a.h5")
    seen = []
    # ATE of a run = delta (the fake's alternating offset): learned 1, 2, 3 cm; classical 1.5 cm every time
    deltas = {("learned", 0): 0.01, ("learned", 1): 0.02, ("learned", 2): 0.03}

    def runner(sequence, detector, config, **kw):
        d = config.detector
        seen.append((detector.name, d.keypoint_noise_px, d.keypoint_noise_seed))
        return _fake_runner(delta=deltas.get((detector.name, d.keypoint_noise_seed), 0.015))(sequence, detector, config, **kw)

    monkeypatch.setattr(bench_mod, "_run_slam", runner)
    dets = [types.SimpleNamespace(name="learned"), types.SimpleNamespace(name="classical-orb")]
    rows = bench_mod.run_bench([seq], dets, tmp_path / "b", modes=("sync",), config=str(empty_config), loop=False,
                               progress=False, repeats=3, keypoint_noise_px=0.3)
    assert seen == [("learned", 0.0, 0), ("learned", 0.3, 1), ("learned", 0.3, 2),
                    ("classical-orb", 0.0, 0), ("classical-orb", 0.3, 1), ("classical-orb", 0.3, 2)]
    assert [(r["repeat"], r["keypoint_noise_px"]) for r in rows[:3]] == [(0, 0.0), (1, 0.3), (2, 0.3)]
    assert (tmp_path / "b" / "tiny_a" / "learned-sync" / "metrics.json").is_file()
    m2 = json.loads((tmp_path / "b" / "tiny_a" / "learned-sync-r2" / "metrics.json").read_text())
    assert m2["keypoint_noise_px"] == 0.3 and m2["keypoint_noise_seed"] == 2
    pct = {(r["detector"], r["repeat"]): r["ate_pct"] for r in rows}
    table = (tmp_path / "b" / "table.md").read_text()
    mean_l = (pct[("learned", 0)] + pct[("learned", 1)] + pct[("learned", 2)]) / 3
    assert f"{mean_l:.2f} ({pct[('learned', 0)]:.2f}-{pct[('learned', 2)]:.2f}), median {pct[('learned', 1)]:.2f}" in table
    assert f"**{pct[('classical-orb', 0)]:.2f} (" in table  # 1.5 cm every time beats the mean of 1, 2, 3 cm
    # the final trajectories' spread (the fake's final trajectory is the ground truth: 0 %, a tie)
    final_table = table.split("final trajectories (`traj_final.txt`): mean (min-max) and median")[1]
    assert "| tiny_a | **0.00 (0.00-0.00), median 0.00** | **0.00 (0.00-0.00), median 0.00** |" in final_table
    s = bench_mod.summarize(rows)
    # the first runs: learned (1 cm) best; the means: classical (1.5 < 2 cm) best
    assert s["learned/sync"]["best_on"] == 1 and s["learned/sync"]["best_on_mean"] == 0
    assert s["classical-orb/sync"]["best_on_mean"] == 1 and s["classical-orb/sync"]["repeats"] == 3
    # the medians: 2 cm against 1.5 cm, classical again
    assert s["classical-orb/sync"]["best_on_median"] == 1 and s["learned/sync"]["best_on_median"] == 0
    assert s["learned/sync"]["runs"] == 1  # the headline counts describe the first runs
    # resume reads the noise back from metrics.json
    again = bench_mod.run_bench([seq], dets, tmp_path / "b", modes=("sync",), config=str(empty_config), loop=False,
                                progress=False, repeats=3, keypoint_noise_px=0.3, resume=True)
    assert again == rows and len(seen) == 6
    # repeats without noise would repeat a sync run exactly: refused
    with pytest.raises(ValueError, match="noise"):
        bench_mod.run_bench([seq], dets, tmp_path / "c", repeats=2, keypoint_noise_px=0.0, progress=False)
    assert main(["bench", "--sequences", str(seq), "--detector", "orb", "--no-learned", "--repeats", "2",
                 "--keypoint-noise-px", "0", "--out", str(tmp_path / "d"), "--quiet"]) == 2
    assert "--repeats 2" in capsys.readouterr().err


def test_bench_refuses_a_bad_settings_file_before_any_run(tmp_path, monkeypatch):
    """A settings file the loader refuses stops the benchmark at once with the loader's message (file
    and field), instead of one "failed" cell per run; nothing is written."""
    seq = _tiny_sequence(tmp_path / "tiny_a.h5")
    bad = tmp_path / "bad.yaml"
    bad.write_text("init:\n  gravity: velocity_change\n  velocity_change_s: 0.5\n")
    monkeypatch.setattr(bench_mod, "_run_slam", lambda *a, **kw: pytest.fail("no run may start"))
    with pytest.raises(DataError, match=r"bad\.yaml.*init\.velocity_change_s must be at least 0\.8"):
        bench_mod.run_bench([seq], [types.SimpleNamespace(name="learned")], tmp_path / "b", modes=("sync",),
                            config=str(bad), loop=False, progress=False)
    assert not (tmp_path / "b").exists()


def test_bench_settings_are_read_once(tmp_path, monkeypatch):
    """Every run of a benchmark gets the settings as they were when it started: the file rewritten
    during the first run (here with a key the loader refuses) changes nothing, and each run gets its
    own copy (repeat 1's keypoint noise does not reach repeat 0's object)."""
    seq = _tiny_sequence(tmp_path / "tiny_a.h5")
    settings = tmp_path / "s.yaml"
    settings.write_text("backend:\n  pixel_sigma: 1.25\n")
    seen = []

    def runner(sequence, detector, config, **kw):
        seen.append(config)
        settings.write_text("backend:\n  no_such_key: 1\n")
        return _fake_runner()(sequence, detector, config, **kw)

    monkeypatch.setattr(bench_mod, "_run_slam", runner)
    rows = bench_mod.run_bench([seq], [types.SimpleNamespace(name="learned")], tmp_path / "b", modes=("sync",),
                               config=str(settings), loop=False, progress=False, repeats=2)
    assert [r["status"] for r in rows] == ["ok", "ok"]
    assert [c.backend.pixel_sigma for c in seen] == [1.25, 1.25]
    assert seen[0] is not seen[1] and seen[0].detector.keypoint_noise_px == 0.0 < seen[1].detector.keypoint_noise_px


def test_bench_median_counts_failures_as_worst():
    """The paper's Table I: the median of 5 runs, failed when at least 3 crash or diverge."""
    def runs(*pcts):
        return [{"status": "ok", "ate_pct": p} if p is not None else {"status": "diverged", "ate_pct": 80.0} for p in pcts]

    assert bench_mod._median_ate_pct(runs(3.0, 1.0, 2.0, 5.0, 4.0)) == 3.0
    assert bench_mod._median_ate_pct(runs(3.0, None, 2.0, None, 4.0)) == 4.0  # two failed: the median is the worst ok run
    assert bench_mod._median_ate_pct(runs(3.0, None, 2.0, None, None)) is None  # three failed: failed
    assert bench_mod._median_ate_pct(runs(1.0, 2.0, 3.0, 6.0)) == 2.5
    assert bench_mod._median_ate_pct(runs(1.0, 2.0, 3.0, None)) == 2.5
    assert bench_mod._median_ate_pct(runs(1.0, 2.0, None, None)) is None
    assert bench_mod._median_ate_pct([]) is None


def test_perturb_keypoints_is_seeded_bounded_and_inside():
    from aerovis_slam.keypoints import Keypoints
    from aerovis_slam.slam.odometry import perturb_keypoints

    rng = np.random.default_rng(0)
    xy = np.array([[0.0, 0.0], [10.5, 7.25], [99.0, 49.0]] * 100, np.float32)
    kp = Keypoints(xy, np.ones(len(xy), np.float32), rng.normal(size=(len(xy), 8)).astype(np.float32))
    a = perturb_keypoints(kp, np.random.default_rng(5), 0.2, 100, 50)
    b = perturb_keypoints(kp, np.random.default_rng(5), 0.2, 100, 50)
    np.testing.assert_array_equal(a.xy, b.xy)  # same seed, same draw
    d = a.xy - xy
    assert np.abs(d).max() <= 0.2 + 1e-6 and np.abs(d[1::3]).mean() > 0.05  # uniform on +-0.2: mean |d| 0.1
    assert a.xy.min() >= 0 and a.xy[:, 0].max() <= 99 and a.xy[:, 1].max() <= 49  # corners stay inside
    assert a.descriptors is kp.descriptors and a.scores is kp.scores


def test_cli_run_end_to_end_on_tiny_matches_eval(tmp_path, capsys):
    """The real pipeline with the shipped bundle on the 1 s tiny sequence; ``eval`` of the written
    trajectory against the sequence's GT reproduces the run's own ATE (same association by
    interpolation; the file's 0.1 µm rounding moves it by far less than 1e-6 m)."""
    from aerovis_slam.sim.cache import ensure_preset

    seq = ensure_preset("tiny", progress=False) / "tiny_handheld.h5"
    out = tmp_path / "run"
    assert main(["run", str(seq), "--config", "accurate", "--out", str(out), "--quiet"]) == 0
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    m = json.loads((out / "metrics.json").read_text())
    assert line["status"] == m["status"] == "ok" and m["complete"] is True and m["mode"] == "sync"
    assert m["poses"] == len(read_tum(out / "traj.txt")) > 10
    # the first output is the warm-up's first frame (the observation lag may place it up to 50 ms
    # earlier; 1 µs for the file's rounding)
    t_first = m["pipeline_info"]["t_first_frame_us"]
    assert line["t_first_frame_us"] == t_first and -1 <= t_first - read_tum(out / "traj.txt").t[0] <= 50_000
    assert m["ate_rmse_m"] is not None and m["stages"]["detector"]["count"] > 0 and m["loop"]["keyframes"] >= 0
    assert main(["eval", str(seq), str(out / "traj.txt"), "--interpolate"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["pairs"] == m["ate_pairs"] and r["ate_rmse_m"] == pytest.approx(m["ate_rmse_m"], abs=1e-6)


def test_cli_run_with_the_oracle_records_it(tmp_path, capsys):
    """``run --oracle-noise-px`` (perfect tracks, oracle.py) on a simulated sequence: the run says so
    in its summary line and metrics.json, so it is never mistaken for a run of the detector's own
    keypoints."""
    from aerovis_slam.sim.cache import ensure_preset

    seq = ensure_preset("tiny", progress=False) / "tiny_handheld.h5"
    out = tmp_path / "run"
    assert main(["run", str(seq), "--detector", "orb", "--oracle-noise-px", "0.5", "--out", str(out), "--quiet"]) == 0
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    m = json.loads((out / "metrics.json").read_text())
    assert m["oracle_noise_px"] == 0.5 and line["oracle"] == m["pipeline_info"]["oracle"]
    assert line["oracle"]["noise_px"] == 0.5
    bad = tmp_path / "bad"  # refused before any output exists
    assert main(["run", str(seq), "--detector", "orb", "--oracle-noise-px", "-1", "--out", str(bad), "--quiet"]) == 2
    assert not bad.exists() and "oracle noise must be >= 0 px" in capsys.readouterr().err


def test_cli_keypoint_errors_and_the_oracle_exclude_each_other(tmp_path, capsys):
    """``run --keypoint-errors --oracle-noise-px``: perfect tracks have no keypoint error to measure;
    refused before any output exists."""
    from aerovis_slam.sim.cache import ensure_preset

    seq = ensure_preset("tiny", progress=False) / "tiny_handheld.h5"
    bad = tmp_path / "bad"
    assert main(["run", str(seq), "--detector", "orb", "--keypoint-errors", "--oracle-noise-px", "0", "--out", str(bad),
                 "--quiet"]) == 2
    assert not bad.exists() and "exclude each other" in capsys.readouterr().err


def test_cli_bench_preset_seed_runs_that_seeds_sequences(tmp_path, capsys, monkeypatch, empty_config):
    """``bench --preset-seed N``: the preset generated with seed N (another cache folder: other rooms
    and paths), said in the summary line; a negative seed is refused before anything is written."""
    from aerovis_slam.io.sequence import Sequence
    from aerovis_slam.sim.cache import ensure_preset

    ran: list[Path] = []
    runner = _fake_runner()

    def run(sequence, *args, **kwargs):
        ran.append(Path(sequence))
        return runner(sequence, *args, **kwargs)

    monkeypatch.setattr(bench_mod, "_run_slam", run)
    common = ["bench", "--no-learned", "--detector", "orb", "--modes", "sync", "--config", str(empty_config), "--no-loop",
              "--quiet"]
    out = tmp_path / "b"
    assert main(common + ["--sequences", "tiny", "--preset-seed", "1", "--out", str(out)]) == 0
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    seed0, seed1 = ensure_preset("tiny", progress=False), ensure_preset("tiny", seed=1, progress=False)
    assert line["preset_seed"] == 1 and sorted(ran) == sorted(seed1.glob("*.h5")) and len(ran) == 2
    # the stand-in's trajectory is not these sequences' ground truth: scored (ok or diverged), never failed
    assert all(r["status"] != "failed" for r in json.loads((out / "bench.json").read_text()))
    with Sequence(seed0 / "tiny_handheld.h5") as a, Sequence(seed1 / "tiny_handheld.h5") as b:
        assert a.num_events("cam0") != b.num_events("cam0")  # another scene, not a copy
    bad = tmp_path / "bad"
    assert main(common + ["--preset-seed", "-1", "--out", str(bad)]) == 2
    assert not bad.exists() and "--preset-seed -1" in capsys.readouterr().err


def test_ctrl_c_stops_cleanly_then_aborts(capsys):
    import os
    import signal

    from aerovis_slam.slam.cli import _stop_on_sigint

    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        with _stop_on_sigint("test") as stop:
            os.kill(os.getpid(), signal.SIGINT)  # first Ctrl-C: the run is asked to stop, nothing raised
            assert stop.is_set()
            os.kill(os.getpid(), signal.SIGINT)  # second: abort
    assert signal.getsignal(signal.SIGINT) is before  # the previous handler is back
    assert "stopping" in capsys.readouterr().err


def test_vocabularies_ship_and_round_trip(tmp_path):
    from aerovis_slam.slam.loop import load_vocabularies, save_vocabulary, vocabulary_for, vocabulary_meta

    shipped = load_vocabularies()
    # SuperLitE's 64-D descriptors; ORB / rBRIEF 256 bits; SIFT 128-D
    assert {k: v.shape[1] for k, v in shipped.items()} == {"superlite": 64, "classical-orb": 256,
                                                           "classical-gftt_brief": 256, "classical-sift": 128}
    assert vocabulary_for("superlite-int8-cpu") is not None and vocabulary_for("superlite_v2") is None
    words = np.random.default_rng(0).normal(size=(8, 4)).astype(np.float32)
    save_vocabulary(tmp_path / "v.npz", "m", words, {"note": "x"})
    save_vocabulary(tmp_path / "v.npz", "n", words[:4], {})
    back = load_vocabularies(tmp_path / "v.npz")
    np.testing.assert_allclose(back["m"], words, rtol=1e-3, atol=1e-3)  # float16 on disk: 3 decimal digits
    assert vocabulary_meta(tmp_path / "v.npz")["m"] == {"note": "x", "words": 8, "dim": 4} and back["n"].shape == (4, 4)


def test_loop_errors_judge_a_closure_by_the_ground_truth():
    """A loop that measured the true relative pose has zero error; the odometry's estimate, 10 cm
    and 2 deg of yaw off, is the drift the loop should have removed. Times outside the GT: None."""
    from aerovis_slam.slam.trajectory import loop_errors

    t = np.arange(0, 2_000_001, 10_000, dtype=np.int64)
    pose7 = np.zeros((len(t), 7))
    pose7[:, 0] = t * 1e-6  # 1 m/s along x, no rotation
    pose7[:, 6] = 1.0
    gt = PoseSamples(t, pose7)
    T_true = np.eye(4)
    T_true[0, 3] = 1.5  # match at 0.2 s, query at 1.7 s
    drift = rigid([0, 0, 1], 2.0, [0.0, 0.1, 0.0])
    r = loop_errors(gt, 200_000, 1_700_000, T_true, T_true @ drift)
    assert r["error_m"] == pytest.approx(0.0, abs=1e-9) and r["error_deg"] == pytest.approx(0.0, abs=1e-6)
    assert r["true_drift_m"] == pytest.approx(0.1, abs=1e-4) and r["true_drift_deg"] == pytest.approx(2.0, abs=1e-3)
    assert loop_errors(gt, 200_000, 2_500_000, T_true, T_true) is None


def test_software_versions_name_the_installed_distributions(monkeypatch):
    import importlib.metadata

    import numpy

    from aerovis_slam import environment

    v = environment.software_versions()
    assert v["packages"]["numpy"] == numpy.__version__ and "torch" not in v["packages"]
    assert v["python"].count(".") == 2 and v["aerovis"] == environment.__version__
    assert v["commit"] is None or len(v["commit"]) == 40
    # numpy's BLAS is named, without the thread count (a run sets its own, SlamConfig.blas_threads)
    assert v["blas"] and all(b["library"] and "num_threads" not in b for b in v["blas"])
    assert "torch" in environment.software_versions(training=True)["packages"]  # the test environment has the training stack
    # an absent distribution is left out, not recorded as a guess
    real = importlib.metadata.version
    monkeypatch.setattr(environment.metadata, "version",
                        lambda n: (_ for _ in ()).throw(importlib.metadata.PackageNotFoundError(n)) if n == "gtsam" else real(n))
    assert "gtsam" not in environment.software_versions()["packages"]
    line = environment.describe({"aerovis": "0.1.0", "commit": "0123456789" * 4, "uncommitted_changes": True, "python": "3.11.7",
                                 "packages": {"numpy": "2.4.6"}})
    assert line == "aerovis 0.1.0 (0123456+changes), python 3.11.7, numpy 2.4.6"
    host = {"machine": "x86_64", "cpu_model": "Intel(R) Xeon(R) Processor", "simd": "avx512f", "cpus": 2}
    assert environment.describe({"aerovis": "0.1.0", "python": "3.11.7", "packages": {}, "host": host}) == \
        "aerovis 0.1.0, python 3.11.7; on Intel(R) Xeon(R) Processor (avx512f, 2 cpus)"
    blas = [{"library": "openblas", "version": "0.3.31", "architecture": "SkylakeX", "num_threads": 2}]
    assert environment.describe({"aerovis": "0.1.0", "python": "3.11.7", "packages": {}, "blas": blas}) == \
        "aerovis 0.1.0, python 3.11.7, openblas 0.3.31 (SkylakeX)"


def test_cpuinfo_names_the_model_and_the_widest_simd_level(tmp_path):
    from aerovis_slam import environment

    x86 = tmp_path / "x86"
    x86.write_text("processor\t: 0\nmodel name\t: AMD EPYC 7B13\nflags\t\t: fpu sse4_2 avx avx2 fma\n\n"
                   "processor\t: 1\nmodel name\t: AMD EPYC 7B13\nflags\t\t: fpu sse4_2 avx avx2 fma\n")
    assert environment._cpuinfo(str(x86)) == ("AMD EPYC 7B13", "avx2")
    arm = tmp_path / "arm"
    arm.write_text("processor\t: 0\nFeatures\t: fp asimd evtstrm aes\nCPU implementer\t: 0x41\n")
    assert environment._cpuinfo(str(arm)) == (None, "asimd")
    assert environment._cpuinfo(str(tmp_path / "absent")) == (None, None)
    assert set(environment.software_versions()["host"]) == {"machine", "processor", "cpu_model", "simd", "cpus"}


def _bench_rows(detector: str, runs: dict[str, list], mode: str = "sync") -> list[dict]:
    """bench.json rows: per sequence, one run per value (a float is an ok run's ATE %, a string its status)."""
    rows = []
    for seq, values in runs.items():
        for i, v in enumerate(values):
            ok = not isinstance(v, str)
            rows.append({"sequence": seq, "mode": mode, "detector": detector, "status": "ok" if ok else v,
                         "ate_pct": float(v) if ok else None, "ate_pct_final": float(v) / 2 if ok else None, "repeat": i})
    return rows


def test_compare_benches_medians_intervals_and_failures():
    from aerovis_slam.slam.compare import compare_benches, format_comparison

    # constant runs: every resample has the same medians, so the interval is the difference itself
    a = _bench_rows("superlite-fp32", {"s1": [1.0, 1.0, 1.0, 1.0], "s2": [2.0, 3.0, 4.0]})
    b = _bench_rows("x-fp32", {"s1": [0.7, 0.7, 0.7], "s2": [1.0, 3.5, "diverged"], "s3": [0.1]})
    r = compare_benches(a, b)
    s1, s2 = r["sequences"]  # s3 is not in A: left out
    assert [s["sequence"] for s in r["sequences"]] == ["s1", "s2"]
    assert s1["median_a"] == 1.0 and s1["median_b"] == 0.7 and s1["b_lower"] == 1.0
    assert s1["difference"] == pytest.approx(-0.3, abs=1e-12) and s1["interval"] == pytest.approx([-0.3, -0.3], abs=1e-12)
    # a diverged run counts as infinitely bad: B's median of (1.0, 3.5, inf) is 3.5, not a mean over two runs
    assert s2["runs_b"] == [1.0, 3.5, "diverged"] and s2["median_b"] == 3.5 and s2["difference"] == pytest.approx(0.5)
    # pairs (A run, B run) with B lower: 1.0 beats 2, 3, 4; 3.5 beats 4; inf beats none -> 4 of 9
    assert s2["b_lower"] == pytest.approx(4 / 9)
    # a resample of B draws "diverged" at least twice with probability 7/27 (> 2.5 %): no median there, an
    # infinite difference, so the interval is unbounded above
    lo, hi = s2["interval"]
    assert lo <= 0.5 and hi is None
    assert r["overall"]["mean_of_medians_a"] == pytest.approx(2.0) and r["overall"]["mean_of_medians_b"] == pytest.approx(2.1)
    assert r["overall"]["difference"] == pytest.approx(0.1)
    # the final trajectories' ATE instead of the live one (halved in these rows)
    assert compare_benches(a, b, key="ate_pct_final")["sequences"][0]["difference"] == pytest.approx(-0.15)
    table = format_comparison(r, "old", "new")
    assert "| s2 | 2.00, 3.00, 4.00 | 1.00, 3.50, diverged | 3.00 | 3.50 | +0.50 | -3.00 to unbounded | 44 % |" in table
    assert "| mean over 2 sequences | | | 2.00 | 2.10 | +0.10 |" in table
    # half the runs failed: no median, no difference, and an interval unbounded above
    r = compare_benches(a, _bench_rows("x", {"s1": [0.5, "failed"]}))
    assert r["sequences"][0]["median_b"] is None and r["sequences"][0]["difference"] is None
    assert r["sequences"][0]["interval"][1] is None


def test_compare_benches_bad_input(tmp_path):
    from aerovis_slam.slam.compare import compare_benches, load_bench

    with pytest.raises(DataError, match="bench.json: no such file"):
        load_bench(tmp_path)
    (tmp_path / "bench.json").write_text('[{"sequence": "s1", "mode": "sync"}]')
    with pytest.raises(DataError, match=r"bench.json: expected a list of runs, each with sequence, mode, detector, status"):
        load_bench(tmp_path)
    two = _bench_rows("superlite-fp32", {"s1": [1.0]}) + _bench_rows("orb", {"s1": [2.0]})
    with pytest.raises(DataError, match=r"A: 2 detectors in mode 'sync' \(superlite-fp32, orb\): name one"):
        compare_benches(two, two)
    assert compare_benches(two, two, detector_a="orb", detector_b="superlite-fp32")["sequences"][0]["difference"] == -1.0
    with pytest.raises(DataError, match=r"B: no runs of detector 'sift' in mode 'sync'"):
        compare_benches(two, two, detector_a="orb", detector_b="sift")
    with pytest.raises(DataError, match="no sequence in common with A in mode 'async'"):
        compare_benches(_bench_rows("x", {"s1": [1.0]}, "async"), _bench_rows("x", {"s2": [1.0]}, "async"), mode="async")


def test_cli_compare_prints_table_and_json(tmp_path, capsys):
    for name, runs in (("a", {"s1": [1.0, 1.2]}), ("b", {"s1": [0.8, 0.9]})):
        (tmp_path / name).mkdir()
        (tmp_path / name / "bench.json").write_text(json.dumps(_bench_rows("superlite-fp32", runs)))
    out_md = tmp_path / "cmp.md"
    assert main(["compare", str(tmp_path / "a"), str(tmp_path / "b"), "--labels", "old", "new", "--out", str(out_md)]) == 0
    text = capsys.readouterr().out
    res = json.loads(text.strip().splitlines()[-1])
    assert res["sequences"][0]["difference"] == pytest.approx(0.85 - 1.1) and res["sequences"][0]["b_lower"] == 1.0
    assert out_md.read_text() in text and "| s1 | 1.00, 1.20 | 0.80, 0.90 | 1.10 | 0.85 | -0.25 |" in text
    assert main(["compare", str(tmp_path / "a"), str(tmp_path / "missing")]) == 2
    assert "missing: no such file" in capsys.readouterr().err


def test_runtime_guide_documents_every_shipped_setting():
    """docs/runtime.md's settings reference names every key of the shipped settings files and of the
    loop closer's defaults, so a new setting cannot ship undocumented."""
    guide = (REPO_ROOT / "docs" / "runtime.md").read_text()
    missing = []
    for name in ("accurate", "realtime"):
        data = yaml.safe_load((REPO_ROOT / "conf" / "slam" / f"{name}.yaml").read_text())
        for key, value in data.items():
            # a table row names a section's first key in full and the next ones alone: `input.max_width`, `max_height`
            names = [(f"{key}.{sub}", sub) for sub in value] if isinstance(value, dict) else [(key, key)]
            missing += [f"{name}: {full}" for full, short in names if f"`{full}`" not in guide and f"`{short}`" not in guide]
    missing += [f"loop: {k}" for k in DEFAULT_CONFIG if f"`{k}`" not in guide]
    assert not missing, missing
