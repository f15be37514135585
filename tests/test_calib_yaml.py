"""Calibration readers: exact round trips on self-written files, plausibility on the real ones."""

from __future__ import annotations


import numpy as np
import pytest
import yaml

from aerovis_slam.calib import CameraCalibration, RigCalibration
from aerovis_slam.errors import DataError
from aerovis_slam.io.calib_yaml import invert_transform, load_calibration, load_ecd_calib_txt


def _rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _T(R, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _assert_rigid(T):
    assert T.shape == (4, 4)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=2e-3)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=2e-3)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])


# -- self-written files ----------------------------------------------------------------------
def test_kalibr_camchain_imucam_round_trip(tmp_path):
    T_cam0_imu = _T(_rot([0.1, 0.2, 1.0], 0.3), [0.01, -0.02, 0.05])
    T_cam1_imu = _T(_rot([0.0, 1.0, 0.1], -0.2), [-0.07, 0.001, 0.04])
    chain = {
        "cam0": {"T_cam_imu": T_cam0_imu.tolist(), "camera_model": "pinhole", "distortion_model": "radtan",
                 "distortion_coeffs": [-0.3, 0.1, 0.001, -0.002], "intrinsics": [250.5, 251.25, 170.0, 130.5],
                 "resolution": [346, 260], "timeshift_cam_imu": 0.0125},
        "cam1": {"T_cam_imu": T_cam1_imu.tolist(), "timeshift_cam_imu": -0.000375, "camera_model": "pinhole", "distortion_model": "equidistant",
                 "distortion_coeffs": [0.01, -0.02, 0.003, -0.004], "intrinsics": [300.0, 301.0, 320.0, 240.0],
                 "resolution": [640, 480], "T_cn_cnm1": np.eye(4).tolist()},
    }
    imu = {"imu0": {"accelerometer_noise_density": 0.011, "accelerometer_random_walk": 0.0022,
                    "gyroscope_noise_density": 0.0033, "gyroscope_random_walk": 4.4e-5, "update_rate": 400.0}}
    (tmp_path / "rig-camchain-imucam.yaml").write_text(yaml.safe_dump(chain))
    (tmp_path / "rig-imu.yaml").write_text(yaml.safe_dump(imu))
    rig = load_calibration(tmp_path / "rig-camchain-imucam.yaml")
    c0, c1 = rig.cameras["cam0"], rig.cameras["cam1"]
    assert (c0.width, c0.height, c0.fx, c0.fy, c0.cx, c0.cy) == (346, 260, 250.5, 251.25, 170.0, 130.5)
    assert c0.distortion_model == "radtan" and c0.distortion_coeffs == [-0.3, 0.1, 0.001, -0.002]
    assert c1.distortion_model == "equidistant" and (c1.width, c1.height) == (640, 480)
    # Kalibr's T_cam_imu is IMU->camera; stored T_imu_cam must be its inverse.
    np.testing.assert_allclose(c0.T_imu_cam @ T_cam0_imu, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(c1.T_imu_cam, np.linalg.inv(T_cam1_imu), atol=1e-12)
    assert rig.imu.accelerometer_noise_density == 0.011 and rig.imu.update_rate == 400.0
    assert rig.imu.gyroscope_random_walk == 4.4e-5
    # Kalibr's timeshift_cam_imu (s, t_imu = t_cam + shift) in µs, kept through the canonical JSON
    assert c0.timeshift_cam_imu_us == pytest.approx(12500.0, abs=1e-9)
    assert c1.timeshift_cam_imu_us == pytest.approx(-375.0, abs=1e-9)
    back = RigCalibration.from_json(rig.to_json())
    assert [back.cameras[c].timeshift_cam_imu_us for c in ("cam0", "cam1")] == [c0.timeshift_cam_imu_us, c1.timeshift_cam_imu_us]
    # The same via a list of files, and via the folder.
    rig2 = load_calibration([tmp_path / "rig-camchain-imucam.yaml", tmp_path / "rig-imu.yaml"])
    np.testing.assert_array_equal(rig2.cameras["cam1"].T_imu_cam, c1.T_imu_cam)
    assert load_calibration(tmp_path).imu.update_rate == 400.0


def test_kalibr_camchain_without_imu_chains_cameras(tmp_path):
    T_c1_c0 = _T(_rot([0, 1, 0], 0.05), [-0.1, 0.002, 0.0])
    T_c2_c1 = _T(_rot([1, 0, 0], -0.02), [-0.05, 0.0, 0.01])
    cam = {"camera_model": "pinhole", "distortion_model": "radtan", "distortion_coeffs": [0, 0, 0, 0],
           "intrinsics": [200.0, 200.0, 120.0, 90.0], "resolution": [240, 180]}
    chain = {"cam0": dict(cam), "cam1": dict(cam, T_cn_cnm1=T_c1_c0.tolist()), "cam2": dict(cam, T_cn_cnm1=T_c2_c1.tolist())}
    p = tmp_path / "stereo-camchain.yaml"
    p.write_text(yaml.safe_dump(chain))
    rig = load_calibration(p)
    np.testing.assert_array_equal(rig.cameras["cam0"].T_imu_cam, np.eye(4))
    np.testing.assert_allclose(rig.cameras["cam1"].T_imu_cam, np.linalg.inv(T_c1_c0), atol=1e-12)
    np.testing.assert_allclose(rig.cameras["cam2"].T_imu_cam, np.linalg.inv(T_c2_c1 @ T_c1_c0), atol=1e-12)
    assert rig.imu is None


def _camera_info(K, D, R, P, model="plumb_bob", size=(640, 480)):
    return {"image_width": size[0], "image_height": size[1], "camera_name": "x",
            "camera_matrix": {"rows": 3, "cols": 3, "data": np.ravel(K).tolist()},
            "distortion_model": model, "distortion_coefficients": {"rows": 1, "cols": len(D), "data": list(D)},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": np.ravel(R).tolist()},
            "projection_matrix": {"rows": 3, "cols": 4, "data": np.ravel(P).tolist()}}


def test_ros_stereo_pair_recovers_the_transform(tmp_path):
    # Build a rectified pair from a known right-from-left transform the way stereoRectify does:
    # rectified frames share the rotation R_l (left) and R_r = R_l R^T, baseline along rectified x.
    R = _rot([0.1, 1.0, 0.2], 0.04)
    t = np.array([-0.12, 0.003, 0.002])
    R_l = _rot(np.cross([1, 0, 0], -R.T @ t), 0.0)  # any rotation works; choose one that aligns the baseline:
    e1 = -R.T @ t / np.linalg.norm(t)  # right camera centre in the left frame, normalised
    e2 = np.cross([0, 0, 1], e1)
    e2 /= np.linalg.norm(e2)
    R_l = np.stack([e1, e2, np.cross(e1, e2)])
    R_r = R_l @ R.T
    f, B = 500.0, np.linalg.norm(t)
    K = np.array([[510.0, 0, 320.0], [0, 511.0, 240.0], [0, 0, 1]])
    P_l = np.array([[f, 0, 330.0, 0], [0, f, 235.0, 0], [0, 0, 1, 0]])
    P_r = P_l.copy()
    P_r[0, 3] = -f * B
    (tmp_path / "left.yaml").write_text(yaml.safe_dump(_camera_info(K, [-0.1, 0.05, 0.001, 0.002, 0.0], R_l, P_l)))
    (tmp_path / "right.yaml").write_text(yaml.safe_dump(_camera_info(K, [-0.11, 0.04, 0.0, 0.001, 0.0], R_r, P_r)))
    rig = load_calibration([tmp_path / "left.yaml", tmp_path / "right.yaml"])
    left, right = rig.cameras["cam0"], rig.cameras["cam1"]
    assert (left.fx, left.fy, left.cx, left.cy) == (510.0, 511.0, 320.0, 240.0)
    assert left.distortion_coeffs == [-0.1, 0.05, 0.001, 0.002]  # zero k3 dropped
    np.testing.assert_array_equal(left.T_imu_cam, np.eye(4))
    np.testing.assert_allclose(left.R_rect, R_l) and np.testing.assert_allclose(right.P_rect, P_r)
    T_rl = invert_transform(right.T_imu_cam)
    np.testing.assert_allclose(T_rl[:3, :3], R, atol=1e-12)
    np.testing.assert_allclose(T_rl[:3, 3], t, atol=1e-12)
    # The folder form gives the same rig.
    np.testing.assert_allclose(load_calibration(tmp_path).cameras["cam1"].T_imu_cam, right.T_imu_cam)


def test_ecd_calib_txt_and_rpg_yaml(tmp_path):
    p = tmp_path / "calib.txt"
    p.write_text("199.092366542 198.82882047 132.192071378 110.712660011 -0.368436311798 0.150947243557 -0.000296130534385 -0.000759431726241 0.0\n")
    rig = load_calibration(p)
    c = rig.cameras["cam0"]
    assert (c.width, c.height) == (240, 180)
    assert (c.fx, c.fy, c.cx, c.cy) == (199.092366542, 198.82882047, 132.192071378, 110.712660011)
    assert c.distortion_model == "radtan" and c.distortion_coeffs == [-0.368436311798, 0.150947243557, -0.000296130534385, -0.000759431726241]
    assert load_ecd_calib_txt(p, (346, 260)).cameras["cam0"].width == 346
    T = _T(_rot([1, 2, 3], 0.1), [0.01, 0.02, 0.03])
    doc = {"label": "x", "cameras": [{"camera": {"label": "dvs", "image_height": 260, "image_width": 346, "type": "pinhole",
                                                   "intrinsics": {"cols": 1, "rows": 4, "data": [1.5, 2.5, 3.5, 4.5]},
                                                   "distortion": {"type": "equidistant", "parameters": {"cols": 1, "rows": 4, "data": [0.1, 0.2, 0.3, 0.4]}}},
                                        "T_B_C": {"cols": 4, "rows": 4, "data": T.ravel().tolist()}}]}
    q = tmp_path / "rig.yaml"
    q.write_text(yaml.safe_dump(doc))
    c = load_calibration(q).cameras["cam0"]
    assert (c.width, c.height, c.fx, c.cy, c.distortion_model) == (346, 260, 1.5, 4.5, "equidistant")
    np.testing.assert_array_equal(c.T_imu_cam, T)  # T_B_C is body<-camera already


def test_vins_opencv_yaml(tmp_path):
    R = _rot([0, 0, 1], 0.5)
    text = f"""%YAML:1.0
model_type: PINHOLE
image_width: 346
image_height: 260
distortion_parameters:
   k1: -0.1
   k2: 0.01
   p1: 0.001
   p2: -0.002
projection_parameters:
   fx: 250.0
   fy: 251.0
   cx: 173.0
   cy: 130.0
extrinsicRotation: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: {R.ravel().tolist()}
extrinsicTranslation: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [0.1, 0.2, 0.3]
T_camera_imu: 1
acc_n: 0.04
gyr_n: 0.004
acc_w: 0.0008
gyr_w: 4.0e-5
"""
    p = tmp_path / "vins.yaml"
    p.write_text(text)
    rig = load_calibration(p)
    c = rig.cameras["cam0"]
    assert (c.fx, c.fy, c.cx, c.cy, c.distortion_coeffs) == (250.0, 251.0, 173.0, 130.0, [-0.1, 0.01, 0.001, -0.002])
    # T_camera_imu: 1 means the file holds cam<-imu: stored is its inverse.
    np.testing.assert_allclose(c.T_imu_cam, np.linalg.inv(_T(R, [0.1, 0.2, 0.3])), atol=1e-12)
    assert rig.imu.accelerometer_noise_density == 0.04 and rig.imu.gyroscope_random_walk == 4.0e-5
    p.write_text(text.replace("T_camera_imu: 1", "T_camera_imu: 0"))
    np.testing.assert_allclose(load_calibration(p).cameras["cam0"].T_imu_cam, _T(R, [0.1, 0.2, 0.3]), atol=1e-12)


@pytest.mark.parametrize("drop", ["intrinsics", "resolution", "T_cam_imu", "distortion_model"])
def test_kalibr_missing_field_names_file_and_field(tmp_path, drop):
    cam = {"T_cam_imu": np.eye(4).tolist(), "distortion_model": "radtan", "distortion_coeffs": [0, 0, 0, 0],
           "intrinsics": [1, 1, 1, 1], "resolution": [10, 10]}
    cam1 = dict(cam)
    del cam1[drop]
    p = tmp_path / "bad-camchain-imucam.yaml"
    p.write_text(yaml.safe_dump({"cam0": cam, "cam1": cam1}))
    with pytest.raises(DataError, match=drop) as err:
        load_calibration(p)
    assert str(p) in str(err.value)


def test_bad_inputs_raise_data_error(tmp_path):
    p = tmp_path / "left.yaml"
    info = _camera_info(np.eye(3), [0, 0, 0, 0], np.eye(3), np.zeros((3, 4)))
    del info["image_height"]
    p.write_text(yaml.safe_dump(info))
    with pytest.raises(DataError, match="image_height") as err:
        load_calibration(p)
    assert str(p) in str(err.value)
    q = tmp_path / "calib.txt"
    q.write_text("199.0 198.0\n")
    with pytest.raises(DataError, match="cx"):
        load_calibration(q)
    r = tmp_path / "notrot-camchain-imucam.yaml"
    r.write_text(yaml.safe_dump({"cam0": {"T_cam_imu": (2 * np.eye(4)).tolist(), "distortion_model": "radtan",
                                          "distortion_coeffs": [0, 0, 0, 0], "intrinsics": [1, 1, 1, 1], "resolution": [10, 10]}}))
    with pytest.raises(DataError, match="T_cam_imu.*not a rotation"):
        load_calibration(r)
    shifted = tmp_path / "shift-camchain-imucam.yaml"
    shifted.write_text(yaml.safe_dump({"cam0": {"T_cam_imu": np.eye(4).tolist(), "distortion_model": "radtan",
                                                "distortion_coeffs": [0, 0, 0, 0], "intrinsics": [1, 1, 1, 1],
                                                "resolution": [10, 10], "timeshift_cam_imu": "soon"}}))
    with pytest.raises(DataError, match="cam0.timeshift_cam_imu") as err:
        load_calibration(shifted)
    assert str(shifted) in str(err.value)
    s = tmp_path / "other.yaml"
    s.write_text("foo: 1\n")
    with pytest.raises(DataError, match="unrecognised calibration"):
        load_calibration(s)
    with pytest.raises(DataError, match="no such"):
        load_calibration(tmp_path / "missing.yaml")


# -- real files ------------------------------------------------------------------------------
def test_every_real_calibration_file_loads(shared_data):
    files = sorted((shared_data / "calib").rglob("*.yaml"))
    assert files
    for f in files:
        if f.name.endswith("-imu.yaml"):
            with pytest.raises(DataError, match="IMU yaml"):
                load_calibration(f)
            continue
        rig = load_calibration(f)
        assert rig.cameras, f
        for c in rig.cameras.values():
            assert (c.width, c.height) in {(240, 180), (346, 260), (640, 480)}, f
            assert 100 < c.fx < 1000 and 0 < c.cx < c.width and 0 < c.cy < c.height, f
            _assert_rigid(c.T_imu_cam)
            assert np.linalg.norm(c.T_imu_cam[:3, 3]) < 0.7, f


def test_real_sensor_sizes_and_extrinsics(shared_data):
    calib = shared_data / "calib"
    ecd = load_calibration(calib / "DAVIS-IJRR17_ultimate_slam.yaml").cameras["cam0"]
    assert (ecd.width, ecd.height, ecd.fx) == (240, 180, 199.37143467278824)
    np.testing.assert_allclose(ecd.T_imu_cam[:3, 3], [0.00674696422488, 0.0007279224709, 0.0342573613538])
    kal = load_calibration(calib / "hku_ESVIO" / "2022-08-15-15-56-54-camchain-imucam.yaml")
    assert (kal.cameras["cam0"].width, kal.cameras["cam0"].height) == (346, 260)
    assert kal.imu.gyroscope_noise_density == 0.0031404034561189407  # picked up from the sibling -imu.yaml
    assert np.linalg.norm(kal.cameras["cam0"].T_imu_cam[:3, 3]) == pytest.approx(0.0602, abs=1e-3)
    assert kal.cameras["cam0"].timeshift_cam_imu_us == pytest.approx(1943.8323735646128, abs=1e-6)  # 0.0019438... s
    chain = load_calibration(calib / "hku_ESVIO" / "stereo_calibra2-camchain.yaml")
    assert np.linalg.norm(chain.cameras["cam1"].T_imu_cam[:3, 3]) == pytest.approx(0.05969, abs=1e-4)
    esvio = load_calibration(calib / "hku_ESVIO" / "esvio.yaml")
    baseline = np.linalg.norm(esvio.cameras["cam1"].T_imu_cam[:3, 3] - esvio.cameras["cam0"].T_imu_cam[:3, 3])
    assert baseline == pytest.approx(0.0597, abs=2e-3)  # same rig as the camchain above


@pytest.mark.parametrize("rig,size,baseline,exact", [("rpg", (240, 180), 0.148, True), ("upenn", (346, 260), 0.0999, True),
                                                     ("hkust", (346, 260), 0.0731, False), ("dsec/zurich_city_04_a", (640, 480), 0.599, False)])
def test_real_ros_stereo(shared_data, rig, size, baseline, exact):
    folder = shared_data / "calib" / "esvo_stereo" / rig
    cal = load_calibration(folder)
    for c in cal.cameras.values():
        assert (c.width, c.height) == size
    T_rl = invert_transform(cal.cameras["cam1"].T_imu_cam)
    _assert_rigid(T_rl)
    P_r = cal.cameras["cam1"].P_rect
    assert np.linalg.norm(T_rl[:3, 3]) == pytest.approx(-P_r[0, 3] / P_r[0, 0], rel=1e-4)  # R_rect is printed to ~6 digits
    assert np.linalg.norm(T_rl[:3, 3]) == pytest.approx(baseline, abs=1e-3)
    ref = np.array(yaml.safe_load((folder / "left.yaml").read_text())["T_right_left"]["data"]).reshape(3, 4)
    assert T_rl[0, 3] == pytest.approx(ref[0, 3], abs=1e-3)  # the baseline component matches the file's own T_right_left
    if exact:  # these files' R_rect/P_rect were produced from their T_right_left
        np.testing.assert_allclose(T_rl[:3], ref, atol=1e-5)


def test_canonical_json_timeshift_is_optional_and_checked():
    """Files written before the field existed (and single-clock rigs) carry no timeshift: 0; a bad one names the camera."""
    cam = CameraCalibration(64, 48, 50.0, 50.0, 32.0, 24.0)
    d = cam.to_json_dict()
    assert "timeshift_cam_imu_us" not in d
    assert CameraCalibration.from_json_dict(d).timeshift_cam_imu_us == 0.0
    d["timeshift_cam_imu_us"] = "late"
    with pytest.raises(DataError, match="cam1: timeshift_cam_imu_us must be a finite number"):
        CameraCalibration.from_json_dict(d, name="cam1")
