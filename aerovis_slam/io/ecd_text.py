"""Event Camera Dataset (ECD) / rpg text folders as a :class:`~aerovis_slam.io.source.Recording`.

A folder in the layout of Mueggler et al., "The Event-Camera Dataset and Simulator" (IJRR 2017)::

    events.txt        t x y p          (t seconds as a decimal string, p 0/1; -1 is read as OFF)
    imu.txt           t ax ay az gx gy gz   (m/s², rad/s, IMU frame)
    groundtruth.txt   t px py pz qx qy qz qw (metres; pose as given by the dataset's motion capture)
    calib.txt         fx fy cx cy k1 k2 p1 p2 k3
    images.txt        t images/frame_XXXXXXXX.png
    images/           the frames

Timestamps are converted from their decimal text to int64 µs exactly: the digits are read as an
integer mantissa and a power of ten, never through float64 (at 1.47e9 s a double's spacing is
0.24 µs, so ``round(float(s) * 1e6)`` is one rounding away from an off-by-one). Sub-µs digits
round half up. ``events.txt`` is streamed in blocks through a numba kernel (tens of millions of
lines per second); the small files are parsed whole.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numba
import numpy as np

from ..calib import RigCalibration
from ..errors import DataError
from ..events import EventArray
from ..measurements import ImuSamples, PoseSamples
from .calib_yaml import ECD_IMAGE_SIZE, load_ecd_calib_txt
from .source import SingleCameraRecording, register_format

FORMAT_NAME = "ecd-text"
_BLOCK_BYTES = 1 << 24  # bytes of events.txt parsed per kernel call


# ------------------------------------------------------------------------------------------
# exact decimal seconds -> µs
# ------------------------------------------------------------------------------------------
@numba.njit(cache=True, nogil=True)
def _parse_time_us(buf, i, end):
    """Parse a decimal number of seconds at ``buf[i:]``; return (µs, next index, ok)."""
    neg = False
    if i < end and (buf[i] == 45 or buf[i] == 43):  # '-' '+'
        neg = buf[i] == 45
        i += 1
    mant = np.int64(0)
    exp10 = 0  # value = mant * 10**exp10
    ndig = 0
    seen_dot = False
    round_up = False
    first_dropped = True
    while i < end:
        c = buf[i]
        if 48 <= c <= 57:
            if ndig < 18:
                mant = mant * 10 + (c - 48)
                ndig += 1 if (ndig > 0 or c != 48) else 0
                if seen_dot:
                    exp10 -= 1
            else:
                # Digits past 18 significant ones: before the point they scale, after it they
                # only matter for rounding below 1e-12 s, so only the first dropped one is kept.
                if not seen_dot:
                    exp10 += 1
                elif first_dropped:
                    round_up = c >= 53
                    first_dropped = False
        elif c == 46 and not seen_dot:  # '.'
            seen_dot = True
        else:
            break
        i += 1
    if i < end and (buf[i] == 101 or buf[i] == 69):  # 'e' 'E'
        i += 1
        eneg = False
        if i < end and (buf[i] == 45 or buf[i] == 43):
            eneg = buf[i] == 45
            i += 1
        e = 0
        nexp = 0
        while i < end and 48 <= buf[i] <= 57:
            e = e * 10 + (buf[i] - 48)
            nexp += 1
            i += 1
        if nexp == 0 or e > 30:
            return np.int64(0), i, False
        exp10 += -e if eneg else e
    s = exp10 + 6  # µs = mant * 10**s
    if s > 18:
        return np.int64(0), i, False
    if s >= 0:
        us = mant
        for _ in range(s):
            us *= 10
        if s == 0 and round_up:  # the first dropped digit sits at 0.1 µs
            us += 1
    elif -s > 18:
        us = np.int64(0)  # mant < 1e18, so the value is below 0.1 µs
    else:
        div = np.int64(1)
        for _ in range(-s):
            div *= 10
        q = mant // div
        r = mant - q * div
        us = q + (1 if 2 * r >= div else 0)  # round half up
    return (-us if neg else us), i, True


@numba.njit(cache=True, nogil=True)
def _skip_blanks(buf, i, end):
    while i < end and (buf[i] == 32 or buf[i] == 9 or buf[i] == 44 or buf[i] == 13):  # space, tab, comma, CR
        i += 1
    return i


@numba.njit(cache=True, nogil=True)
def _parse_uint(buf, i, end):
    v = np.int64(0)
    n = 0
    while i < end and 48 <= buf[i] <= 57 and n < 12:
        v = v * 10 + (buf[i] - 48)
        i += 1
        n += 1
    return v, i, n > 0


@numba.njit(cache=True, nogil=True)
def _parse_event_block(buf, out_t, out_x, out_y, out_p):
    """Parse complete lines ``t x y p`` of ``buf``.

    Returns:
        (events written, lines consumed, index of the first bad line or -1, error code).
        Codes: 1 bad time, 2 bad x, 3 bad y, 4 bad polarity, 5 trailing text.
    """
    end = len(buf)
    i = 0
    n = 0
    line = 0
    while i < end:
        j = _skip_blanks(buf, i, end)
        if j >= end:
            break
        c = buf[j]
        if c == 10 or c == 35:  # blank line or '#' comment
            while j < end and buf[j] != 10:
                j += 1
            i = j + 1
            line += 1
            continue
        t, j, ok = _parse_time_us(buf, j, end)
        if not ok or j >= end or not (buf[j] == 32 or buf[j] == 9 or buf[j] == 44):
            return n, line, line, 1
        j = _skip_blanks(buf, j, end)
        x, j, ok = _parse_uint(buf, j, end)
        if not ok or x > 65535:
            return n, line, line, 2
        j = _skip_blanks(buf, j, end)
        y, j, ok = _parse_uint(buf, j, end)
        if not ok or y > 65535:
            return n, line, line, 3
        j = _skip_blanks(buf, j, end)
        neg = False
        if j < end and (buf[j] == 45 or buf[j] == 43):
            neg = buf[j] == 45
            j += 1
        p, j, ok = _parse_uint(buf, j, end)
        if not ok or p > 1 or (neg and p != 1):
            return n, line, line, 4
        j = _skip_blanks(buf, j, end)
        if j < end and buf[j] != 10:
            return n, line, line, 5
        out_t[n] = t
        out_x[n] = x
        out_y[n] = y
        out_p[n] = 0 if neg else p  # -1 (OFF in some exports) -> 0
        n += 1
        line += 1
        i = j + 1
    return n, line, -1, 0


_EVENT_ERRORS = {1: "timestamp (expected decimal seconds)", 2: "x (expected an integer 0..65535)",
                 3: "y (expected an integer 0..65535)", 4: "polarity (expected 0, 1 or -1)",
                 5: "trailing text (expected exactly 't x y p')"}


def parse_seconds_to_us(text: str) -> int:
    """Convert a decimal string of seconds (``"1468939993.067416"``, ``"1.5e-3"``) to int µs exactly.

    Raises:
        ValueError: not a decimal number.
    """
    buf = np.frombuffer(text.strip().encode("ascii"), np.uint8)
    us, i, ok = _parse_time_us(buf, 0, len(buf))
    if not ok or i != len(buf) or len(buf) == 0:
        raise ValueError(f"not a decimal number of seconds: {text!r}")
    return int(us)


# ------------------------------------------------------------------------------------------
# the recording
# ------------------------------------------------------------------------------------------
class EcdTextRecording(SingleCameraRecording):
    """An ECD / rpg text folder (one camera, ``cam0``).

    Args:
        path: the folder holding ``events.txt``.
        sensor_size: (width, height); defaults to the DAVIS240C's 240x180 that every ECD/rpg text
            recording uses (the text files do not store it).
    """

    format_name = FORMAT_NAME

    def __init__(self, path: str | os.PathLike, sensor_size: tuple[int, int] = ECD_IMAGE_SIZE):
        super().__init__(path)
        self.events_path = self.path / "events.txt"
        if not self.events_path.is_file():
            raise DataError(self.path, "no events.txt in this folder (expected an ECD/rpg text recording)")
        self._size = (int(sensor_size[0]), int(sensor_size[1]))

    def iter_events(self, cam: str = "cam0", chunk_events: int = 1 << 20) -> Iterator[EventArray]:
        """Stream ``events.txt`` in chunks of at most ``chunk_events``, checked as it goes.

        Raises:
            DataError: a malformed line, a decreasing timestamp or a pixel outside the sensor,
                naming ``events.txt`` and the 1-based line number.
        """
        self._check_cam(cam)
        width, height = self._size
        block = max(1 << 16, min(_BLOCK_BYTES, chunk_events * 24))
        line0 = 0  # lines before the current block
        last_t = None
        carry = b""
        with open(self.events_path, "rb") as f:
            while True:
                data = f.read(block)
                eof = not data
                buf = carry + data
                if not eof:
                    cut = buf.rfind(b"\n")
                    if cut < 0:
                        carry = buf  # a line longer than the block: read on
                        continue
                    carry, buf = buf[cut + 1 :], buf[: cut + 1]
                else:
                    carry = b""
                if buf:
                    arr = np.frombuffer(buf, np.uint8)
                    cap = len(buf) // 8 + 1  # the shortest event line "0 0 0 0\n" is 8 bytes
                    t = np.empty(cap, np.int64)
                    x = np.empty(cap, np.uint16)
                    y = np.empty(cap, np.uint16)
                    p = np.empty(cap, np.int8)
                    n, nlines, bad, code = _parse_event_block(arr, t, x, y, p)
                    if bad >= 0:
                        text = buf.split(b"\n")[bad][:80].decode("ascii", "replace").rstrip()
                        raise DataError(self.events_path, f"line {line0 + bad + 1}: bad {_EVENT_ERRORS[code]}: {text!r}")
                    ev = EventArray(t[:n], x[:n], y[:n], p[:n])
                    self._check_chunk(ev, buf, line0, last_t, width, height)
                    if n:
                        last_t = int(ev.t[-1])
                    for s in range(0, n, chunk_events):
                        yield ev[s : s + chunk_events]
                    line0 += nlines
                if eof:
                    break

    def _check_chunk(self, ev: EventArray, buf: bytes, line0: int, last_t, width: int, height: int) -> None:
        if len(ev) == 0:
            return

        def line_of(k: int) -> int:
            # Event k's line, counting comment/blank lines (rare, so found by scanning only on error).
            lines = buf.split(b"\n")
            seen = -1
            for li, text in enumerate(lines):
                s = text.strip()
                if s and not s.startswith(b"#"):
                    seen += 1
                    if seen == k:
                        return line0 + li + 1
            return line0 + len(lines)

        if last_t is not None and ev.t[0] < last_t:
            raise DataError(self.events_path, f"line {line_of(0)}: timestamp {ev.t[0]} µs is before the previous event's {last_t} µs (expected sorted)")
        dec = np.flatnonzero(np.diff(ev.t) < 0)
        if len(dec):
            k = int(dec[0]) + 1
            raise DataError(self.events_path, f"line {line_of(k)}: timestamp {ev.t[k]} µs is before the previous event's {ev.t[k - 1]} µs (expected sorted)")
        out = np.flatnonzero((ev.x >= width) | (ev.y >= height))
        if len(out):
            k = int(out[0])
            raise DataError(self.events_path, f"line {line_of(k)}: pixel ({ev.x[k]}, {ev.y[k]}) is outside the {width}x{height} sensor")

    # -- small streams --------------------------------------------------------------------
    def imu(self) -> ImuSamples | None:
        """``imu.txt``: ``t ax ay az gx gy gz`` (acc first, as the ECD documents it)."""
        path = self.path / "imu.txt"
        if not path.is_file():
            return None
        t, v = _read_table(path, 6, "t ax ay az gx gy gz")
        _check_increasing(path, t)
        return ImuSamples(t, gyro=v[:, 3:6], acc=v[:, 0:3])

    def gt(self) -> PoseSamples | None:
        """``groundtruth.txt``: ``t px py pz qx qy qz qw`` as stored (the dataset's mocap pose)."""
        path = self.path / "groundtruth.txt"
        if not path.is_file():
            return None
        t, v = _read_table(path, 7, "t px py pz qx qy qz qw")
        _check_increasing(path, t)
        norms = np.linalg.norm(v[:, 3:], axis=1)
        bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-3)
        if len(bad):
            raise DataError(path, f"row {int(bad[0]) + 1}: quaternion norm {norms[bad[0]]:.4f}, expected unit length")
        return PoseSamples(t, v)

    def calibration(self) -> RigCalibration | None:
        path = self.path / "calib.txt"
        return load_ecd_calib_txt(path, self._size) if path.is_file() else None

    def iter_frames(self, cam: str = "cam0") -> Iterator[tuple[int, np.ndarray]]:
        """Frames listed in ``images.txt`` (``t relative/path.png``), as uint8 grayscale."""
        import cv2

        self._check_cam(cam)
        path = self.path / "images.txt"
        if not path.is_file():
            return
        for lineno, t, name in _read_image_list(path):
            img_path = self.path / name
            img = cv2.imread(str(img_path), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise DataError(path, f"line {lineno}: cannot read image {img_path}")
            yield t, img


def _read_table(path: Path, ncols: int, layout: str) -> tuple[np.ndarray, np.ndarray]:
    """Parse ``t v1 .. vN`` lines: t exact µs, values float64. Blank and ``#`` lines are skipped."""
    ts: list[int] = []
    vals: list[list[float]] = []
    with open(path, encoding="ascii", errors="replace") as f:
        for lineno, line in enumerate(f, 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.replace(",", " ").split()
            if len(parts) != ncols + 1:
                raise DataError(path, f"line {lineno}: {len(parts)} columns, expected {ncols + 1} ({layout})")
            try:
                ts.append(parse_seconds_to_us(parts[0]))
                vals.append([float(v) for v in parts[1:]])
            except ValueError:
                raise DataError(path, f"line {lineno}: expected numbers ({layout}), got {s[:80]!r}") from None
    return np.asarray(ts, np.int64), np.asarray(vals, np.float64).reshape(-1, ncols)


def _check_increasing(path: Path, t: np.ndarray) -> None:
    bad = np.flatnonzero(np.diff(t) <= 0)
    if len(bad):
        i = int(bad[0]) + 1
        raise DataError(path, f"data row {i + 1}: timestamp {t[i]} µs does not follow {t[i - 1]} µs (expected strictly increasing)")


def _read_image_list(path: Path) -> list[tuple[int, int, str]]:
    out = []
    with open(path, encoding="utf-8") as f:
        for lineno, line in enumerate(f, 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.split()
            if len(parts) != 2:
                raise DataError(path, f"line {lineno}: expected 't path', got {s[:80]!r}")
            try:
                out.append((lineno, parse_seconds_to_us(parts[0]), parts[1]))
            except ValueError:
                raise DataError(path, f"line {lineno}: bad timestamp {parts[0]!r} (expected decimal seconds)") from None
    return out


def _probe(path: Path) -> bool:
    return path.is_dir() and (path / "events.txt").is_file()


register_format(FORMAT_NAME, _probe, EcdTextRecording)
