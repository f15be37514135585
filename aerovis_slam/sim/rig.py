"""Simulated sensor rigs: YAML files in ``conf/rig/`` turned into :class:`RigCalibration`.

A rig file holds ``cameras`` (``cam0``, ``cam1``, ... each with ``width``, ``height``, ``fx``,
``fy``, ``cx``, ``cy`` and ``T_imu_cam``, the 4x4 camera-to-IMU/body transform) and ``imu``
(``update_rate`` in Hz and the Kalibr noise densities of :class:`~aerovis_slam.calib.ImuNoise`).
The simulator renders ideal pinhole images, so every camera is stored with
``distortion_model: none``.

Example:
    >>> rig = load_rig("tiny_stereo")
    >>> sorted(rig.cameras), rig.cameras["cam0"].width, rig.imu.update_rate
    (['cam0', 'cam1'], 64, 1000.0)
    >>> scale_rig(rig, 0.5).cameras["cam0"].width
    32
"""

from __future__ import annotations

import os
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import yaml

from ..calib import CameraCalibration, ImuNoise, RigCalibration
from ..errors import DataError

#: Folder of the rig files shipped with the repository (``<repo>/conf/rig``).
RIG_DIR = Path(__file__).resolve().parents[2] / "conf" / "rig"
_CAMERA_FIELDS = ("width", "height", "fx", "fy", "cx", "cy", "T_imu_cam")
_IMU_FIELDS = tuple(asdict(ImuNoise()).keys())


def available_rigs() -> list[str]:
    """Names of the rig files in :data:`RIG_DIR` (without ``.yaml``)."""
    return sorted(p.stem for p in RIG_DIR.glob("*.yaml")) if RIG_DIR.is_dir() else []


def rig_path(name_or_path: str | os.PathLike) -> Path:
    """Resolve a rig name (``drone424``) or a path to a YAML file."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        if not p.is_file():
            raise DataError(p, "rig file not found")
        return p
    cand = RIG_DIR / f"{name_or_path}.yaml"
    if not cand.is_file():
        raise DataError(cand, f"unknown rig {str(name_or_path)!r}; available: {available_rigs()}")
    return cand


def load_rig(name_or_path: str | os.PathLike) -> RigCalibration:
    """Load a rig YAML (by name in ``conf/rig`` or by path) as a :class:`RigCalibration`.

    Raises:
        DataError: naming the file and the missing or malformed field.
    """
    path = rig_path(name_or_path)
    try:
        d = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise DataError(path, f"not a readable YAML file ({exc})") from None
    if not isinstance(d, dict):
        raise DataError(path, "a rig file must be a mapping with 'cameras' and 'imu'")
    for key in ("cameras", "imu"):
        if key not in d:
            raise DataError(path, f"missing field '{key}' (a rig needs 'cameras' and 'imu')")
    cams_d = d["cameras"]
    if not isinstance(cams_d, dict) or not cams_d:
        raise DataError(path, "field 'cameras' must map camera names (cam0, cam1, ...) to their calibration")
    cameras = {}
    for name, c in cams_d.items():
        if not str(name).startswith("cam"):
            raise DataError(path, f"camera name {name!r} must start with 'cam' (cam0, cam1, ...)")
        if not isinstance(c, dict):
            raise DataError(path, f"cameras.{name} must be a mapping with fields {list(_CAMERA_FIELDS)}")
        missing = [k for k in _CAMERA_FIELDS if k not in c]
        if missing:
            raise DataError(path, f"cameras.{name} lacks field(s) {missing} (expected all of {list(_CAMERA_FIELDS)})")
        T = np.asarray(c["T_imu_cam"], dtype=np.float64)
        if T.shape != (4, 4):
            raise DataError(path, f"cameras.{name}.T_imu_cam has shape {T.shape}, expected (4, 4)")
        R = T[:3, :3]
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or abs(np.linalg.det(R) - 1) > 1e-6:
            raise DataError(path, f"cameras.{name}.T_imu_cam: the rotation block is not a rotation matrix")
        cameras[str(name)] = CameraCalibration(
            width=c["width"], height=c["height"], fx=c["fx"], fy=c["fy"], cx=c["cx"], cy=c["cy"],
            distortion_model="none", distortion_coeffs=[], T_imu_cam=T,
        )
    imu_d = d["imu"]
    if not isinstance(imu_d, dict):
        raise DataError(path, f"field 'imu' must be a mapping with fields {list(_IMU_FIELDS)}")
    missing = [k for k in _IMU_FIELDS if k not in imu_d]
    if missing:
        raise DataError(path, f"imu lacks field(s) {missing} (expected all of {list(_IMU_FIELDS)})")
    imu = ImuNoise(**{k: float(imu_d[k]) for k in _IMU_FIELDS})
    return RigCalibration(cameras, imu)


def scale_rig(rig: RigCalibration, factor: float) -> RigCalibration:
    """Resize every camera by ``factor`` (width/height rounded; intrinsics scaled about pixel centres).

    With pixel centres at integer coordinates, a pixel edge at -0.5 maps to -0.5, so
    ``c' = (c + 0.5) * s - 0.5`` where ``s`` is the exact ratio of the rounded sizes.
    """
    cams = {}
    for name, c in rig.cameras.items():
        w, h = max(1, round(c.width * factor)), max(1, round(c.height * factor))
        sx, sy = w / c.width, h / c.height
        cams[name] = replace(c, width=w, height=h, fx=c.fx * sx, fy=c.fy * sy,
                             cx=(c.cx + 0.5) * sx - 0.5, cy=(c.cy + 0.5) * sy - 0.5,
                             T_imu_cam=c.T_imu_cam.copy())
    return RigCalibration(cams, replace(rig.imu) if rig.imu is not None else None)
