"""Event HDF5 files of public datasets (DSEC, TUM-VIE, EDS) as a :class:`~aerovis_slam.io.source.Recording`.

Layouts read (one file per camera):

* **DSEC** (``events.h5``): ``/events/{t,x,y,p}`` with ``t`` µs *relative to* ``/t_offset`` (µs,
  scalar), plus ``/ms_to_idx``; 640x480 (Prophesee Gen3.1). Events are zstd/blosc compressed
  through HDF5 filter plugins, which :mod:`hdf5plugin` registers (imported here when installed).
* **TUM-VIE** (``*-events_left.h5`` / ``*-events_right.h5``): ``/events/{t,x,y,p}`` (µs) and
  ``/ms_to_idx``, no ``t_offset``; 1280x720 (Prophesee Gen4 HD).
* **EDS** (``events.h5``): root datasets ``x, y, t (µs), p``; 640x480.

A stereo recording is a folder with ``left/events.h5`` + ``right/events.h5`` (DSEC's
``events/left``), ``events_left/events.h5`` + ``events_right/events.h5`` (DSEC's zips), one
``*events_left.h5`` + ``*events_right.h5`` pair (TUM-VIE), or an explicit list of files
(``cam0`` first). The sensor size comes from ``width``/``height`` attributes where a file has
them, else from the layout as above, or from the ``sensor_size`` argument. Events are streamed in
index chunks; nothing is loaded whole.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from pathlib import Path

import h5py
import numpy as np

from ..errors import DataError
from ..events import EventArray
from .sequence import FORMAT_NAME as CANONICAL_FORMAT, dataset_filters
from .source import Recording, register_format

import hdf5plugin  # noqa: F401  registers the blosc / zstd / lz4 ... filters that DSEC and TUM-VIE use

FORMAT_NAME = "event-h5"
#: Known sensor sizes (width, height) by layout, used when a file stores none.
SENSOR_SIZES = {"dsec": (640, 480), "tumvie": (1280, 720), "eds": (640, 480)}
_FIELDS = ("t", "x", "y", "p")


def _event_group(f: h5py.File) -> h5py.Group | None:
    """The group holding the t/x/y/p datasets (``/events`` or the root), or None."""
    for g in (f.get("events"), f):
        if isinstance(g, h5py.Group) and all(isinstance(g.get(k), h5py.Dataset) for k in _FIELDS):
            return g
    return None


def _layout(f: h5py.File, group: h5py.Group) -> str:
    if group.name == "/":
        return "eds"
    return "dsec" if "t_offset" in f else "tumvie"


def _check_filters(path: Path, ds: h5py.Dataset) -> None:
    """Raise a clear DataError if ``ds`` needs an HDF5 filter that is not registered."""
    for code, fname in dataset_filters(ds):
        if not h5py.h5z.filter_avail(code):
            raise DataError(path, f"dataset {ds.name} is compressed with HDF5 filter {code} ({fname or 'unknown'}), "
                                  f"which is not available: it is not among hdf5plugin {hdf5plugin.version}'s filters "
                                  "(https://github.com/HDFGroup/hdf5_plugins lists where others come from)")


class _CameraFile:
    """One camera's event file, opened lazily-streamable."""

    def __init__(self, path: Path, sensor_size: tuple[int, int] | None):
        self.path = path
        try:
            self.file = h5py.File(path, "r")
        except OSError as exc:
            raise DataError(path, f"not a readable HDF5 file ({exc})") from None
        group = _event_group(self.file)
        if group is None:
            self.file.close()
            raise DataError(path, "no event datasets: expected /events/{t,x,y,p} (DSEC, TUM-VIE) or /{x,y,t,p} (EDS)")
        self.group = group
        self.layout = _layout(self.file, group)
        self.ds = {k: group[k] for k in _FIELDS}
        n = {k: d.shape[0] if d.ndim == 1 else -1 for k, d in self.ds.items()}
        if len(set(n.values())) != 1 or -1 in n.values():
            self.file.close()
            raise DataError(path, f"event datasets {group.name}/{{t,x,y,p}} must be 1-D and equally long, got lengths {n}")
        self.n = n["t"]
        for ds in self.ds.values():
            _check_filters(path, ds)
        self.t_offset = 0
        if "t_offset" in self.file:
            self.t_offset = int(np.asarray(self.file["t_offset"][()]).ravel()[0])
        self.size = sensor_size or self._stored_size() or SENSOR_SIZES[self.layout]

    def _stored_size(self) -> tuple[int, int] | None:
        for obj in (self.group, self.file):
            a = obj.attrs
            if "width" in a and "height" in a:
                return int(a["width"]), int(a["height"])
            if "sensor_size" in a:  # some exports store (height, width); width is the larger side of these sensors
                h, w = sorted(int(v) for v in np.asarray(a["sensor_size"]).ravel()[:2])
                return w, h
        return None

    def read(self, start: int, stop: int) -> EventArray:
        try:
            t = self.ds["t"][start:stop].astype(np.int64)
            x, y, p = (self.ds[k][start:stop] for k in ("x", "y", "p"))
        except OSError as exc:
            raise DataError(self.path, f"cannot read events [{start}, {stop}) ({exc})") from None
        if self.t_offset:
            t += self.t_offset
        p = np.asarray(p)
        if p.dtype != np.bool_:
            bad = (p != 0) & (p != 1) & (p != -1)
            if bad.any():
                raise DataError(self.path, f"{self.group.name}/p has values {np.unique(p[bad])[:5].tolist()} (expected 0/1 or -1/1)")
        return EventArray(t, x, y, (p > 0).astype(np.int8))

    def close(self) -> None:
        self.file.close()


def _stereo_files(folder: Path) -> list[Path] | None:
    for left, right in (("left/events.h5", "right/events.h5"), ("events_left/events.h5", "events_right/events.h5"),
                        ("events/left/events.h5", "events/right/events.h5")):
        if (folder / left).is_file() and (folder / right).is_file():
            return [folder / left, folder / right]
    lefts = sorted(folder.glob("*events_left.h5"))
    if len(lefts) == 1:
        right = lefts[0].with_name(lefts[0].name.replace("events_left", "events_right"))
        return [lefts[0], right] if right.is_file() else [lefts[0]]
    if (folder / "events.h5").is_file():
        return [folder / "events.h5"]
    return None


class H5EventsRecording(Recording):
    """DSEC / TUM-VIE / EDS event files, one per camera.

    Args:
        path: an event ``.h5`` file, a stereo folder (see the module docstring), or a list of files
            (``cam0``, ``cam1``, ...).
        sensor_size: (width, height) to use for every camera, overriding the files and layout defaults.
    """

    format_name = FORMAT_NAME

    def __init__(self, path: str | os.PathLike | Sequence[str | os.PathLike], sensor_size: tuple[int, int] | None = None):
        if isinstance(path, (str, os.PathLike)):
            p = Path(path)
            files = _stereo_files(p) if p.is_dir() else [p]
            if files is None:
                raise DataError(p, "no event files: expected left/events.h5 + right/events.h5, events.h5, or *events_left.h5")
            super().__init__(p)
        else:
            files = [Path(f) for f in path]
            if not files:
                raise DataError(None, "no event files given")
            super().__init__(files[0].parent if len(files) > 1 else files[0])
        self._cams: dict[str, _CameraFile] = {}
        try:
            for i, f in enumerate(files):
                if not f.is_file():
                    raise DataError(f, "no such event file")
                self._cams[f"cam{i}"] = _CameraFile(f, sensor_size)
        except Exception:
            self.close()
            raise

    def cameras(self) -> list[str]:
        return list(self._cams)

    def sensor_size(self, cam: str) -> tuple[int, int]:
        return self._cam(cam).size

    def iter_events(self, cam: str, chunk_events: int = 1 << 20) -> Iterator[EventArray]:
        """Stream ``cam``'s events (absolute µs: DSEC's ``t_offset`` added) in index chunks.

        Raises:
            DataError: decreasing timestamps or pixels outside the sensor (file and dataset named).
        """
        cf = self._cam(cam)
        w, h = cf.size
        last = None
        for s in range(0, cf.n, chunk_events):
            ev = cf.read(s, min(s + chunk_events, cf.n))
            if len(ev) == 0:
                continue
            d = np.diff(ev.t)
            if (last is not None and ev.t[0] < last) or (d < 0).any():
                k = 0 if (last is not None and ev.t[0] < last) else int(np.flatnonzero(d < 0)[0]) + 1
                prev = last if k == 0 else int(ev.t[k - 1])
                raise DataError(cf.path, f"{cf.group.name}/t decreases at index {s + k}: {int(ev.t[k])} µs after {prev} µs (expected sorted)")
            out = np.flatnonzero((ev.x >= w) | (ev.y >= h))
            if len(out):
                k = int(out[0])
                raise DataError(cf.path, f"{cf.group.name}: event {s + k} at pixel ({ev.x[k]}, {ev.y[k]}) is outside the {w}x{h} "
                                         f"sensor (pass sensor_size if this is not a {cf.layout} file)")
            last = int(ev.t[-1])
            yield ev

    def info(self) -> dict:
        """Summary read from the first/last timestamps only (no pass over the events)."""
        cams = {}
        for cam, cf in self._cams.items():
            first = int(cf.ds["t"][0]) + cf.t_offset if cf.n else None
            last = int(cf.ds["t"][cf.n - 1]) + cf.t_offset if cf.n else None
            cams[cam] = {"width": cf.size[0], "height": cf.size[1], "events": cf.n, "t_first_us": first, "t_last_us": last,
                         "layout": cf.layout}
        return {"path": str(self.path), "format": self.format_name, "cameras": cams, "imu": 0, "gt": 0, "calibrated": False}

    def _cam(self, cam: str) -> _CameraFile:
        if cam not in self._cams:
            raise DataError(self.path, f"no camera {cam!r}; cameras are {list(self._cams)}")
        return self._cams[cam]

    def close(self) -> None:
        for cf in getattr(self, "_cams", {}).values():
            cf.close()


def _probe_file(path: Path) -> bool:
    if not path.is_file() or path.suffix.lower() not in (".h5", ".hdf5"):
        return False
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") == CANONICAL_FORMAT:
                return False
            return _event_group(f) is not None
    except OSError:
        return False


def _probe(path: Path) -> bool:
    if path.is_dir():
        files = _stereo_files(path)
        return bool(files) and all(_probe_file(f) for f in files)
    return _probe_file(path)


register_format(FORMAT_NAME, _probe, H5EventsRecording)
