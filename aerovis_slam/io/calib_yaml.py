"""Read camera/IMU calibration files of the common event-camera toolchains into a :class:`RigCalibration`.

Supported (detected by :func:`load_calibration` from the file's content, not its name):

* **Kalibr** ``camchain-imucam.yaml`` (``cam0``/``cam1`` with ``intrinsics [fu fv pu pv]``,
  ``distortion_model``, ``distortion_coeffs``, ``resolution [w h]`` and ``T_cam_imu``) and plain
  ``camchain.yaml`` (no IMU: ``cam0`` is the rig frame, ``camN`` chained through ``T_cn_cnm1``),
  plus the Kalibr IMU yaml (``imu0:`` noise densities) into :class:`ImuNoise`. A camchain-imucam
  named ``PREFIX-camchain-imucam.yaml`` picks up ``PREFIX-imu.yaml`` beside it automatically.
  Each camera's ``timeshift_cam_imu`` (s; ``t_imu = t_cam + shift``) becomes its
  ``timeshift_cam_imu_us``.
* **ROS camera_info** yaml (``image_width``, ``camera_matrix``, ``distortion_model``,
  ``distortion_coefficients``, ``rectification_matrix``, ``projection_matrix``): one file is a
  mono rig; two files (or a folder with ``left.yaml`` + ``right.yaml``) are a stereo rig whose
  right-from-left transform is derived from the rectification rotations and projection matrices.
* **ECD / rpg** ``calib.txt`` (one line ``fx fy cx cy k1 k2 p1 p2 k3``; no image size in the file,
  so it defaults to the DAVIS240C's 240x180).
* **rpg ultimate_slam / svo** camera yaml (``cameras:`` list of ``camera`` + ``T_B_C``).
* **VINS-Mono/Fusion** (OpenCV FileStorage, ``%YAML:1.0``) camera configs (``model_type``,
  ``projection_parameters``, ``distortion_parameters``) and the master configs that name them
  (``cam0_calib``/``event0_calib``) with ``extrinsicRotation``/``extrinsicTranslation`` or
  ``body_T_cam1`` and the ``acc_n``/``gyr_n``/``acc_w``/``gyr_w`` noise model.

Frames: every camera's ``T_imu_cam`` maps camera points into the IMU/body frame. When a format has
no IMU, ``cam0`` is the rig frame (``T_imu_cam = I``) and the other cameras are placed relative to it.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import yaml

from ..calib import CameraCalibration, ImuNoise, RigCalibration
from ..errors import DataError

#: ECD / rpg DAVIS240C sensor size, used for ``calib.txt`` (which does not store the image size).
ECD_IMAGE_SIZE = (240, 180)

_KALIBR_DISTORTION = {"radtan": "radtan", "equidistant": "equidistant", "none": "none"}
_ROS_DISTORTION = {"plumb_bob": "radtan", "equidistant": "equidistant", "fisheye": "equidistant", "none": "none", "": "none"}
_RPG_DISTORTION = {"radial-tangential": "radtan", "equidistant": "equidistant", "none": "none"}


# ------------------------------------------------------------------------------------------
# small helpers
# ------------------------------------------------------------------------------------------
class _OpenCvLoader(yaml.SafeLoader):
    """SafeLoader that also understands OpenCV FileStorage's ``!!opencv-matrix`` tag."""


def _construct_opencv_matrix(loader: yaml.SafeLoader, node: yaml.Node):
    d = loader.construct_mapping(node, deep=True)
    return {"rows": d.get("rows"), "cols": d.get("cols"), "data": d.get("data")}


_OpenCvLoader.add_constructor("tag:yaml.org,2002:opencv-matrix", _construct_opencv_matrix)


def _read_yaml(path: Path) -> dict:
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise DataError(path, f"cannot read calibration file ({exc.strerror})") from None
    # OpenCV FileStorage writes "%YAML:1.0", which is not a valid YAML directive.
    text = re.sub(r"\A\s*%YAML:\d\.\d[^\n]*\n", "", text)
    try:
        d = yaml.load(text, Loader=_OpenCvLoader)
    except yaml.YAMLError as exc:
        raise DataError(path, f"not valid YAML ({exc})") from None
    if not isinstance(d, dict):
        raise DataError(path, "expected a YAML mapping at the top level")
    return d


def _field(d: dict, key: str, path: Path, where: str = ""):
    if not isinstance(d, dict) or key not in d or d[key] is None:
        raise DataError(path, f"missing calibration field {where}{key!r}")
    return d[key]


def _numbers(value, n: int | None, path: Path, name: str) -> np.ndarray:
    """A flat float array from a list / nested list / ``{rows, cols, data}`` matrix node."""
    if isinstance(value, dict):
        if "data" not in value:
            raise DataError(path, f"calibration field {name!r} is a matrix without 'data'")
        value = value["data"]
    try:
        arr = np.asarray(value, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise DataError(path, f"calibration field {name!r} must be numbers, got {value!r}") from None
    if n is not None and arr.size != n:
        raise DataError(path, f"calibration field {name!r} has {arr.size} values, expected {n}")
    return arr


def _rigid(value, path: Path, name: str) -> np.ndarray:
    """A 4x4 rigid transform from 16 numbers or a 3x4 matrix, checked for a proper rotation."""
    arr = _numbers(value, None, path, name)
    if arr.size == 12:
        arr = np.concatenate([arr, [0.0, 0.0, 0.0, 1.0]])
    if arr.size != 16:
        raise DataError(path, f"calibration field {name!r} has {arr.size} values, expected a 4x4 (16) or 3x4 (12) transform")
    T = arr.reshape(4, 4)
    _check_rotation(T[:3, :3], path, name)
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise DataError(path, f"calibration field {name!r}: last row is {T[3].tolist()}, expected [0, 0, 0, 1]")
    return T


def _check_rotation(R: np.ndarray, path: Path, name: str, tol: float = 1e-3) -> None:
    # Calibration tools print 8-10 digits, so orthonormality holds to ~1e-6; 1e-3 catches
    # transposed/garbled matrices without rejecting rounded ones.
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > tol or np.linalg.det(R) < 0:
        raise DataError(path, f"calibration field {name!r} is not a rotation (|R R^T - I| = {err:.2g}, det = {np.linalg.det(R):.4f})")


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) rigid transform, computed as ``[R^T | -R^T t]`` (no general inverse)."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def _camera(path: Path, name: str, width, height, fx, fy, cx, cy, model: str, coeffs, T_imu_cam=None, **extra) -> CameraCalibration:
    expected = {"radtan": (4, 5), "equidistant": (4,), "none": (0, 4, 5)}[model]
    coeffs = [float(c) for c in coeffs]
    if model == "none" and any(coeffs):
        raise DataError(path, f"{name}: distortion model 'none' with non-zero coefficients {coeffs}")
    if len(coeffs) not in expected:
        raise DataError(path, f"{name}: {model} distortion needs {' or '.join(map(str, expected))} coefficients, got {len(coeffs)}")
    if model == "none":
        coeffs = []
    w, h = int(width), int(height)
    if w <= 0 or h <= 0:
        raise DataError(path, f"{name}: image size {w}x{h} must be positive")
    return CameraCalibration(w, h, fx, fy, cx, cy, model, coeffs, np.eye(4) if T_imu_cam is None else T_imu_cam, **extra)


# ------------------------------------------------------------------------------------------
# Kalibr
# ------------------------------------------------------------------------------------------
def _is_kalibr_camchain(d: dict) -> bool:
    return isinstance(d.get("cam0"), dict) and "intrinsics" in d["cam0"]


def _kalibr_camchain(d: dict, path: Path) -> RigCalibration:
    names = sorted((k for k in d if re.fullmatch(r"cam\d+", k)), key=lambda k: int(k[3:]))
    if names != [f"cam{i}" for i in range(len(names))]:
        raise DataError(path, f"camera keys {names} are not consecutive cam0, cam1, ...")
    has_imu = "T_cam_imu" in d["cam0"]
    cams: dict[str, CameraCalibration] = {}
    for i, name in enumerate(names):
        c = d[name]
        where = f"{name}."
        model = str(_field(c, "camera_model", path, where)) if "camera_model" in c else "pinhole"
        if model != "pinhole":
            raise DataError(path, f"{name}.camera_model is {model!r}; only 'pinhole' is supported")
        fu, fv, pu, pv = _numbers(_field(c, "intrinsics", path, where), 4, path, f"{name}.intrinsics")
        w, h = _numbers(_field(c, "resolution", path, where), 2, path, f"{name}.resolution")
        dist = str(_field(c, "distortion_model", path, where))
        if dist not in _KALIBR_DISTORTION:
            raise DataError(path, f"{name}.distortion_model is {dist!r}, expected one of {sorted(_KALIBR_DISTORTION)}")
        coeffs = _numbers(c.get("distortion_coeffs", []), None, path, f"{name}.distortion_coeffs")
        if has_imu:
            # Kalibr stores IMU->camera; the project stores camera->IMU.
            T_imu_cam = invert_transform(_rigid(_field(c, "T_cam_imu", path, where), path, f"{name}.T_cam_imu"))
        elif i == 0:
            T_imu_cam = np.eye(4)  # no IMU: cam0 is the rig frame
        else:
            # T_cn_cnm1 maps cam(n-1) points into cam n: T_rig_cn = T_rig_cnm1 @ inv(T_cn_cnm1).
            T_cn_cnm1 = _rigid(_field(c, "T_cn_cnm1", path, where), path, f"{name}.T_cn_cnm1")
            T_imu_cam = cams[names[i - 1]].T_imu_cam @ invert_transform(T_cn_cnm1)
        extra = {}
        if has_imu and c.get("timeshift_cam_imu") is not None:
            (shift_s,) = _numbers(c["timeshift_cam_imu"], 1, path, f"{name}.timeshift_cam_imu")
            if not np.isfinite(shift_s):
                raise DataError(path, f"{name}.timeshift_cam_imu must be a finite number of seconds, got {shift_s}")
            extra["timeshift_cam_imu_us"] = shift_s * 1e6
        cams[name] = _camera(path, name, w, h, fu, fv, pu, pv, _KALIBR_DISTORTION[dist], coeffs, T_imu_cam, **extra)
    imu = None
    if has_imu:
        m = re.fullmatch(r"(.*)-camchain-imucam\.ya?ml", path.name)
        if m:
            for suffix in (".yaml", ".yml"):
                sibling = path.with_name(f"{m.group(1)}-imu{suffix}")
                if sibling.is_file():
                    imu = _kalibr_imu(_read_yaml(sibling), sibling)
                    break
    return RigCalibration(cams, imu)


def _is_kalibr_imu(d: dict) -> bool:
    return isinstance(d.get("imu0"), dict)


def _kalibr_imu(d: dict, path: Path) -> ImuNoise:
    imu = _field(d, "imu0", path)
    vals = {}
    for key in ("accelerometer_noise_density", "accelerometer_random_walk", "gyroscope_noise_density", "gyroscope_random_walk", "update_rate"):
        v = _field(imu, key, path, "imu0.")
        try:
            vals[key] = float(v)
        except (TypeError, ValueError):
            raise DataError(path, f"imu0.{key} must be a number, got {v!r}") from None
        if vals[key] <= 0:
            raise DataError(path, f"imu0.{key} must be positive, got {vals[key]}")
    return ImuNoise(**vals)


# ------------------------------------------------------------------------------------------
# ROS camera_info
# ------------------------------------------------------------------------------------------
def _is_ros_camera_info(d: dict) -> bool:
    return "camera_matrix" in d and "image_width" in d


def _ros_camera(d: dict, path: Path, name: str) -> CameraCalibration:
    w = _field(d, "image_width", path)
    h = _field(d, "image_height", path)
    K = _numbers(_field(d, "camera_matrix", path), 9, path, "camera_matrix")
    dist = str(d.get("distortion_model", "none") or "none")
    if dist not in _ROS_DISTORTION:
        raise DataError(path, f"distortion_model is {dist!r}, expected one of {sorted(k for k in _ROS_DISTORTION if k)}")
    coeffs = _numbers(d.get("distortion_coefficients", {"data": []}), None, path, "distortion_coefficients")
    model = _ROS_DISTORTION[dist]
    if model == "radtan" and len(coeffs) == 5 and coeffs[4] == 0.0:
        coeffs = coeffs[:4]  # ROS always writes k3; drop a zero one so the model stays 4-parameter
    if model == "none":
        coeffs = coeffs[np.flatnonzero(coeffs)] if np.any(coeffs) else np.empty(0)
    R = _numbers(d["rectification_matrix"], 9, path, "rectification_matrix").reshape(3, 3) if "rectification_matrix" in d else None
    P = _numbers(d["projection_matrix"], 12, path, "projection_matrix").reshape(3, 4) if "projection_matrix" in d else None
    if R is not None:
        _check_rotation(R, path, "rectification_matrix")
    # K is read by position (fx, cx, fy, cy); some published files have a garbled last row.
    return _camera(path, name, w, h, K[0], K[4], K[2], K[5], model, coeffs, None, R_rect=R, P_rect=P)


def ros_stereo_T_right_left(left: CameraCalibration, right: CameraCalibration, *, path=None) -> np.ndarray:
    """Right-from-left transform (4, 4) of a rectified ROS stereo pair.

    In the rectified frames both cameras share the rotation and the right projection is
    ``P_r = K' [I | t]`` with ``t = (Tx / fx', Ty / fy', 0)`` (ROS: ``Tx = -fx' * baseline``), and
    ``R_rect`` rotates each raw camera frame into its rectified frame, so
    ``p_right = R_r^T (R_l p_left + t)``.

    Raises:
        DataError: a camera lacks ``R_rect``/``P_rect``.
    """
    for side, c in (("left", left), ("right", right)):
        if c.R_rect is None or c.P_rect is None:
            raise DataError(path, f"{side} camera_info lacks rectification_matrix/projection_matrix, needed for the stereo transform")
    P = right.P_rect
    t_rect = np.array([P[0, 3] / P[0, 0], P[1, 3] / P[1, 1], 0.0])
    if left.P_rect[0, 3] != 0.0:
        # Left P normally has Tx = 0; a non-zero one shifts the rectified origin the same way.
        t_rect[0] -= left.P_rect[0, 3] / left.P_rect[0, 0]
    T = np.eye(4)
    T[:3, :3] = right.R_rect.T @ left.R_rect
    T[:3, 3] = right.R_rect.T @ t_rect
    return T


def _ros_stereo(left_path: Path, right_path: Path) -> RigCalibration:
    left = _ros_camera(_read_yaml(left_path), left_path, "cam0")
    right = _ros_camera(_read_yaml(right_path), right_path, "cam1")
    T_rl = ros_stereo_T_right_left(left, right, path=right_path)
    right.T_imu_cam = invert_transform(T_rl)  # no IMU: left camera is the rig frame
    return RigCalibration({"cam0": left, "cam1": right})


# ------------------------------------------------------------------------------------------
# ECD calib.txt and rpg ultimate_slam yaml
# ------------------------------------------------------------------------------------------
def load_ecd_calib_txt(path: str | os.PathLike, image_size: tuple[int, int] = ECD_IMAGE_SIZE) -> RigCalibration:
    """Read an ECD / rpg ``calib.txt`` (``fx fy cx cy k1 k2 p1 p2 k3`` on one line).

    Args:
        path: the file.
        image_size: (width, height); the file does not store it (ECD/rpg: DAVIS240C, 240x180).

    Returns:
        a one-camera rig; ``T_imu_cam`` is identity because the file has no extrinsics.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise DataError(path, f"cannot read calibration file ({exc.strerror})") from None
    tokens = text.split()
    names = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"]
    if len(tokens) < 4:
        missing = names[len(tokens) : 4]
        raise DataError(path, f"missing calibration field(s) {missing} (expected 'fx fy cx cy k1 k2 p1 p2 k3')")
    if len(tokens) not in (4, 8, 9):
        raise DataError(path, f"expected 4, 8 or 9 numbers 'fx fy cx cy [k1 k2 p1 p2 [k3]]', found {len(tokens)}")
    try:
        vals = [float(v) for v in tokens]
    except ValueError:
        raise DataError(path, f"calibration values must be numbers, got {tokens}") from None
    coeffs = vals[4:]
    if len(coeffs) == 5 and coeffs[4] == 0.0:
        coeffs = coeffs[:4]
    model = "radtan" if any(coeffs) else "none"
    cam = _camera(path, "cam0", image_size[0], image_size[1], *vals[:4], model, coeffs if model == "radtan" else [])
    return RigCalibration({"cam0": cam})


def _is_rpg_cameras(d: dict) -> bool:
    return isinstance(d.get("cameras"), list)


def _rpg_cameras(d: dict, path: Path) -> RigCalibration:
    cams = {}
    for i, entry in enumerate(d["cameras"]):
        name = f"cam{i}"
        where = f"cameras[{i}]."
        c = _field(entry, "camera", path, where)
        where += "camera."
        ctype = str(c.get("type", "pinhole"))
        if ctype != "pinhole":
            raise DataError(path, f"{where}type is {ctype!r}; only 'pinhole' is supported")
        fx, fy, cx, cy = _numbers(_field(c, "intrinsics", path, where), 4, path, f"{where}intrinsics")
        dist = _field(c, "distortion", path, where)
        dtype = str(_field(dist, "type", path, f"{where}distortion."))
        if dtype not in _RPG_DISTORTION:
            raise DataError(path, f"{where}distortion.type is {dtype!r}, expected one of {sorted(_RPG_DISTORTION)}")
        coeffs = _numbers(dist.get("parameters", {"data": []}), None, path, f"{where}distortion.parameters")
        # T_B_C maps camera points into the body (IMU) frame: already T_imu_cam.
        T = _rigid(_field(entry, "T_B_C", path, f"cameras[{i}]."), path, f"cameras[{i}].T_B_C")
        cams[name] = _camera(path, name, _field(c, "image_width", path, where), _field(c, "image_height", path, where),
                             fx, fy, cx, cy, _RPG_DISTORTION[dtype], coeffs, T)
    if not cams:
        raise DataError(path, "'cameras' list is empty")
    return RigCalibration(cams)


# ------------------------------------------------------------------------------------------
# VINS-Mono / VINS-Fusion (OpenCV FileStorage)
# ------------------------------------------------------------------------------------------
def _is_vins_camera(d: dict) -> bool:
    return "projection_parameters" in d and "model_type" in d


def _vins_camera(d: dict, path: Path, name: str, T_imu_cam=None) -> CameraCalibration:
    mtype = str(_field(d, "model_type", path)).upper()
    pp = _field(d, "projection_parameters", path)
    w, h = _field(d, "image_width", path), _field(d, "image_height", path)
    if mtype == "PINHOLE":
        intr = [_field(pp, k, path, "projection_parameters.") for k in ("fx", "fy", "cx", "cy")]
        dp = d.get("distortion_parameters") or {}
        coeffs = [float(dp.get(k, 0.0)) for k in ("k1", "k2", "p1", "p2")]
        model = "radtan" if any(coeffs) else "none"
    elif mtype == "KANNALA_BRANDT":
        # camodocal's Kannala-Brandt k2..k5 are OpenCV fisheye's k1..k4; mu, mv, u0, v0 = fx, fy, cx, cy.
        intr = [_field(pp, k, path, "projection_parameters.") for k in ("mu", "mv", "u0", "v0")]
        coeffs = [float(_field(pp, k, path, "projection_parameters.")) for k in ("k2", "k3", "k4", "k5")]
        model = "equidistant"
    else:
        raise DataError(path, f"model_type is {mtype!r}; supported: PINHOLE, KANNALA_BRANDT")
    return _camera(path, name, w, h, *intr, model, coeffs if model != "none" else [], T_imu_cam)


def _is_vins_config(d: dict) -> bool:
    return any(k in d for k in ("cam0_calib", "event0_calib", "acc_n")) or ("extrinsicRotation" in d and _is_vins_camera(d))


def _vins_extrinsic(d: dict, path: Path, suffix: str, flag: str) -> np.ndarray | None:
    rkey, tkey = f"extrinsicRotation{suffix}", f"extrinsicTranslation{suffix}"
    if rkey not in d:
        return None
    R = _numbers(d[rkey], 9, path, rkey).reshape(3, 3)
    _check_rotation(R, path, rkey)
    t = _numbers(_field(d, tkey, path), 3, path, tkey)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    # VINS stores imu^T_cam; a flag of 1 (HKU/ESVIO configs) says the file holds cam^T_imu instead.
    return invert_transform(T) if int(d.get(flag, 0) or 0) == 1 else T


def _vins_config(d: dict, path: Path) -> RigCalibration:
    cams: dict[str, CameraCalibration] = {}
    # Event-camera configs (ESVIO) name both frame and event cameras; an event SLAM wants the latter.
    kind = "event" if "event0_calib" in d else "cam"
    if f"{kind}0_calib" in d:
        for i in range(8):
            key = f"{kind}{i}_calib"
            if key not in d:
                break
            sub = path.parent / str(d[key])
            if not sub.is_file():
                raise DataError(path, f"{key} names {sub}, which does not exist")
            if i == 0:
                T = _vins_extrinsic(d, path, "_event" if kind == "event" else "", "T_event_imu" if kind == "event" else "T_camera_imu")
            else:
                T = None
            bkey = f"body_T_{kind}{i}"
            if bkey in d:
                T = _rigid(d[bkey], path, bkey)
            if T is None:
                raise DataError(path, f"missing calibration field {bkey!r} (extrinsics of {key})")
            cams[f"cam{i}"] = _vins_camera(_read_yaml(sub), sub, f"cam{i}", T)
    elif _is_vins_camera(d):
        T = _vins_extrinsic(d, path, "", "T_camera_imu")
        cams["cam0"] = _vins_camera(d, path, "cam0", T)
    else:
        raise DataError(path, "VINS config names no camera (expected cam0_calib/event0_calib or model_type + projection_parameters)")
    imu = None
    if "acc_n" in d:
        # VINS's acc_n/gyr_n/acc_w/gyr_w play the role of Kalibr's continuous-time densities.
        vals = {}
        for src, dst in (("acc_n", "accelerometer_noise_density"), ("acc_w", "accelerometer_random_walk"),
                         ("gyr_n", "gyroscope_noise_density"), ("gyr_w", "gyroscope_random_walk")):
            vals[dst] = float(_field(d, src, path))
        imu = ImuNoise(**vals)
    return RigCalibration(cams, imu)


# ------------------------------------------------------------------------------------------
# entry point
# ------------------------------------------------------------------------------------------
def _load_one(path: Path) -> RigCalibration | ImuNoise:
    if path.suffix.lower() == ".txt":
        return load_ecd_calib_txt(path)
    d = _read_yaml(path)
    if _is_kalibr_camchain(d):
        return _kalibr_camchain(d, path)
    if _is_kalibr_imu(d):
        return _kalibr_imu(d, path)
    if _is_ros_camera_info(d):
        return RigCalibration({"cam0": _ros_camera(d, path, "cam0")})
    if _is_rpg_cameras(d):
        return _rpg_cameras(d, path)
    if _is_vins_config(d):
        return _vins_config(d, path)
    if _is_vins_camera(d):
        return RigCalibration({"cam0": _vins_camera(d, path, "cam0")})
    raise DataError(path, "unrecognised calibration file: expected Kalibr camchain/imu yaml, ROS camera_info yaml, "
                          "rpg 'cameras:' yaml, VINS config or ECD calib.txt")


def load_calibration(path_or_paths: str | os.PathLike | Sequence[str | os.PathLike]) -> RigCalibration:
    """Load a rig calibration from one file, a folder, or several files, detecting the format.

    Args:
        path_or_paths: a calibration file (see the module docstring for the formats); a folder with
            ``left.yaml`` + ``right.yaml`` (ROS stereo), a ``*camchain-imucam.yaml`` or ``calib.txt``;
            or a list: two ROS camera_info files (left, right) make a stereo rig, and a Kalibr
            camchain plus a Kalibr IMU yaml are merged.

    Returns:
        the rig; cameras keyed ``cam0``, ``cam1``, ... with ``T_imu_cam`` camera->IMU (4x4).

    Raises:
        DataError: unreadable or unrecognised file, missing or inconsistent field (names file and field).
    """
    if isinstance(path_or_paths, (str, os.PathLike)):
        path = Path(path_or_paths)
        if path.is_dir():
            return _load_folder(path)
        if not path.is_file():
            raise DataError(path, "no such calibration file")
        out = _load_one(path)
        if isinstance(out, ImuNoise):
            raise DataError(path, "this is a Kalibr IMU yaml (noise only); give it together with a camchain file")
        return out
    paths = [Path(p) for p in path_or_paths]
    if not paths:
        raise DataError(None, "no calibration files given")
    for p in paths:
        if not p.is_file():
            raise DataError(p, "no such calibration file")
    if len(paths) == 1:
        return load_calibration(paths[0])
    if len(paths) == 2 and all(p.suffix.lower() != ".txt" and _is_ros_camera_info(_read_yaml(p)) for p in paths):
        return _ros_stereo(paths[0], paths[1])
    cams: dict[str, CameraCalibration] = {}
    imu: ImuNoise | None = None
    for p in paths:
        out = _load_one(p)
        if isinstance(out, ImuNoise):
            imu = out
            continue
        for name, cam in out.cameras.items():
            if name in cams:
                raise DataError(p, f"camera {name} is defined again (already read from an earlier file)")
            cams[name] = cam
        imu = out.imu if out.imu is not None else imu
    if not cams:
        raise DataError(paths[0], "no camera calibration among the given files")
    return RigCalibration(cams, imu)


def _load_folder(folder: Path) -> RigCalibration:
    left, right = folder / "left.yaml", folder / "right.yaml"
    if left.is_file() and right.is_file():
        return _ros_stereo(left, right)
    chains = sorted(folder.glob("*camchain-imucam.yaml")) or sorted(folder.glob("*camchain.yaml"))
    if len(chains) == 1:
        return load_calibration(chains[0])
    if (folder / "calib.txt").is_file():
        return load_ecd_calib_txt(folder / "calib.txt")
    raise DataError(folder, "no calibration found in folder (expected left.yaml + right.yaml, one *camchain*.yaml, or calib.txt)")
