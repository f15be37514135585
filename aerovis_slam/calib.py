"""Camera and IMU calibration of a rig, as stored in the canonical sequence's ``/calib``.

Frames: ``T_imu_cam`` (4x4) maps points from the camera frame to the IMU/body frame,
``p_imu = T_imu_cam @ p_cam``. Cameras are pinhole with an optional distortion model:

* ``"none"``: no distortion.
* ``"radtan"``: OpenCV's plumb-bob ``[k1, k2, p1, p2(, k3)]`` (Kalibr ``radtan``).
* ``"equidistant"``: OpenCV's fisheye ``[k1, k2, k3, k4]`` (Kalibr ``equidistant``).

The JSON form is an object keyed by camera name (``cam0``, ``cam1``), each with ``width``,
``height``, ``fx``, ``fy``, ``cx``, ``cy``, ``distortion_model``, ``distortion_coeffs`` and
``T_imu_cam`` (4x4 nested list), optionally ``R_rect`` (3x3) and ``P_rect`` (3x4) for stereo
rectification; and an optional ``imu`` object with Kalibr-named noise parameters.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field

import cv2
import numpy as np

from .errors import DataError

DISTORTION_MODELS = ("none", "radtan", "equidistant")
_REQUIRED_CAMERA_FIELDS = ("width", "height", "fx", "fy", "cx", "cy", "distortion_model", "distortion_coeffs", "T_imu_cam")


@dataclass
class CameraCalibration:
    """Intrinsics, distortion and IMU extrinsics of one camera.

    Attributes:
        width, height: image size in pixels.
        fx, fy, cx, cy: pinhole intrinsics in pixels.
        distortion_model: one of :data:`DISTORTION_MODELS`.
        distortion_coeffs: coefficients of that model.
        T_imu_cam: (4, 4) camera-to-IMU transform.
        R_rect: optional (3, 3) rectifying rotation (ROS ``R``).
        P_rect: optional (3, 4) rectified projection (ROS ``P``).
        timeshift_cam_imu_us: camera-to-IMU clock offset in µs, Kalibr's ``timeshift_cam_imu``:
            ``t_imu = t_cam + timeshift_cam_imu_us``. The SLAM runtime moves this camera's event
            timestamps onto the IMU clock with it (0: one clock, as hardware-synchronised rigs and
            the simulator).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion_model: str = "none"
    distortion_coeffs: list[float] = field(default_factory=list)
    T_imu_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    R_rect: np.ndarray | None = None
    P_rect: np.ndarray | None = None
    timeshift_cam_imu_us: float = 0.0

    def __post_init__(self) -> None:
        self.width, self.height = int(self.width), int(self.height)
        self.fx, self.fy, self.cx, self.cy = (float(v) for v in (self.fx, self.fy, self.cx, self.cy))
        self.distortion_coeffs = [float(c) for c in self.distortion_coeffs]
        self.T_imu_cam = np.asarray(self.T_imu_cam, dtype=np.float64)
        if self.R_rect is not None:
            self.R_rect = np.asarray(self.R_rect, dtype=np.float64).reshape(3, 3)
        if self.P_rect is not None:
            self.P_rect = np.asarray(self.P_rect, dtype=np.float64).reshape(3, 4)
        self.timeshift_cam_imu_us = float(self.timeshift_cam_imu_us)
        if not math.isfinite(self.timeshift_cam_imu_us):
            raise ValueError(f"timeshift_cam_imu_us must be finite, got {self.timeshift_cam_imu_us}")

    @property
    def imu_clock_offset_us(self) -> int:
        """``timeshift_cam_imu_us`` in whole µs, as timestamps are: add it to this camera's times for IMU-clock times."""
        return int(round(self.timeshift_cam_imu_us))

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def undistort_points(self, points_px: np.ndarray, rectify: bool = False) -> np.ndarray:
        """Map distorted pixel coordinates (N, 2) to ideal pinhole pixels (N, 2).

        With ``rectify`` and a stored ``R_rect``/``P_rect``, the result is in the rectified image.
        """
        pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 1, 2)
        R = self.R_rect if (rectify and self.R_rect is not None) else None
        P = self.P_rect[:, :3] if (rectify and self.P_rect is not None) else self.K
        if self.distortion_model == "equidistant":
            out = cv2.fisheye.undistortPoints(pts, self.K, np.asarray(self.distortion_coeffs), R=R, P=P)
        else:
            D = np.asarray(self.distortion_coeffs) if self.distortion_model == "radtan" else np.zeros(4)
            out = cv2.undistortPoints(pts, self.K, D, R=R, P=P)
        return out.reshape(-1, 2)

    def to_json_dict(self) -> dict:
        d = asdict(self)
        d["T_imu_cam"] = self.T_imu_cam.tolist()
        for key in ("R_rect", "P_rect"):
            if d[key] is None:
                del d[key]
            else:
                d[key] = np.asarray(d[key]).tolist()
        if not self.timeshift_cam_imu_us:  # files of single-clock rigs stay as before
            del d["timeshift_cam_imu_us"]
        return d

    @classmethod
    def from_json_dict(cls, d: dict, *, path=None, name: str = "cam") -> "CameraCalibration":
        missing = [k for k in _REQUIRED_CAMERA_FIELDS if k not in d]
        if missing:
            raise DataError(path, f"calibration of {name} lacks field(s) {missing} (expected all of {list(_REQUIRED_CAMERA_FIELDS)})")
        if d["distortion_model"] not in DISTORTION_MODELS:
            raise DataError(path, f"calibration of {name}: distortion_model {d['distortion_model']!r} is not one of {DISTORTION_MODELS}")
        T = np.asarray(d["T_imu_cam"], dtype=np.float64)
        if T.shape != (4, 4):
            raise DataError(path, f"calibration of {name}: T_imu_cam has shape {T.shape}, expected (4, 4)")
        known = {k: d[k] for k in ("width", "height", "fx", "fy", "cx", "cy", "distortion_model", "distortion_coeffs", "R_rect", "P_rect") if k in d}
        shift = d.get("timeshift_cam_imu_us", 0.0)
        if isinstance(shift, bool) or not isinstance(shift, (int, float)) or not math.isfinite(shift):
            raise DataError(path, f"calibration of {name}: timeshift_cam_imu_us must be a finite number of µs, got {shift!r}")
        return cls(T_imu_cam=T, timeshift_cam_imu_us=shift, **known)


@dataclass
class ImuNoise:
    """Continuous-time IMU noise densities in Kalibr's names and units.

    Defaults are a Bosch BMI160-like consumer IMU (the AERO-VIS drone's).
    """

    accelerometer_noise_density: float = 2.0e-3  # m/s^2/sqrt(Hz)
    accelerometer_random_walk: float = 3.0e-3  # m/s^3/sqrt(Hz)
    gyroscope_noise_density: float = 1.6e-4  # rad/s/sqrt(Hz)
    gyroscope_random_walk: float = 2.0e-5  # rad/s^2/sqrt(Hz)
    update_rate: float = 200.0  # Hz


@dataclass
class RigCalibration:
    """All cameras of a rig (keyed ``cam0``, ``cam1``, ...) and the IMU noise model."""

    cameras: dict[str, CameraCalibration]
    imu: ImuNoise | None = None

    def to_json(self) -> str:
        d: dict = {name: cam.to_json_dict() for name, cam in self.cameras.items()}
        if self.imu is not None:
            d["imu"] = asdict(self.imu)
        return json.dumps(d)

    @classmethod
    def from_json(cls, text: str, *, path=None) -> "RigCalibration":
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise DataError(path, f"/calib attribute 'json' is not valid JSON ({exc})") from None
        if not isinstance(d, dict):
            raise DataError(path, "/calib attribute 'json' must be a JSON object keyed by camera name")
        cams = {k: CameraCalibration.from_json_dict(v, path=path, name=k) for k, v in d.items() if k.startswith("cam")}
        imu = ImuNoise(**d["imu"]) if isinstance(d.get("imu"), dict) else None
        return cls(cams, imu)
