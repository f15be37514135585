"""Geometry (rotations, poses, pinhole warps, epipolar distance) and keypoint post-processing."""

from __future__ import annotations

import numpy as np
import pytest

from aerovis_slam import geometry as g
from aerovis_slam.keypoints import (
    cosine_similarity,
    extract_keypoints,
    mutual_nearest_neighbours,
    nms_mask,
    quantize_descriptors,
    refine_subpixel,
    sample_descriptors,
)

rng = np.random.default_rng(0)


def random_T(n=1, trans=1.0):
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = g.so3_exp(rng.normal(size=(n, 3)))
    T[:, :3, 3] = rng.normal(scale=trans, size=(n, 3))
    return T


def test_rotation_round_trips():
    R = g.so3_exp(rng.normal(size=(200, 3)) * 1.5)
    np.testing.assert_allclose(g.quat_to_rot(g.rot_to_quat(R)), R, atol=1e-12)
    w = rng.normal(size=(200, 3))
    w *= (rng.uniform(0, 3.1, 200) / np.linalg.norm(w, axis=1))[:, None]  # angles below pi
    np.testing.assert_allclose(g.so3_log(g.so3_exp(w)), w, atol=1e-9)
    np.testing.assert_allclose(g.rotation_angle_deg(g.so3_exp(np.array([0, 0, np.pi / 2]))), 90.0)
    T = random_T(5)
    np.testing.assert_allclose(g.pose7_to_matrix(g.matrix_to_pose7(T)), T, atol=1e-12)
    np.testing.assert_allclose(g.invert_T(T) @ T, np.tile(np.eye(4), (5, 1, 1)), atol=1e-12)


def test_pose_difference_is_the_motion_in_the_first_frame():
    """inv(A) @ B: A turned 90 deg about z; B is 2 m along A's own x and turned 30 deg further, so
    the difference is 2 m and 30 deg, whatever A's position (the world offset cancels)."""
    A = np.eye(4)
    A[:3, :3] = g.so3_exp(np.array([0, 0, np.pi / 2]))
    A[:3, 3] = [5.0, -1.0, 2.0]
    step = np.eye(4)
    step[:3, :3] = g.so3_exp(np.array([0, 0, np.radians(30)]))
    step[:3, 3] = [2.0, 0, 0]
    metres, degrees = g.pose_difference(A, A @ step)
    assert metres == pytest.approx(2.0, abs=1e-12) and degrees == pytest.approx(30.0, abs=1e-9)
    assert g.pose_difference(A, A) == (0.0, 0.0)


def test_interpolate_poses():
    t = np.array([0, 1_000_000])
    q1 = g.rot_to_quat(g.so3_exp(np.array([0, 0, np.radians(90)])))
    poses = np.array([[0, 0, 0, 0, 0, 0, 1.0], [2, 0, 0, *q1]])
    mid = g.interpolate_poses([500_000, 0, 1_000_000], t, poses)
    np.testing.assert_allclose(mid[0, :3], [1, 0, 0])
    np.testing.assert_allclose(g.rotation_angle_deg(g.quat_to_rot(mid[0, 3:])), 45.0, atol=1e-9)
    np.testing.assert_allclose(mid[1:], poses, atol=1e-12)
    with pytest.raises(ValueError, match="outside"):
        g.interpolate_poses([2_000_000], t, poses)


def test_warp_plane_and_epipolar():
    K = np.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]])
    xy0 = np.array([[50.0, 40.0], [10.0, 70.0]])
    depth0 = np.array([2.0, 4.0])
    T_1_0 = np.eye(4)
    T_1_0[0, 3] = -0.1  # camera 1 is 10 cm to the right: points move left by f * b / z
    xy1, vis = g.warp_pixels(xy0, depth0, K, K, T_1_0, image_size1=(100, 80))
    np.testing.assert_allclose(xy1, [[50 - 5.0, 40.0], [10 - 2.5, 70.0]])
    assert vis.all()
    # occlusion: a depth map of view 1 that is nearer than the point hides it
    depth1 = np.full((80, 100), 1.0)
    _, vis = g.warp_pixels(xy0, depth0, K, K, T_1_0, depth1)
    assert not vis.any()
    # correct correspondences lie on their epipolar lines
    T = random_T(1, 0.3)[0]
    pts0 = np.c_[rng.uniform(-1, 1, (20, 2)), rng.uniform(2, 5, 20)]
    xy0, _ = g.project(pts0, K)
    xy1, _ = g.project(g.transform_points(T, pts0), K)
    d = g.epipolar_distance(xy0, xy1, K, K, T)
    assert np.abs(np.diag(d)).max() < 1e-8
    assert np.median(d[~np.eye(20, dtype=bool)]) > 1.0


def test_nms_topk_and_descriptor_sampling():
    scores = np.zeros((32, 40), np.float32)
    scores[10, 10], scores[10, 11], scores[20, 30], scores[5, 20] = 0.9, 0.5, 0.7, 0.02
    mask = nms_mask(scores, radius=2, threshold=0.01)
    assert set(zip(*np.nonzero(mask))) == {(10, 10), (20, 30), (5, 20)}
    D = 16
    grid = rng.normal(size=(D, 4, 5)).astype(np.float32)
    kp = extract_keypoints(scores, grid, top_k=2, border=4, subpixel=False)
    np.testing.assert_array_equal(kp.xy, [[10, 10], [30, 20]])  # highest first
    # sub-pixel: the 3x3 score centroid; the 0.5 neighbour pulls the first peak 0.5 / 1.4 px right
    kp = extract_keypoints(scores, grid, top_k=2, border=4)
    np.testing.assert_allclose(kp.xy, [[10 + 0.5 / 1.4, 10], [30, 20]], atol=1e-6)
    np.testing.assert_allclose(kp.scores, [0.9, 0.7])
    # at a cell centre (8 j + 3.5, 8 i + 3.5) bilinear sampling returns that cell's vector
    d = sample_descriptors(grid, np.array([[8 * 2 + 3.5, 8 * 1 + 3.5]]))
    np.testing.assert_allclose(d[0], grid[:, 1, 2] / np.linalg.norm(grid[:, 1, 2]), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(kp.descriptors, axis=1), 1.0, atol=1e-6)


def test_subpixel_refinement_of_a_sampled_gaussian():
    # a separable Gaussian blob centred between pixels: the y factor cancels in the x centroid, so the
    # refined offset is the 1D centroid of the three samples at -1, 0, 1 around the integer peak
    sigma, cx, cy = 1.0, 20.3, 11.8
    yy, xx = np.mgrid[0:32, 0:40].astype(np.float64)
    scores = np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma**2)).astype(np.float32)

    def centroid(delta):
        w = np.exp(-((np.arange(-1, 2) - delta) ** 2) / (2 * sigma**2))
        return (w * np.arange(-1, 2)).sum() / w.sum()

    xy = refine_subpixel(scores, np.array([[20, 12]]))
    np.testing.assert_allclose(xy[0], [20 + centroid(0.3), 12 + centroid(-0.2)], atol=1e-5)
    # closer to the true centre than the integer peak, moved less than the true offset (3x3 truncation)
    assert np.all(np.abs(xy[0] - [cx, cy]) < np.abs(np.array([20, 12]) - [cx, cy]))
    # a symmetric peak stays put, and an empty input stays empty
    sym = np.zeros((9, 9), np.float32)
    sym[4, 4], sym[4, 3], sym[4, 5] = 1.0, 0.3, 0.3
    np.testing.assert_allclose(refine_subpixel(sym, np.array([[4, 4]])), [[4, 4]], atol=1e-7)
    assert refine_subpixel(sym, np.zeros((0, 2))).shape == (0, 2)


def test_int8_descriptors_and_mutual_matching():
    desc = rng.normal(size=(300, 64)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    scale = 127 / np.abs(desc).max()
    q = quantize_descriptors(desc, scale)
    # rounding error per component <= 0.5 / scale; relative to |q| ~ scale, cosine changes by O((0.5/scale)^2 D)
    np.testing.assert_allclose(cosine_similarity(q, q[:10]), cosine_similarity(desc, desc[:10]), atol=0.02)
    perm = rng.permutation(300)
    noisy = desc[perm] + rng.normal(scale=0.01, size=desc.shape).astype(np.float32)
    matches = mutual_nearest_neighbours(quantize_descriptors(desc, scale), quantize_descriptors(noisy / np.linalg.norm(noisy, axis=1, keepdims=True), scale))
    assert len(matches) == 300
    np.testing.assert_array_equal(perm[matches[:, 1]], matches[:, 0])
