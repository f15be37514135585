"""Prophesee ``.raw`` files (EVT 2.0 / EVT 3.0) as a :class:`~aerovis_slam.io.source.Recording`.

A RAW file is an ASCII header of ``% key value`` lines followed by the binary event stream.
Header variants seen in the wild::

    % evt 2.0                                  (older Metavision, e.g. Gen3 cameras)
    % format EVT3;height=720;width=1280        (Metavision >= 3)
    % geometry 640x480
    % Width 640 / % Height 480
    % end                                      (optional end-of-header marker)

The body is streamed in chunks through :mod:`~aerovis_slam.io.prophesee_codecs`, so a
multi-GB file never sits in memory. Timestamps are the sensor's µs clock, unwrapped across
its rollovers. The single camera is ``cam0``.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..events import EventArray
from .prophesee_codecs import CodecError, DecodedEvents, make_decoder, regroup_events
from .source import SingleCameraRecording, register_format

__all__ = ["PropheseeRawRecording", "PropheseeRawHeader", "read_raw_header"]

# Geometry of sensors whose older RAW headers name only the HAL plugin, not the size.
_PLUGIN_GEOMETRY = (
    ("gen31", (640, 480)),
    ("gen3", (640, 480)),
    ("gen41", (1280, 720)),
    ("gen4", (1280, 720)),
    ("imx636", (1280, 720)),
    ("evk4", (1280, 720)),
    ("genx320", (320, 320)),
    ("imx8", (320, 320)),
)

_MAX_HEADER_BYTES = 1 << 20


class PropheseeRawHeader:
    """The parsed ASCII header of a RAW file.

    Attributes:
        fields: header key (lower-cased) -> value string, in file order.
        encoding: ``"evt2"`` or ``"evt3"``.
        width, height: sensor size in pixels.
        body_offset: byte offset where the binary stream starts.
    """

    def __init__(self, fields: dict[str, str], encoding: str, width: int, height: int, body_offset: int):
        self.fields, self.encoding = fields, encoding
        self.width, self.height, self.body_offset = width, height, body_offset


def read_raw_header(path: str | Path) -> PropheseeRawHeader:
    """Parse the ``%`` header of a RAW file.

    Raises:
        DataError: no ``%`` header, an event format other than EVT 2.0/3.0, or no geometry.
    """
    path = Path(path)
    fields: dict[str, str] = {}
    with open(path, "rb") as f:
        offset = 0
        while True:
            if offset > _MAX_HEADER_BYTES:
                raise DataError(path, f"header: no end of the '%' header within {_MAX_HEADER_BYTES} bytes")
            first = f.read(1)
            if first != b"%":
                break
            line = f.readline()
            offset += 1 + len(line)
            text = line.decode("ascii", errors="replace").strip()
            if text == "end":
                break
            key, _, value = text.partition(" ")
            if key:
                fields[key.lower()] = value.strip()
    if offset == 0:
        raise DataError(path, "header: a Prophesee RAW file starts with '%' header lines; found none")

    fmt = fields.get("format", "")
    evt = fields.get("evt", "")
    kind = (fmt.split(";")[0] if fmt else evt).upper().replace(" ", "").replace(".", "")
    if kind in ("EVT2", "20", "2"):
        encoding = "evt2"
    elif kind in ("EVT3", "30", "3"):
        encoding = "evt3"
    elif kind:
        raise DataError(path, f"header: event format {fmt or evt!r} is not supported (expected EVT 2.0 or EVT 3.0)")
    else:
        raise DataError(path, "header: no event format ('% evt 2.0' / '% format EVT3;...') found")

    width = height = None
    opts = dict(kv.split("=", 1) for kv in fmt.split(";")[1:] if "=" in kv)
    if "width" in opts and "height" in opts:
        width, height = int(opts["width"]), int(opts["height"])
    elif "geometry" in fields:
        m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", fields["geometry"])
        if not m:
            raise DataError(path, f"header: geometry {fields['geometry']!r} is not WIDTHxHEIGHT")
        width, height = int(m.group(1)), int(m.group(2))
    elif "width" in fields and "height" in fields:
        width, height = int(fields["width"]), int(fields["height"])
    else:
        plugin = (fields.get("plugin_name", "") + " " + fields.get("camera_integrator_name", "")).lower()
        for key, size in _PLUGIN_GEOMETRY:
            if key in plugin:
                width, height = size
                break
    if width is None or height is None:
        raise DataError(path, "header: no sensor geometry ('% geometry WxH', '% format ...;width=..;height=..' "
                        "or '% Width'/'% Height') and an unknown plugin_name")
    return PropheseeRawHeader(fields, encoding, width, height, offset)


class PropheseeRawRecording(SingleCameraRecording):
    """A Prophesee RAW file (EVT 2.0 or EVT 3.0), single camera ``cam0``.

    Args:
        path: the ``.raw`` file.
        read_bytes: bytes read per chunk from disk.
    """

    def __init__(self, path, read_bytes: int = 1 << 22):
        super().__init__(path)
        self.header = read_raw_header(self.path)
        self._size = (self.header.width, self.header.height)
        self.format_name = f"prophesee-raw-{self.header.encoding}"
        self.read_bytes = int(read_bytes)
        self._triggers: tuple[np.ndarray, np.ndarray] | None = None
        self._scanned = False

    def iter_decoded(self) -> Iterator[DecodedEvents]:
        """Decode the body chunk by chunk: sensor-time (µs) CD and trigger events.

        Raises:
            DataError: the body ends inside a word (truncated file).
        """
        dec = make_decoder(self.header.encoding, self.header.width, self.header.height)
        with open(self.path, "rb") as f:
            f.seek(self.header.body_offset)
            while True:
                buf = f.read(self.read_bytes)
                if not buf:
                    break
                yield dec.decode(buf)
        try:
            dec.finish()
        except CodecError as exc:
            raise DataError(self.path, f"event data after the header (byte {self.header.body_offset}): {exc}") from None

    def iter_events(self, cam: str, chunk_events: int = 1 << 20) -> Iterator[EventArray]:
        """Stream CD events of ``cam0`` in chunks of about ``chunk_events`` (µs timestamps)."""
        self._check_cam(cam)
        trig: list[DecodedEvents] = []
        yield from regroup_events(self.iter_decoded(), chunk_events, trig)
        self._set_triggers(trig)

    def _set_triggers(self, parts: list[DecodedEvents]) -> None:
        d = DecodedEvents.concatenate(parts)
        self._triggers = (d.trig_t, d.trig_edge) if len(d.trig_t) else None
        self._scanned = True

    def triggers(self, cam: str) -> tuple[np.ndarray, np.ndarray] | None:
        """External triggers ``(t µs int64, edge int8 1 = rising)``, or None if the file has none."""
        self._check_cam(cam)
        if not self._scanned:
            self._set_triggers([d for d in self.iter_decoded() if len(d.trig_t)])
        return self._triggers

    def info(self) -> dict:
        """Summary from one streaming pass (no events are kept)."""
        n, first, last, trig = 0, None, None, []
        for d in self.iter_decoded():
            if len(d):
                first = int(d.t[0]) if first is None else first
                last = int(d.t[-1])
                n += len(d)
            if len(d.trig_t):
                trig.append(d)
        self._set_triggers(trig)
        cam = {"width": self.header.width, "height": self.header.height, "events": n,
               "t_first_us": first, "t_last_us": last}
        if self._triggers is not None:
            cam["triggers"] = int(len(self._triggers[0]))
        return {"path": str(self.path), "format": self.format_name, "cameras": {"cam0": cam},
                "imu": 0, "gt": 0, "calibrated": False}


def _probe(path: Path) -> bool:
    if not path.is_file() or path.suffix.lower() != ".raw":
        return False
    try:
        with open(path, "rb") as f:
            return f.read(1) == b"%"
    except OSError:
        return False


register_format("prophesee-raw", _probe, PropheseeRawRecording)
