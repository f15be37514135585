"""The interface of every recording reader, format detection, and conversion.

A :class:`Recording` streams a recording in some external format (ECD text, DSEC-style HDF5,
ROS bags, Prophesee RAW, AEDAT4, or the canonical sequence itself) as event chunks per camera,
plus IMU, ground truth, calibration, frames and triggers where the format has them. Every reader
registers itself with :func:`register_format`; :func:`open_recording` picks the first whose
``probe`` accepts the path, and :func:`convert` writes any recording in the canonical format.
"""

from __future__ import annotations

import os
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..calib import RigCalibration
from ..errors import DataError
from ..events import EventArray
from ..measurements import ImuSamples, PoseSamples


class Recording(ABC):
    """A recording opened for streaming. Timestamps are µs; cameras are named ``cam0``, ``cam1``...

    Subclasses implement :meth:`cameras`, :meth:`sensor_size` and :meth:`iter_events`, and
    override the optional streams their format carries.
    """

    #: short name of the format, e.g. ``"prophesee-raw-evt3"``
    format_name: str = "unknown"

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)

    @abstractmethod
    def cameras(self) -> list[str]:
        """Camera names, ``["cam0"]`` or ``["cam0", "cam1"]``."""

    @abstractmethod
    def sensor_size(self, cam: str) -> tuple[int, int]:
        """(width, height) in pixels."""

    @abstractmethod
    def iter_events(self, cam: str, chunk_events: int = 1 << 20) -> Iterator[EventArray]:
        """Stream the events of ``cam`` in time order, in chunks of roughly ``chunk_events``."""

    def imu(self) -> ImuSamples | None:
        return None

    def gt(self) -> PoseSamples | None:
        return None

    def calibration(self) -> RigCalibration | None:
        return None

    def iter_frames(self, cam: str) -> Iterator[tuple[int, np.ndarray]]:
        """(t µs, uint8 (H, W) grayscale image) pairs, if the format has frames."""
        return iter(())

    def triggers(self, cam: str) -> tuple[np.ndarray, np.ndarray] | None:
        """External-trigger events ``(t µs int64, edge int8 1 = rising)`` if present."""
        return None

    def info(self) -> dict:
        """JSON-ready summary. Streams through the events once unless a subclass knows better."""
        cams = {}
        for cam in self.cameras():
            w, h = self.sensor_size(cam)
            n, first, last = 0, None, None
            for chunk in self.iter_events(cam):
                if len(chunk):
                    first = int(chunk.t[0]) if first is None else first
                    last = int(chunk.t[-1])
                    n += len(chunk)
            cams[cam] = {"width": w, "height": h, "events": n, "t_first_us": first, "t_last_us": last}
            trig = self.triggers(cam)
            if trig is not None:
                cams[cam]["triggers"] = int(len(trig[0]))
        imu, gt = self.imu(), self.gt()
        return {
            "path": str(self.path),
            "format": self.format_name,
            "cameras": cams,
            "imu": len(imu) if imu is not None else 0,
            "gt": len(gt) if gt is not None else 0,
            "calibrated": self.calibration() is not None,
        }

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class SingleCameraRecording(Recording):
    """A recording of one camera, exposed as ``cam0``. Subclasses set ``self._size = (width, height)``."""

    _size: tuple[int, int]

    def cameras(self) -> list[str]:
        return ["cam0"]

    def sensor_size(self, cam: str) -> tuple[int, int]:
        self._check_cam(cam)
        return self._size

    def _check_cam(self, cam: str) -> None:
        if cam != "cam0":
            raise DataError(self.path, f"no camera {cam!r}; a {self.format_name} recording has only 'cam0'")


@dataclass
class _Format:
    name: str
    probe: Callable[[Path], bool]
    open: Callable[[Path], Recording]


_FORMATS: list[_Format] = []
_BUILTINS_LOADED = False


def register_format(name: str, probe: Callable[[Path], bool], opener: Callable[[Path], Recording]) -> None:
    """Register a reader: ``probe(path)`` says cheaply whether it can read ``path``."""
    _FORMATS.append(_Format(name, probe, opener))


def _load_builtin_readers() -> None:
    # Imported for their register_format side effect; each module is self-contained. A flag, not
    # "is the list empty", since importing one reader module directly registers that one alone.
    global _BUILTINS_LOADED
    if _BUILTINS_LOADED:
        return
    _BUILTINS_LOADED = True
    import importlib

    for mod in ("canonical", "ecd_text", "h5_datasets", "rosbag", "prophesee_raw", "aedat4"):
        try:
            importlib.import_module(f"{__package__}.{mod}")
        except ModuleNotFoundError as exc:
            if exc.name != f"{__package__}.{mod}":
                raise


def supported_formats() -> list[str]:
    _load_builtin_readers()
    return [f.name for f in _FORMATS]


def open_recording(path: str | os.PathLike) -> Recording:
    """Open ``path`` with the first reader whose probe accepts it.

    Raises:
        DataError: the path does not exist or no reader recognises it.
    """
    path = Path(path)
    if not path.exists():
        raise DataError(path, "no such file or folder")
    _load_builtin_readers()
    for fmt in _FORMATS:
        if fmt.probe(path):
            return fmt.open(path)
    raise DataError(path, f"unrecognised recording format; supported: {', '.join(f.name for f in _FORMATS)}")


def convert(
    recording: Recording,
    out_path: str | os.PathLike,
    *,
    calib: RigCalibration | None = None,
    require_calib: bool = True,
    progress: bool = True,
) -> dict:
    """Write ``recording`` as a canonical sequence at ``out_path`` (atomically) and return its summary.

    Args:
        recording: any opened recording.
        out_path: the ``.h5`` to write.
        calib: overrides (or supplies) the recording's calibration.
        require_calib: refuse to write a sequence without calibration (geometry needs it); with
            False, only sensor sizes are stored and ``/calib`` is absent.
        progress: show a tqdm bar per camera.
    """
    from tqdm import tqdm

    from .sequence import Sequence, SequenceWriter

    calib = calib or recording.calibration()
    if calib is None and require_calib:
        raise DataError(recording.path, "no calibration in this recording: pass one (--calib, a Kalibr camchain-imucam or "
                                        "ROS camera_info yaml), or convert without it (--no-calib)")
    sizes = {cam: recording.sensor_size(cam) for cam in recording.cameras()}
    if calib is not None:
        for cam, (w, h) in sizes.items():
            c = calib.cameras.get(cam)
            if c is None:
                raise DataError(recording.path, f"calibration has no camera {cam!r} (it has {sorted(calib.cameras)})")
            if (c.width, c.height) != (w, h):
                raise DataError(recording.path, f"calibration of {cam} is {c.width}x{c.height} but the sensor is {w}x{h}")
    meta = {"source": str(recording.path), "source_format": recording.format_name}
    with SequenceWriter(out_path, calib, sensor_sizes=sizes, meta=meta) as writer:
        for cam in recording.cameras():
            bar = tqdm(desc=f"{cam} events", unit="ev", unit_scale=True, disable=not progress, leave=False)
            for chunk in recording.iter_events(cam):
                writer.add_events(cam, chunk)
                bar.update(len(chunk))
            bar.close()
            trig = recording.triggers(cam)
            if trig is not None:
                writer.add_triggers(cam, *trig)
            for t, image in recording.iter_frames(cam):
                writer.add_frames(cam, np.array([t]), image[None])
        imu = recording.imu()
        if imu is not None:
            writer.set_imu(imu)
        gt = recording.gt()
        if gt is not None:
            writer.set_gt(gt)
    with Sequence(out_path) as seq:
        return seq.summary()
