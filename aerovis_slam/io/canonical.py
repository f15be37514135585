"""The canonical sequence itself, as a :class:`~aerovis_slam.io.source.Recording` (for ``info``)."""

from __future__ import annotations

from pathlib import Path

import h5py

from .sequence import FORMAT_NAME, Sequence
from .source import Recording, register_format


class CanonicalRecording(Recording):
    format_name = FORMAT_NAME

    def __init__(self, path):
        super().__init__(path)
        self.seq = Sequence(path)

    def cameras(self):
        return self.seq.cameras

    def sensor_size(self, cam):
        return self.seq.sensor_size(cam)

    def iter_events(self, cam, chunk_events=1 << 20):
        return self.seq.iter_events(cam, chunk_events)

    def imu(self):
        return self.seq.imu

    def gt(self):
        return self.seq.gt

    def calibration(self):
        return self.seq.calib if self.seq.has_calib else None

    def triggers(self, cam):
        return self.seq.triggers(cam)

    def iter_frames(self, cam):
        times = self.seq.frame_times(cam)
        for i, t in enumerate(times if times is not None else []):
            yield int(t), self.seq.frame(cam, i)

    def info(self):
        return self.seq.summary()

    def close(self):
        self.seq.close()


def _probe(path: Path) -> bool:
    if not path.is_file() or path.suffix.lower() not in (".h5", ".hdf5"):
        return False
    try:
        with h5py.File(path, "r") as f:
            return f.attrs.get("format") == FORMAT_NAME
    except OSError:
        return False


register_format(FORMAT_NAME, _probe, CanonicalRecording)
