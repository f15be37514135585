"""The canonical sequence: one HDF5 file per recording, readable with h5py (after ``import hdf5plugin``).

Layout (format ``aerovis-sequence``, version 1)::

    /                       attrs: format="aerovis-sequence", format_version=1, meta=JSON (free-form provenance)
    /events/cam{i}/t        int64 (N,) µs, sorted
    /events/cam{i}/x, y     uint16 (N,)
    /events/cam{i}/p        int8 (N,), 0 = OFF, 1 = ON
    /events/cam{i}/ms_to_idx int64 (M+1,), attr t0_ms: ms_to_idx[k] = number of events with
                            t < (t0_ms + k) * 1000 µs, so the events of millisecond t0_ms + k are
                            [ms_to_idx[k], ms_to_idx[k + 1]) (as DSEC's ms_to_idx)
    /events/cam{i}          attrs: width, height (sensor size in pixels)
    /triggers/cam{i}/{t,p}  optional external-trigger events (int64 µs, int8 edge: 1 rising, 0 falling)
    /imu/{t,gyro,acc}       int64 µs; float64 (N,3) rad/s; float64 (N,3) m/s², IMU/body frame
    /gt/{t,pose}            int64 µs; float64 (N,7) tx ty tz qx qy qz qw of body in world
    /calib                  attr json: see :mod:`aerovis_slam.calib`
    /frames/cam{i}/{t,image} optional, uint8 (N,H,W) grayscale
    /depth/cam{i}/{t,depth} optional, float32 (N,H,W) z-depth in metres (inf = no surface)

Events are chunked and compressed with Blosc (LZ4, bit shuffle: sorted int64 timestamps shrink
several-fold), from :mod:`hdf5plugin`, which registers the filter with HDF5 on import; this module
imports it, and so must any other program that reads the events (DSEC's files need it too). Files
written with ``event_compression="gzip"`` (and those of earlier versions) read with plain h5py.
Frames and depth maps are gzip-compressed. Writers stream: memory stays bounded by one chunk,
whatever the length.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import h5py
import hdf5plugin
import numpy as np

from ..calib import RigCalibration
from ..errors import DataError
from ..events import EventArray, check_events
from ..measurements import ImuSamples, PoseSamples, check_sorted_times

FORMAT_NAME = "aerovis-sequence"
FORMAT_VERSION = 1
EVENT_CHUNK = 1 << 16  # HDF5 chunk length of event datasets (elements)
_COMPRESSION = dict(compression="gzip", compression_opts=1, shuffle=True)  # frames, depth maps
#: HDF5 filters of the event datasets, by name. Blosc-LZ4 with bit shuffle is the default because
#: reading is what limits a replay: h5py serialises all reads of a process behind one lock, so both
#: cameras' reader threads share one decoder. Measured on this project's 2-core box on bench events
#: (4 M events of shake_rapid and handheld_office, read in the runtime's 200k chunks): gzip-1 +
#: shuffle reads 23-24 Mev/s at 2.61-2.83 B/event, Blosc-LZ4 + bit shuffle 80-86 Mev/s at
#: 2.67-3.14 B/event (and writes 8x faster); shake_rapid needs 25.7 Mev/s for its two cameras.
#: ``aerovis-bench read`` measures both in one run.
EVENT_COMPRESSION = {
    "blosc-lz4": hdf5plugin.Blosc(cname="lz4", clevel=5, shuffle=hdf5plugin.Blosc.BITSHUFFLE),
    "gzip": dict(_COMPRESSION),
}
#: the compressing HDF5 filter of each :data:`EVENT_COMPRESSION` choice, by id
_EVENT_COMPRESSION_FILTER = {h5py.h5z.FILTER_DEFLATE: "gzip", hdf5plugin.BLOSC_ID: "blosc-lz4"}


def dataset_filters(ds: h5py.Dataset) -> list[tuple[int, str]]:
    """The HDF5 filter pipeline of ``ds``: ``(filter id, name stored in the file)`` in order."""
    plist = ds.id.get_create_plist()
    out = []
    for i in range(plist.get_nfilters()):
        code, _flags, _values, name = plist.get_filter(i)
        out.append((int(code), name.decode(errors="replace") if isinstance(name, bytes) else str(name)))
    return out


def camera_key(cam: str | int) -> str:
    """Normalise ``0`` / ``"0"`` / ``"cam0"`` to ``"cam0"``."""
    s = str(cam)
    return s if s.startswith("cam") else f"cam{s}"


class SequenceWriter:
    """Write a canonical sequence incrementally, atomically.

    Data goes to ``PATH.partial`` and is renamed to ``PATH`` only by :meth:`close` after a
    successful write; on an exception inside ``with`` the partial file is deleted, so a crash
    never leaves a half-written sequence under the final name.

    Args:
        event_compression: filter of the event datasets, a key of :data:`EVENT_COMPRESSION`:
            ``"blosc-lz4"`` (default, fast to read; readers import :mod:`hdf5plugin`) or ``"gzip"``
            (for tools that read HDF5 without filter plugins; about 3.5x slower to read).

    Example:
        >>> import tempfile, numpy as np
        >>> from aerovis_slam.events import EventArray
        >>> path = tempfile.mkdtemp() + "/seq.h5"
        >>> with SequenceWriter(path, sensor_sizes={"cam0": (4, 3)}) as w:
        ...     w.add_events("cam0", EventArray([10, 1500], [0, 3], [2, 1], [1, 0]))
        >>> with Sequence(path) as s:
        ...     s.num_events("cam0"), s.events("cam0", 1000, 2000).t.tolist()
        (2, [1500])
    """

    def __init__(
        self,
        path: str | os.PathLike,
        calib: RigCalibration | None = None,
        *,
        sensor_sizes: dict[str, tuple[int, int]] | None = None,
        meta: dict | None = None,
        event_compression: str = "blosc-lz4",
    ):
        self.path = Path(path)
        if event_compression not in EVENT_COMPRESSION:
            raise ValueError(f"event_compression must be one of {sorted(EVENT_COMPRESSION)}, not {event_compression!r}")
        self._event_filter = EVENT_COMPRESSION[event_compression]
        if not self.path.parent.exists():
            raise DataError(self.path.parent, "output folder does not exist")
        if not os.access(self.path.parent, os.W_OK):
            raise DataError(self.path.parent, "output folder is not writable")
        self.tmp_path = self.path.with_name(self.path.name + ".partial")
        self.calib = calib
        self._sizes: dict[str, tuple[int, int]] = {}
        if calib is not None:
            self._sizes.update({k: (c.width, c.height) for k, c in calib.cameras.items()})
        if sensor_sizes:
            self._sizes.update({camera_key(k): tuple(v) for k, v in sensor_sizes.items()})
        self._file = h5py.File(self.tmp_path, "w")
        self._file.attrs["format"] = FORMAT_NAME
        self._file.attrs["format_version"] = FORMAT_VERSION
        self._file.attrs["meta"] = json.dumps(meta or {})
        self._last_t: dict[str, int] = {}
        self._ms_index: dict[str, list[np.ndarray]] = {}
        self._t0_ms: dict[str, int] = {}
        self._next_k: dict[str, int] = {}
        self._count: dict[str, int] = {}
        self._closed = False

    # -- events -------------------------------------------------------------------------
    def add_events(self, cam: str | int, events: EventArray) -> None:
        """Append a chunk of events of camera ``cam`` (must continue the stream's time order)."""
        cam = camera_key(cam)
        if cam not in self._sizes:
            raise DataError(self.path, f"sensor size of {cam} unknown: give a calibration or sensor_sizes for it")
        width, height = self._sizes[cam]
        check_events(events, width, height, path=self.path, field=f"/events/{cam}", previous_t=self._last_t.get(cam))
        if len(events) == 0:
            return
        group = self._file.require_group(f"events/{cam}")
        if "t" not in group:
            group.attrs["width"], group.attrs["height"] = width, height
            for name, dtype in (("t", np.int64), ("x", np.uint16), ("y", np.uint16), ("p", np.int8)):
                group.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(EVENT_CHUNK,), **self._event_filter)
            self._t0_ms[cam] = int(events.t[0]) // 1000
            self._next_k[cam] = 0
            self._ms_index[cam] = []
            self._count[cam] = 0
        offset = self._count[cam]
        n = len(events)
        for name in ("t", "x", "y", "p"):
            ds = group[name]
            ds.resize((offset + n,))
            ds[offset:] = getattr(events, name)
        # ms boundaries that this chunk settles: every (t0_ms + k) ms up to its last event.
        k_last = int(events.t[-1]) // 1000 - self._t0_ms[cam]
        ks = np.arange(self._next_k[cam], k_last + 1, dtype=np.int64)
        if len(ks):
            bounds = (self._t0_ms[cam] + ks) * 1000
            self._ms_index[cam].append(offset + np.searchsorted(events.t, bounds, side="left"))
            self._next_k[cam] = k_last + 1
        self._count[cam] = offset + n
        self._last_t[cam] = int(events.t[-1])

    def add_triggers(self, cam: str | int, t: np.ndarray, p: np.ndarray) -> None:
        """Write the external-trigger events of ``cam`` (whole, sorted µs; p 1 = rising)."""
        cam = camera_key(cam)
        check_sorted_times(t, path=self.path, field=f"/triggers/{cam}/t")
        g = self._file.require_group(f"triggers/{cam}")
        g.create_dataset("t", data=np.asarray(t, np.int64))
        g.create_dataset("p", data=np.asarray(p, np.int8))

    # -- small streams ------------------------------------------------------------------
    def set_imu(self, imu: ImuSamples) -> None:
        check_sorted_times(imu.t, path=self.path, field="/imu/t", strict=True)
        g = self._file.require_group("imu")
        g.create_dataset("t", data=imu.t)
        g.create_dataset("gyro", data=imu.gyro)
        g.create_dataset("acc", data=imu.acc)

    def set_gt(self, gt: PoseSamples) -> None:
        check_sorted_times(gt.t, path=self.path, field="/gt/t", strict=True)
        norms = np.linalg.norm(gt.pose[:, 3:], axis=1)
        if len(norms) and np.max(np.abs(norms - 1.0)) > 1e-3:
            raise DataError(self.path, f"/gt/pose quaternions must be unit length (found norm {norms[np.argmax(np.abs(norms - 1))]:.4f})")
        g = self._file.require_group("gt")
        g.create_dataset("t", data=gt.t)
        g.create_dataset("pose", data=gt.pose)

    def add_frames(self, cam: str | int, t: np.ndarray, images: np.ndarray, *, kind: str = "frames") -> None:
        """Append frames (``kind="frames"``, uint8 (N,H,W)) or depth maps (``kind="depth"``, float32 metres)."""
        cam = camera_key(cam)
        if kind not in ("frames", "depth"):
            raise ValueError(f"kind must be 'frames' or 'depth', not {kind!r}")
        name, dtype = ("image", np.uint8) if kind == "frames" else ("depth", np.float32)
        t = np.atleast_1d(np.asarray(t, np.int64))
        images = np.asarray(images, dtype=dtype)
        if images.ndim == 2:
            images = images[None]
        if images.shape[0] != len(t):
            raise DataError(self.path, f"/{kind}/{cam}: {len(t)} timestamps for {images.shape[0]} images")
        g = self._file.require_group(f"{kind}/{cam}")
        if "t" not in g:
            h, w = images.shape[1:]
            g.create_dataset("t", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1024,))
            g.create_dataset(name, shape=(0, h, w), maxshape=(None, h, w), dtype=dtype, chunks=(1, h, w), **_COMPRESSION)
        prev = g["t"][-1] if len(g["t"]) else None
        check_sorted_times(np.concatenate([[prev], t]) if prev is not None else t, path=self.path, field=f"/{kind}/{cam}/t")
        n0 = len(g["t"])
        g["t"].resize((n0 + len(t),))
        g["t"][n0:] = t
        g[name].resize((n0 + len(t),) + g[name].shape[1:])
        g[name][n0:] = images

    # -- finish -------------------------------------------------------------------------
    def close(self) -> Path:
        """Finish indices and calibration, close, and rename to the final path."""
        if self._closed:
            return self.path
        for cam, parts in self._ms_index.items():
            idx = np.concatenate(parts + [np.array([self._count[cam]], np.int64)])
            ds = self._file[f"events/{cam}"].create_dataset("ms_to_idx", data=idx)
            ds.attrs["t0_ms"] = self._t0_ms[cam]
        for cam, (w, h) in self._sizes.items():
            if f"events/{cam}" not in self._file:  # a camera that saw no events still has a size
                g = self._file.require_group(f"events/{cam}")
                g.attrs["width"], g.attrs["height"] = w, h
        if self.calib is not None:
            self._file.require_group("calib").attrs["json"] = self.calib.to_json()
        self._file.close()
        os.replace(self.tmp_path, self.path)
        self._closed = True
        return self.path

    def abort(self) -> None:
        """Discard everything written so far."""
        if not self._closed:
            self._file.close()
            self.tmp_path.unlink(missing_ok=True)
            self._closed = True

    def __enter__(self) -> "SequenceWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


class Sequence:
    """Read-only, streaming access to a canonical sequence.

    Nothing is loaded at open; :meth:`events` reads only the requested time range, found
    through the per-millisecond index.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        if not self.path.exists():
            raise DataError(self.path, "no such file")
        try:
            self._file = h5py.File(self.path, "r")
        except OSError as exc:
            raise DataError(self.path, f"not a readable HDF5 file ({exc})") from None
        fmt = self._file.attrs.get("format")
        if fmt != FORMAT_NAME:
            self._file.close()
            raise DataError(self.path, f"root attribute 'format' is {fmt!r}, expected {FORMAT_NAME!r} (convert it with `aerovis-data convert`)")
        if "events" not in self._file:
            self._file.close()
            raise DataError(self.path, "no /events group")
        self.meta = json.loads(self._file.attrs.get("meta", "{}"))

    # -- metadata -----------------------------------------------------------------------
    @property
    def cameras(self) -> list[str]:
        return sorted(self._file["events"].keys())

    def sensor_size(self, cam: str | int) -> tuple[int, int]:
        """(width, height) of camera ``cam``."""
        g = self._group(cam)
        return int(g.attrs["width"]), int(g.attrs["height"])

    @property
    def has_calib(self) -> bool:
        return "calib" in self._file and "json" in self._file["calib"].attrs

    @property
    def calib(self) -> RigCalibration:
        if not self.has_calib:
            raise DataError(self.path, "no /calib (attribute 'json'): this sequence was converted without calibration")
        return RigCalibration.from_json(self._file["calib"].attrs["json"], path=self.path)

    def num_events(self, cam: str | int) -> int:
        g = self._group(cam)
        return int(g["t"].shape[0]) if "t" in g else 0

    def time_range(self, cam: str | int) -> tuple[int, int] | None:
        """(first, last) event timestamp in µs, or None without events."""
        g = self._group(cam)
        if "t" not in g or g["t"].shape[0] == 0:
            return None
        return int(g["t"][0]), int(g["t"][-1])

    # -- events -------------------------------------------------------------------------
    def index_at(self, cam: str | int, t_us: int) -> int:
        """Index of the first event with ``t >= t_us`` (so events before ``t_us`` are ``[0, index)``)."""
        g = self._group(cam)
        if "t" not in g:
            return 0
        idx = g["ms_to_idx"]
        t0_ms = int(idx.attrs["t0_ms"])
        k = t_us // 1000 - t0_ms  # t_us lies in millisecond t0_ms + k
        n = g["t"].shape[0]
        if k < 0:
            return 0
        if k >= len(idx) - 1:
            return n
        i0, i1 = int(idx[k]), int(idx[k + 1])
        return i0 + int(np.searchsorted(g["t"][i0:i1], t_us, side="left"))

    def events_by_index(self, cam: str | int, start: int, stop: int) -> EventArray:
        g = self._group(cam)
        if "t" not in g:
            return EventArray.empty()
        sl = slice(max(start, 0), max(stop, 0))
        return EventArray(g["t"][sl], g["x"][sl], g["y"][sl], g["p"][sl])

    def events(self, cam: str | int, t_start_us: int | None = None, t_end_us: int | None = None) -> EventArray:
        """Events with ``t_start_us <= t < t_end_us`` (whole stream when both are None)."""
        i0 = 0 if t_start_us is None else self.index_at(cam, t_start_us)
        i1 = self.num_events(cam) if t_end_us is None else self.index_at(cam, t_end_us)
        return self.events_by_index(cam, i0, i1)

    def iter_events(self, cam: str | int, chunk_events: int = 1 << 20, t_start_us=None, t_end_us=None) -> Iterator[EventArray]:
        """Stream the events of ``cam`` in chunks of at most ``chunk_events``."""
        i0 = 0 if t_start_us is None else self.index_at(cam, t_start_us)
        i1 = self.num_events(cam) if t_end_us is None else self.index_at(cam, t_end_us)
        for s in range(i0, i1, chunk_events):
            yield self.events_by_index(cam, s, min(s + chunk_events, i1))

    def triggers(self, cam: str | int) -> tuple[np.ndarray, np.ndarray] | None:
        key = f"triggers/{camera_key(cam)}"
        if key not in self._file:
            return None
        return self._file[key]["t"][:], self._file[key]["p"][:]

    # -- other streams --------------------------------------------------------------------
    @property
    def imu(self) -> ImuSamples | None:
        if "imu" not in self._file:
            return None
        g = self._file["imu"]
        return ImuSamples(g["t"][:], g["gyro"][:], g["acc"][:])

    @property
    def gt(self) -> PoseSamples | None:
        if "gt" not in self._file:
            return None
        g = self._file["gt"]
        return PoseSamples(g["t"][:], g["pose"][:])

    def frame_times(self, cam: str | int, kind: str = "frames") -> np.ndarray | None:
        key = f"{kind}/{camera_key(cam)}"
        return self._file[key]["t"][:] if key in self._file else None

    def frame(self, cam: str | int, index: int, kind: str = "frames") -> np.ndarray:
        """One frame (uint8 (H,W)) or depth map (float32 (H,W) metres, ``kind="depth"``)."""
        g = self._file[f"{kind}/{camera_key(cam)}"]
        return g["image" if kind == "frames" else "depth"][index]

    def event_compression(self, cam: str | int) -> str | None:
        """The filter of ``cam``'s event timestamps: a key of :data:`EVENT_COMPRESSION` when it is
        one of those, else HDF5's filter names joined by ``+``; None when uncompressed or eventless."""
        g = self._group(cam)
        if "t" not in g:
            return None
        pipeline = [(code, name) for code, name in dataset_filters(g["t"])
                    if code not in (h5py.h5z.FILTER_SHUFFLE, h5py.h5z.FILTER_FLETCHER32)]
        if not pipeline:
            return None
        if len(pipeline) == 1 and pipeline[0][0] in _EVENT_COMPRESSION_FILTER:
            return _EVENT_COMPRESSION_FILTER[pipeline[0][0]]
        return "+".join(name or str(code) for code, name in pipeline)

    def summary(self) -> dict:
        """JSON-ready overview: cameras, sizes, event counts, time ranges and event compression, IMU and GT counts."""
        cams = {}
        for cam in self.cameras:
            w, h = self.sensor_size(cam)
            tr = self.time_range(cam)
            cams[cam] = {"width": w, "height": h, "events": self.num_events(cam),
                         "t_first_us": tr[0] if tr else None, "t_last_us": tr[1] if tr else None,
                         "event_compression": self.event_compression(cam)}
            ft = self.frame_times(cam)
            if ft is not None:
                cams[cam]["frames"] = int(len(ft))
            dt = self.frame_times(cam, "depth")
            if dt is not None:
                cams[cam]["depth"] = int(len(dt))
        return {
            "path": str(self.path),
            "format": FORMAT_NAME,
            "cameras": cams,
            "imu": int(self._file["imu/t"].shape[0]) if "imu" in self._file else 0,
            "gt": int(self._file["gt/t"].shape[0]) if "gt" in self._file else 0,
            "calibrated": self.has_calib,
        }

    def _group(self, cam: str | int) -> h5py.Group:
        key = camera_key(cam)
        if key not in self._file["events"]:
            raise DataError(self.path, f"no camera {key!r}; cameras are {self.cameras}")
        return self._file["events"][key]

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> "Sequence":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
