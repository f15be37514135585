"""Streaming, vectorised decoders for Prophesee EVT 2.0 and EVT 3.0 event streams.

Both formats are documented publicly by Prophesee ("EVT 2.0 format", "EVT 3.0 format" in the
Metavision docs). The decoders here are numpy-only (no per-event Python loop) and *streamable*:
a decoder object carries the format's state (time high bits and their rollover count, current
row, vector base column and polarity, a partial trailing word) from one :meth:`decode` call to
the next, so a multi-GB file or a sequence of ROS packets can be fed in arbitrary byte chunks and
the result is identical to decoding the whole stream at once.

Word layouts (little-endian; the 4 most significant bits are the word type):

EVT 2.0, 32-bit words::

    CD_OFF (0x0) / CD_ON (0x1)  [27:22] time LSB (6 bits)  [21:11] x  [10:0] y
    EVT_TIME_HIGH (0x8)         [27:0] time bits 33..6
    EXT_TRIGGER (0xA)           [27:22] time LSB  [12:8] channel id  [0] edge (1 = rising)
    OTHERS (0xE), CONTINUED (0xF): ignored

EVT 3.0, 16-bit words::

    EVT_ADDR_Y (0x0)    [11] system type  [10:0] y          sets the current row
    EVT_ADDR_X (0x2)    [11] polarity     [10:0] x          one CD event at (x, current row)
    VECT_BASE_X (0x3)   [11] polarity     [10:0] x          sets base column and polarity
    VECT_12 (0x4)       [11:0] valid mask                   events at base+i, then base += 12
    VECT_8 (0x5)        [7:0] valid mask                    events at base+i, then base += 8
    EVT_TIME_LOW (0x6)  [11:0] time bits 11..0
    EVT_TIME_HIGH (0x8) [11:0] time bits 23..12
    EXT_TRIGGER (0xA)   [11:8] channel id  [0] edge (1 = rising)
    CONTINUED_4 (0x7), padding (0x9), OTHERS (0xE), CONTINUED_12 (0xF): ignored

Times are the sensor's native unit, microseconds, and *unwrapped*: the 34-bit (EVT 2.0) or
24-bit (EVT 3.0) sensor clock rolls over (after ~4.8 h or ~16.8 s), and every rollover of the
time-high field adds one period, so decoded timestamps keep increasing.

Events before the stream's time is known are dropped: EVT 2.0 needs one EVT_TIME_HIGH; EVT 3.0
needs an EVT_TIME_HIGH followed by an EVT_TIME_LOW (the rule of Metavision and of the ROS
``event_camera_codecs``, whose outputs the tests use as oracles). With a sensor geometry given,
CD events outside it are dropped and counted, as ``event_camera_codecs`` does.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..events import EventArray

__all__ = [
    "CodecError",
    "DecodedEvents",
    "Evt2Decoder",
    "Evt3Decoder",
    "decode_evt2",
    "decode_evt3",
    "make_decoder",
]


class CodecError(ValueError):
    """Malformed codec input (e.g. a stream that ends inside a word). Readers re-raise it as
    :class:`~aerovis_slam.errors.DataError` naming the file."""


@dataclass
class DecodedEvents:
    """The output of one decode call, in stream order.

    Attributes:
        t: (N,) int64 CD timestamps in the sensor's unit (µs for EVT 2.0/3.0), unwrapped.
        x: (N,) uint16 columns.
        y: (N,) uint16 rows.
        p: (N,) int8 polarity, 0 = OFF, 1 = ON.
        trig_t: (M,) int64 external-trigger timestamps, same unit as ``t``.
        trig_id: (M,) uint8 trigger channel.
        trig_edge: (M,) int8 edge, 1 = rising, 0 = falling.
    """

    t: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    x: np.ndarray = field(default_factory=lambda: np.empty(0, np.uint16))
    y: np.ndarray = field(default_factory=lambda: np.empty(0, np.uint16))
    p: np.ndarray = field(default_factory=lambda: np.empty(0, np.int8))
    trig_t: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    trig_id: np.ndarray = field(default_factory=lambda: np.empty(0, np.uint8))
    trig_edge: np.ndarray = field(default_factory=lambda: np.empty(0, np.int8))

    def __len__(self) -> int:
        return len(self.t)

    def events(self, offset: int = 0, divisor: int = 1) -> EventArray:
        """CD events as an :class:`EventArray` with ``t = (t + offset) // divisor``.

        Args:
            offset: added to the raw timestamps first (same unit as ``t``).
            divisor: e.g. 1000 to turn nanoseconds into µs (floor division).
        """
        t = self.t if (offset == 0 and divisor == 1) else (self.t + offset) // divisor
        return EventArray(t, self.x, self.y, self.p)

    @classmethod
    def concatenate(cls, parts: list["DecodedEvents"]) -> "DecodedEvents":
        if not parts:
            return cls()
        return cls(*(np.concatenate([getattr(d, f) for d in parts]) for f in (
            "t", "x", "y", "p", "trig_t", "trig_id", "trig_edge")))


def _last_setter(setters: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """For each sorted query word index, the position in ``setters`` (sorted word indices of
    state-setting words) of the last setter at or before it, or -1 if none: a forward fill."""
    return np.searchsorted(setters, queries, side="right") - 1


def _unwrap(raw: np.ndarray, last_raw: int | None, loops: int, period_bits: int) -> tuple[np.ndarray, int]:
    """Count rollovers of a time-high field.

    A decrease of more than half the field's range is a rollover; a smaller decrease is a glitch
    of the sensor clock (seen in real data) and is kept as is, without a rollover.

    Args:
        raw: (K,) raw time-high values in stream order.
        last_raw: the value preceding ``raw[0]`` (from the previous chunk), or None.
        loops: rollovers counted before ``raw[0]``.
        period_bits: width of the field in bits.

    Returns:
        (K,) int64 rollover counts for each value, and the count after the last one.
    """
    v = raw.astype(np.int64)
    prev = np.empty_like(v)
    if len(v):
        prev[0] = v[0] if last_raw is None else last_raw
        prev[1:] = v[:-1]
    wrapped = (prev - v) > (1 << (period_bits - 1))
    counts = loops + np.cumsum(wrapped, dtype=np.int64)
    return counts, int(counts[-1]) if len(counts) else loops


def regroup_events(decoded, chunk_events: int, triggers: list, divisor: int = 1):
    """Regroup decoder outputs (one per packet or byte chunk) into :class:`EventArray` chunks of about
    ``chunk_events`` CD events, ``t // divisor``; parts holding triggers are appended to ``triggers``."""
    pending: list[DecodedEvents] = []
    n_pending = 0
    for d in decoded:
        if len(d.trig_t):
            triggers.append(d)
        if len(d):
            pending.append(d)
            n_pending += len(d)
        if n_pending >= chunk_events:
            yield DecodedEvents.concatenate(pending).events(0, divisor)
            pending, n_pending = [], 0
    if pending:
        yield DecodedEvents.concatenate(pending).events(0, divisor)


class _SensorClip:
    """Drops (and counts) CD events outside an optional sensor geometry; shared by every decoder."""

    def __init__(self, width: int | None = None, height: int | None = None):
        self.width, self.height = width, height
        #: CD events dropped for lying outside the given sensor geometry
        self.n_out_of_bounds = 0

    def _clip(self, t, x, y, p) -> tuple:
        if self.width is None or self.height is None or len(x) == 0:
            return t, x, y, p
        ok = (x < self.width) & (y < self.height)
        if ok.all():
            return t, x, y, p
        self.n_out_of_bounds += int(len(ok) - np.count_nonzero(ok))
        return t[ok], x[ok], y[ok], p[ok]


class _StreamDecoder(_SensorClip):
    """Bytes-to-words plumbing shared by both decoders."""

    word_bytes = 4

    def __init__(self, width: int | None = None, height: int | None = None):
        super().__init__(width, height)
        self._pending = b""
        #: CD events dropped because they came before the stream's time was known
        self.n_before_time = 0
        #: words processed so far
        self.n_words = 0

    @property
    def pending_bytes(self) -> int:
        """Bytes of an incomplete trailing word waiting for the next chunk."""
        return len(self._pending)

    def _words(self, data, dtype) -> np.ndarray:
        buf = memoryview(data).cast("B") if not isinstance(data, np.ndarray) else data.view(np.uint8).reshape(-1)
        if self._pending:
            buf = np.concatenate([np.frombuffer(self._pending, np.uint8), np.frombuffer(buf, np.uint8)])
        n = len(buf) // self.word_bytes
        cut = n * self.word_bytes
        self._pending = bytes(buf[cut:])
        self.n_words += n
        return np.frombuffer(buf, dtype, count=n)

    def finish(self) -> None:
        """Declare the end of the stream.

        Raises:
            CodecError: the stream ended inside a word (a truncated file).
        """
        if self._pending:
            n = len(self._pending)
            self._pending = b""
            raise CodecError(
                f"stream ends with {n} byte(s) of an incomplete {self.word_bytes}-byte word (truncated data)")


class Evt2Decoder(_StreamDecoder):
    """Streaming EVT 2.0 decoder. Feed byte chunks to :meth:`decode` in order.

    Args:
        width, height: sensor size; CD events outside it are dropped (None keeps all).

    State kept across chunks: the unwrapped time-high (with its rollover count) and a partial
    trailing word.
    """

    word_bytes = 4
    TIME_BITS = 34

    def __init__(self, width: int | None = None, height: int | None = None):
        super().__init__(width, height)
        self._th_raw: int | None = None  # last raw 28-bit EVT_TIME_HIGH value
        self._loops = 0  # rollovers of the 28-bit field so far

    @property
    def time_high(self) -> int | None:
        """Current unwrapped time high (µs, multiple of 64), or None before the first one."""
        if self._th_raw is None:
            return None
        return ((self._loops << 28) | self._th_raw) << 6

    def decode(self, data) -> DecodedEvents:
        """Decode the next chunk of the stream (any length; a partial word waits for the next).

        Args:
            data: bytes-like or uint8 array.

        Returns:
            The CD and trigger events completed by this chunk.
        """
        w = self._words(data, "<u4")
        if len(w) == 0:
            return DecodedEvents()
        typ = w >> 28
        th_idx = np.flatnonzero(typ == 0x8)
        th_raw = w[th_idx] & 0x0FFFFFFF
        loops, end_loops = _unwrap(th_raw, self._th_raw, self._loops, 28)
        th_full = ((loops << 28) | th_raw.astype(np.int64)) << 6
        prev_th = self.time_high
        if len(th_idx):
            self._th_raw, self._loops = int(th_raw[-1]), end_loops

        def times(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            j = _last_setter(th_idx, idx)
            if prev_th is None:
                valid = j >= 0
                idx, j = idx[valid], j[valid]
                base = th_full[j] if len(j) else np.empty(0, np.int64)
            else:
                valid = None
                base = np.where(j >= 0, th_full[np.maximum(j, 0)] if len(th_full) else 0, prev_th)
            return idx, base + ((w[idx] >> 22) & 0x3F).astype(np.int64), valid

        cd_idx = np.flatnonzero(typ <= 0x1)
        n_cd = len(cd_idx)
        cd_idx, t, _ = times(cd_idx)
        self.n_before_time += n_cd - len(cd_idx)
        cw = w[cd_idx]
        x = ((cw >> 11) & 0x7FF).astype(np.uint16)
        y = (cw & 0x7FF).astype(np.uint16)
        p = (cw >> 28).astype(np.int8)
        t, x, y, p = self._clip(t, x, y, p)

        tr_idx, tr_t, _ = times(np.flatnonzero(typ == 0xA))
        tw = w[tr_idx]
        return DecodedEvents(t, x, y, p, tr_t, ((tw >> 8) & 0x1F).astype(np.uint8), (tw & 1).astype(np.int8))


# EVT 3.0 vector words: for every 12-bit mask, its popcount and the column offset of its k-th set
# bit, so that vector expansion is two table look-ups.
_MASKS = np.arange(4096, dtype=np.uint16)
_BITS = ((_MASKS[:, None] >> np.arange(12, dtype=np.uint16)) & 1).astype(bool)
_POPCOUNT = _BITS.sum(axis=1).astype(np.int64)
_NTH_BIT = np.zeros((4096, 12), np.uint16)
_rows, _cols = np.nonzero(_BITS)
_NTH_BIT[_rows, (np.cumsum(_BITS, axis=1) - 1)[_rows, _cols]] = _cols
_NTH_BIT_FLAT = _NTH_BIT.reshape(-1)
del _rows, _cols


class Evt3Decoder(_StreamDecoder):
    """Streaming EVT 3.0 decoder. Feed byte chunks to :meth:`decode` in order.

    Args:
        width, height: sensor size; CD events outside it are dropped (None keeps all).

    State kept across chunks: time high (unwrapped, with rollovers) and time low, whether the
    time is valid yet, the current row, the vector base column and polarity, and an odd
    trailing byte.
    """

    word_bytes = 2
    TIME_BITS = 24

    def __init__(self, width: int | None = None, height: int | None = None):
        super().__init__(width, height)
        self._th_raw: int | None = None
        self._loops = 0
        self._tl = 0
        self._valid = False  # an EVT_TIME_LOW has followed an EVT_TIME_HIGH
        self._y = 0
        self._base_x = 0
        self._pol = 0

    @property
    def time(self) -> int | None:
        """Current unwrapped time (µs), or None while not yet valid."""
        if not self._valid:
            return None
        return (((self._loops << 12) | self._th_raw) << 12) | self._tl

    def decode(self, data) -> DecodedEvents:
        """Decode the next chunk of the stream (any length; an odd byte waits for the next).

        Args:
            data: bytes-like or uint8 array.

        Returns:
            The CD and trigger events completed by this chunk, in stream order.
        """
        w = self._words(data, "<u2")
        if len(w) == 0:
            return DecodedEvents()
        typ = w >> 12
        pay = w & 0x0FFF

        # ---- time: forward-fill time high (unwrapped) and time low to every word
        th_idx = np.flatnonzero(typ == 0x8)
        th_raw = pay[th_idx]
        loops, end_loops = _unwrap(th_raw, self._th_raw, self._loops, 12)
        th_full = ((loops << 12) | th_raw.astype(np.int64)) << 12
        tl_idx = np.flatnonzero(typ == 0x6)
        tl_val = pay[tl_idx].astype(np.int64)
        prev_th = None if self._th_raw is None else (((self._loops << 12) | self._th_raw) << 12)
        prev_tl = self._tl

        # first word index whose events have a valid time
        if self._valid:
            valid_from = 0
        else:
            first_th = 0 if self._th_raw is not None else (int(th_idx[0]) if len(th_idx) else len(w))
            k = np.searchsorted(tl_idx, first_th, side="left")
            valid_from = int(tl_idx[k]) + 1 if k < len(tl_idx) else len(w) + 1
            self._valid = valid_from <= len(w)

        def time_at(idx: np.ndarray) -> np.ndarray:
            j = _last_setter(th_idx, idx)
            hi = np.where(j >= 0, th_full[np.maximum(j, 0)] if len(th_full) else 0,
                          prev_th if prev_th is not None else 0)
            j = _last_setter(tl_idx, idx)
            lo = np.where(j >= 0, tl_val[np.maximum(j, 0)] if len(tl_val) else 0, prev_tl)
            return hi | lo

        # ---- state of vector words: base column and polarity from the last VECT_BASE_X,
        # advanced by 12 or 8 per vector word since then
        s_idx = np.flatnonzero((typ >= 0x3) & (typ <= 0x5))
        s_typ = typ[s_idx]
        s_pay = pay[s_idx]
        inc = np.where(s_typ == 0x4, 12, np.where(s_typ == 0x5, 8, 0)).astype(np.int64)
        before = np.cumsum(inc) - inc  # increments before each S word
        is_base = s_typ == 0x3
        base_pos = np.flatnonzero(is_base)
        j = _last_setter(base_pos, np.arange(len(s_idx)))
        jj = np.maximum(j, 0)
        if len(base_pos):
            bpos = base_pos[jj]
            s_base = np.where(j >= 0, (s_pay[bpos] & 0x7FF).astype(np.int64) + before - before[bpos],
                              self._base_x + before)
            s_pol = np.where(j >= 0, (s_pay[bpos] >> 11) & 1, self._pol)
        else:
            s_base = self._base_x + before
            s_pol = np.full(len(s_idx), self._pol)

        # ---- CD events: one per EVT_ADDR_X, popcount(mask) per vector word, in word order
        ev_idx = np.flatnonzero((typ == 0x2) | (typ == 0x4) | (typ == 0x5))
        ev_typ = typ[ev_idx]
        ev_pay = pay[ev_idx]
        is_x = ev_typ == 0x2
        mask = np.where(ev_typ == 0x5, ev_pay & 0xFF, ev_pay)
        mask[is_x] = 1  # one "bit" at offset 0
        counts = _POPCOUNT[mask]
        # vector words' base/polarity: their position among the S words
        spos = np.searchsorted(s_idx, ev_idx)
        spos_c = np.minimum(spos, max(len(s_idx) - 1, 0))
        base = np.where(is_x, (ev_pay & 0x7FF).astype(np.int64), s_base[spos_c] if len(s_idx) else 0)
        pol = np.where(is_x, (ev_pay >> 11) & 1, s_pol[spos_c] if len(s_idx) else 0)
        y_idx = np.flatnonzero(typ == 0x0)
        jy = _last_setter(y_idx, ev_idx)
        yv = np.where(jy >= 0, pay[y_idx[np.maximum(jy, 0)]] & 0x7FF if len(y_idx) else 0, self._y)
        tv = time_at(ev_idx)
        if valid_from > 0:
            keep = ev_idx >= valid_from
            n_before = int(counts[~keep].sum())
            self.n_before_time += n_before
            counts = np.where(keep, counts, 0)

        k = np.repeat(np.arange(len(ev_idx)), counts)
        rank = np.arange(len(k)) - np.repeat(np.cumsum(counts) - counts, counts)
        x = (base[k] + _NTH_BIT_FLAT[mask[k].astype(np.int64) * 12 + rank]).astype(np.uint16)
        t = tv[k]
        y = yv[k].astype(np.uint16)
        p = pol[k].astype(np.int8)
        t, x, y, p = self._clip(t, x, y, p)

        # ---- triggers
        tr_idx = np.flatnonzero(typ == 0xA)
        tr_idx = tr_idx[tr_idx >= valid_from]
        tr_pay = pay[tr_idx]
        trig = (time_at(tr_idx), ((tr_pay >> 8) & 0xF).astype(np.uint8), (tr_pay & 1).astype(np.int8))

        # ---- carry the state to the next chunk
        if len(th_idx):
            self._th_raw, self._loops = int(th_raw[-1]), end_loops
        if len(tl_idx):
            self._tl = int(tl_val[-1])
        if len(y_idx):
            self._y = int(pay[y_idx[-1]] & 0x7FF)
        if len(s_idx):
            self._base_x = int(s_base[-1] + inc[-1])
            self._pol = int(s_pol[-1])
        return DecodedEvents(t, x, y, p, *trig)


def make_decoder(encoding: str, width: int | None = None, height: int | None = None) -> _StreamDecoder:
    """A fresh decoder for ``encoding`` (``"evt2"``/``"evt2.0"`` or ``"evt3"``/``"evt3.0"``).

    Raises:
        CodecError: unknown encoding.
    """
    key = encoding.strip().lower().replace(" ", "").replace("_", "").replace(".0", "")
    if key in ("evt2", "2"):
        return Evt2Decoder(width, height)
    if key in ("evt3", "3"):
        return Evt3Decoder(width, height)
    raise CodecError(f"unknown Prophesee encoding {encoding!r} (expected EVT 2.0 or EVT 3.0)")


def decode_evt2(data, width: int | None = None, height: int | None = None) -> DecodedEvents:
    """Decode a complete EVT 2.0 byte stream (sensor µs).

    Raises:
        CodecError: the stream ends inside a word.
    """
    dec = Evt2Decoder(width, height)
    out = dec.decode(data)
    dec.finish()
    return out


def decode_evt3(data, width: int | None = None, height: int | None = None) -> DecodedEvents:
    """Decode a complete EVT 3.0 byte stream (sensor µs).

    Raises:
        CodecError: the stream ends inside a word.
    """
    dec = Evt3Decoder(width, height)
    out = dec.decode(data)
    dec.finish()
    return out
