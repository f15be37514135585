"""The stereo camera model the runtime works in: pinhole at the MCTS resolution.

Each camera's events pass through a :class:`~aerovis_slam.mcts.PixelMap` (identity for the simulator's
ideal pinhole rigs; undistortion/rectification when the calibration has distortion or ``R_rect``;
area-binning when the sensor exceeds the configured resolution), and the MCTS is cropped top-left
to the detector's size multiple (which keeps the intrinsics). Frames:

* ``T_body_cam`` (4, 4) maps camera points into the body (IMU) frame: the calibration's ``T_imu_cam``,
  times the inverse rectifying rotation when events are rectified (``p_rect = R_rect p_cam``).
* ``T_right_left`` = ``inv(T_body_right) @ T_body_left`` maps left-camera points into the right camera.

Example:
    >>> from aerovis_slam.sim.rig import load_rig
    >>> cams = StereoCameras.from_rig(load_rig("drone424"), max_width=424, max_height=240, size_multiple=8)
    >>> cams.left.width, cams.left.height, round(float(cams.baseline_m), 3)
    (424, 240, 0.074)
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from ..calib import CameraCalibration, RigCalibration
from ..errors import DataError
from ..geometry import invert_T
from ..mcts import PixelMap


@dataclass
class CameraModel:
    """One camera as the frontend sees it.

    Attributes:
        name: calibration key (``cam0``).
        K: (3, 3) intrinsics at the MCTS resolution.
        width, height: MCTS size after the crop to the detector's size multiple.
        buffer_width, buffer_height: timestamp-buffer size (before the crop).
        T_body_cam: (4, 4) camera-to-body transform.
        pixel_map: sensor -> buffer mapping.
    """

    name: str
    K: np.ndarray
    width: int
    height: int
    buffer_width: int
    buffer_height: int
    T_body_cam: np.ndarray
    pixel_map: PixelMap

    @property
    def cal3(self) -> gtsam.Cal3_S2:
        return gtsam.Cal3_S2(self.K[0, 0], self.K[1, 1], 0.0, self.K[0, 2], self.K[1, 2])

    @property
    def body_P_sensor(self) -> gtsam.Pose3:
        return gtsam.Pose3(self.T_body_cam)

    @classmethod
    def from_calibration(cls, name: str, cam: CameraCalibration, *, max_width: int, max_height: int,
                         size_multiple: int, rectify: bool) -> "CameraModel":
        needs_undistort = cam.distortion_model != "none" and any(abs(c) > 0 for c in cam.distortion_coeffs)
        scale = min(1.0, max_width / cam.width, max_height / cam.height)
        w, h = max(1, int(round(cam.width * scale))), max(1, int(round(cam.height * scale)))
        T_body_cam = np.asarray(cam.T_imu_cam, np.float64).copy()
        if needs_undistort or (rectify and cam.R_rect is not None):
            pm = PixelMap.from_calibration(cam, w, h, rectify=rectify)
            if rectify and cam.R_rect is not None:
                T_rect = np.eye(4)
                T_rect[:3, :3] = cam.R_rect.T  # rectified -> original camera frame
                T_body_cam = T_body_cam @ T_rect
        elif (w, h) != (cam.width, cam.height):
            pm = PixelMap.downsample(cam.width, cam.height, w, h, K=cam.K)
        else:
            pm = PixelMap.identity(w, h, K=cam.K)
        m = max(int(size_multiple), 1)
        cw, ch = w - w % m, h - h % m
        if cw < m or ch < m:
            raise DataError(None, f"camera {name}: {w}x{h} is smaller than the detector's size multiple {m}")
        return cls(name, pm.K, cw, ch, w, h, T_body_cam, pm)


@dataclass
class StereoCameras:
    """Left (``cam0``) and right (``cam1``) :class:`CameraModel`.

    Attributes:
        left, right: the cameras. T_right_left: (4, 4) left-to-right transform.
    """

    left: CameraModel
    right: CameraModel

    @property
    def T_right_left(self) -> np.ndarray:
        return invert_T(self.right.T_body_cam) @ self.left.T_body_cam

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.T_right_left[:3, 3]))

    @property
    def cams(self) -> tuple[CameraModel, CameraModel]:
        return self.left, self.right

    @classmethod
    def from_rig(cls, rig: RigCalibration, *, max_width: int, max_height: int, size_multiple: int,
                 path=None) -> "StereoCameras":
        """Build from a rig calibration (needs ``cam0`` and ``cam1``)."""
        for key in ("cam0", "cam1"):
            if key not in rig.cameras:
                raise DataError(path, f"/calib has no {key}: stereo SLAM needs cam0 (left) and cam1 (right); found {sorted(rig.cameras)}")
        c0, c1 = rig.cameras["cam0"], rig.cameras["cam1"]
        rectify = c0.R_rect is not None and c1.R_rect is not None and c0.P_rect is not None and c1.P_rect is not None
        kw = dict(max_width=max_width, max_height=max_height, size_multiple=size_multiple, rectify=rectify)
        return cls(CameraModel.from_calibration("cam0", c0, **kw), CameraModel.from_calibration("cam1", c1, **kw))
