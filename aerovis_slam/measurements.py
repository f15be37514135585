"""Inertial and pose measurements (small enough to hold in memory whole).

Units: ``t`` int64 µs; gyro rad/s and acc m/s² in the IMU/body frame (the accelerometer
measures specific force, so a resting IMU reads +9.81 m/s² upwards); poses are
``tx ty tz qx qy qz qw`` of the body (IMU) in the world, ``T_world_body``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import DataError


@dataclass
class ImuSamples:
    """IMU samples. ``t`` (N,) int64 µs, ``gyro`` (N, 3) rad/s, ``acc`` (N, 3) m/s²."""

    t: np.ndarray
    gyro: np.ndarray
    acc: np.ndarray

    def __post_init__(self) -> None:
        self.t = np.ascontiguousarray(self.t, dtype=np.int64)
        self.gyro = np.ascontiguousarray(self.gyro, dtype=np.float64).reshape(-1, 3)
        self.acc = np.ascontiguousarray(self.acc, dtype=np.float64).reshape(-1, 3)
        if not (len(self.t) == len(self.gyro) == len(self.acc)):
            raise DataError(None, f"IMU fields differ in length: t={len(self.t)}, gyro={len(self.gyro)}, acc={len(self.acc)}")

    def __len__(self) -> int:
        return len(self.t)


@dataclass
class PoseSamples:
    """Poses ``T_world_body``. ``t`` (N,) int64 µs, ``pose`` (N, 7) = tx ty tz qx qy qz qw (metres)."""

    t: np.ndarray
    pose: np.ndarray

    def __post_init__(self) -> None:
        self.t = np.ascontiguousarray(self.t, dtype=np.int64)
        self.pose = np.ascontiguousarray(self.pose, dtype=np.float64).reshape(-1, 7)
        if len(self.t) != len(self.pose):
            raise DataError(None, f"pose fields differ in length: t={len(self.t)}, pose={len(self.pose)}")

    def __len__(self) -> int:
        return len(self.t)


def check_sorted_times(t: np.ndarray, *, path, field: str, strict: bool = False) -> None:
    """Raise :class:`DataError` if ``t`` decreases (or repeats, with ``strict``)."""
    d = np.diff(np.asarray(t))
    bad = np.flatnonzero(d <= 0 if strict else d < 0)
    if len(bad):
        i = int(bad[0])
        need = "strictly increasing" if strict else "non-decreasing"
        raise DataError(path, f"{field} is not {need}: value {t[i + 1]} at index {i + 1} follows {t[i]}")
