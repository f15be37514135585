"""iniVation AEDAT4 recordings (DV software, DAVIS / DVXplorer) as a :class:`~aerovis_slam.io.source.Recording`.

Decoding (header, flatbuffer packets, lz4/zstd compression, the file data table) is left to
iniVation's own ``dv-processing`` library (``pip install dv-processing``; cp3x manylinux wheels),
imported only when a file is opened, so the runtime does not depend on it otherwise.

Units: AEDAT4 timestamps are µs already. DV's IMU packets carry the accelerometer in g and the
gyroscope in deg/s; they are converted to m/s² (standard gravity 9.80665) and rad/s. Frames are
returned as uint8 grayscale (colour frames are converted). External-trigger rising/falling edges
become :meth:`triggers`. Only the first camera of a file is read (``cam0``).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..events import EventArray
from ..measurements import ImuSamples
from .source import SingleCameraRecording, register_format

FORMAT_NAME = "aedat4"
MAGIC = b"#!AER-DAT4.0"
STANDARD_GRAVITY = 9.80665  # m/s² per g (the value DV's drivers scale by)
DEG_TO_RAD = np.pi / 180.0


def _dv(path=None):
    try:
        import dv_processing
    except ImportError:
        raise DataError(path, "reading AEDAT4 needs iniVation's dv-processing: `pip install dv-processing`") from None
    return dv_processing


class Aedat4Recording(SingleCameraRecording):
    """An AEDAT4 file (one camera).

    Args:
        path: the ``.aedat4`` file.

    Raises:
        DataError: not an AEDAT4 file, truncated, or without an event stream.
    """

    format_name = FORMAT_NAME

    def __init__(self, path: str | os.PathLike):
        super().__init__(path)
        with open(self.path, "rb") as f:
            if f.read(len(MAGIC)) != MAGIC:
                raise DataError(self.path, f"not an AEDAT4 file (expected it to start with {MAGIC!r})")
        rec = self._open()
        try:
            if not rec.isEventStreamAvailable():
                raise DataError(self.path, f"no event stream (streams: {list(rec.getStreamNames())})")
            w, h = rec.getEventResolution()
        except RuntimeError as exc:
            raise self._error(exc) from None
        self._size = (int(w), int(h))
        self._has = {"imu": rec.isImuStreamAvailable(), "frames": rec.isFrameStreamAvailable(),
                     "triggers": rec.isTriggerStreamAvailable()}

    def _open(self):
        dv = _dv(self.path)
        try:
            return dv.io.MonoCameraRecording(str(self.path))
        except RuntimeError as exc:
            raise self._error(exc) from None

    def _error(self, exc: Exception) -> DataError:
        msg = str(exc)
        why = "truncated or corrupt" if ("EndOfFile" in msg or "could not verify" in msg or "FileDataTable" in msg) else "unreadable"
        return DataError(self.path, f"AEDAT4 file is {why} ({msg.splitlines()[-1].strip()[:160]})")

    def iter_events(self, cam: str = "cam0", chunk_events: int = 1 << 20) -> Iterator[EventArray]:
        """Stream the events, regrouped from DV packets into chunks of about ``chunk_events``.

        Raises:
            DataError: truncated file, decreasing timestamps or pixels outside the sensor.
        """
        self._check_cam(cam)
        rec = self._open()
        w, h = self._size
        pending: list[np.ndarray] = []
        n_pending = 0
        last = None
        while True:
            try:
                batch = rec.getNextEventBatch()
            except RuntimeError as exc:
                raise self._error(exc) from None
            if batch is not None and len(batch):
                a = batch.numpy()
                pending.append(a)
                n_pending += len(a)
            if n_pending and (batch is None or n_pending >= chunk_events):
                a = np.concatenate(pending)
                pending, n_pending = [], 0
                ev = EventArray(a["timestamp"], a["x"], a["y"], a["polarity"].astype(np.int8))
                if (last is not None and ev.t[0] < last) or np.any(np.diff(ev.t) < 0):
                    raise DataError(self.path, f"event timestamps decrease near {int(ev.t[0])} µs (expected sorted)")
                if (a["x"].min() < 0 or a["y"].min() < 0 or ev.x.max() >= w or ev.y.max() >= h):
                    raise DataError(self.path, f"events outside the {w}x{h} sensor (x in [{a['x'].min()}, {a['x'].max()}], "
                                               f"y in [{a['y'].min()}, {a['y'].max()}])")
                last = int(ev.t[-1])
                yield ev
            if batch is None:
                return

    def imu(self) -> ImuSamples | None:
        """IMU samples with acc converted g -> m/s² and gyro deg/s -> rad/s (axes as in the file)."""
        if not self._has["imu"]:
            return None
        rec = self._open()
        rows = []
        while True:
            try:
                batch = rec.getNextImuBatch()
            except RuntimeError as exc:
                raise self._error(exc) from None
            if batch is None:
                break
            rows.extend((s.timestamp, s.accelerometerX, s.accelerometerY, s.accelerometerZ,
                         s.gyroscopeX, s.gyroscopeY, s.gyroscopeZ) for s in batch)
        if not rows:
            return None
        t = np.array([r[0] for r in rows], np.int64)
        v = np.array([r[1:] for r in rows], np.float64)
        return ImuSamples(t, gyro=v[:, 3:6] * DEG_TO_RAD, acc=v[:, 0:3] * STANDARD_GRAVITY)

    def iter_frames(self, cam: str = "cam0") -> Iterator[tuple[int, np.ndarray]]:
        """(t µs, uint8 (H, W)) grayscale frames (DAVIS APS)."""
        self._check_cam(cam)
        if not self._has["frames"]:
            return
        import cv2

        rec = self._open()
        while True:
            try:
                frame = rec.getNextFrame()
            except RuntimeError as exc:
                raise self._error(exc) from None
            if frame is None:
                return
            img = np.asarray(frame.image)
            if img.ndim == 3:
                img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
            if img.dtype != np.uint8:
                raise DataError(self.path, f"frame at {frame.timestamp} µs has dtype {img.dtype}, expected 8-bit")
            yield int(frame.timestamp), img

    def triggers(self, cam: str = "cam0") -> tuple[np.ndarray, np.ndarray] | None:
        """External-signal edges: (t µs, 1 rising / 0 falling); other trigger kinds are dropped."""
        self._check_cam(cam)
        if not self._has["triggers"]:
            return None
        dv = _dv(self.path)
        edge = {dv.TriggerType.EXTERNAL_SIGNAL_RISING_EDGE: 1, dv.TriggerType.EXTERNAL_SIGNAL_FALLING_EDGE: 0}
        rec = self._open()
        t, p = [], []
        while True:
            try:
                batch = rec.getNextTriggerBatch()
            except RuntimeError as exc:
                raise self._error(exc) from None
            if batch is None:
                break
            for trig in batch:
                if trig.type in edge:
                    t.append(trig.timestamp)
                    p.append(edge[trig.type])
        if not t:
            return None
        return np.asarray(t, np.int64), np.asarray(p, np.int8)


def _probe(path: Path) -> bool:
    if not path.is_file():
        return False
    try:
        with open(path, "rb") as f:
            return f.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


register_format(FORMAT_NAME, _probe, Aedat4Recording)
