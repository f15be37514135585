"""Vectorised decoders for iniVation (libcaer) event packets as carried by ROS
``event_camera_msgs/msg/EventPacket`` with ``encoding: libcaer`` or ``libcaer_cmp``.

The layouts are those of the ROS ``event_camera_codecs`` package (Apache-2.0), whose decoders
define the meaning of these messages:

``libcaer``: libcaer polarity events, 8 bytes each, little-endian::

    uint32 data:  [31:17] x  [16:2] y  [1] polarity  [0] valid mark
    int32  timestamp: µs, the low 31 bits of the device clock

  sensor time (ns) = ``time_base`` + 1000 * timestamp, where the driver advances ``time_base``
  by the high bits of the device clock; a timestamp that decreases *within* a packet is a
  rollover of the 31-bit clock and adds 2^31 µs to the rest of the packet.

``libcaer_cmp``: 16-bit words, [15:12] code, [11:0] payload::

    TIME_HIGH (0) [11:0] time bits 23..12     TIME_LOW (1) [11:0] time bits 11..0
    ADDR_X (2)    [10:0] x (current column)
    ADDR_Y (3)    [11] polarity [10:0] y       one event at (current column, y)
    VECT_BASE_Y (4) [11] polarity [10:0] y     base row and polarity for VECT_8
    VECT_8 (5)    [7:0] mask                   events at (column, base + i), then base += 8

  sensor time (ns) = ``time_base`` + 1000 * time, the time restarting at 0 in every packet; the
  column, base row and polarity carry over from packet to packet.

Both produce times in nanoseconds since the epoch (the drivers put host time in ``time_base``).
"""

from __future__ import annotations

import numpy as np

from .prophesee_codecs import _NTH_BIT_FLAT, _POPCOUNT, CodecError, DecodedEvents, _last_setter, _SensorClip

__all__ = ["LibcaerDecoder", "LibcaerCmpDecoder", "ROLLOVER_US"]

#: the libcaer device clock's period: 31-bit µs timestamps
ROLLOVER_US = 1 << 31


class LibcaerDecoder(_SensorClip):
    """Decoder of ``libcaer`` packets (uncompressed libcaer polarity events).

    Packets are independent (the driver's ``time_base`` carries the clock's high part), so the
    decoder keeps no state between packets; it is a class for symmetry with the others.

    Args:
        width, height: sensor size; events outside it are dropped (None keeps all).
    """

    EVENT_BYTES = 8

    def decode_packet(self, data, time_base_ns: int) -> DecodedEvents:
        """Decode one packet.

        Args:
            data: bytes-like or uint8 array, a whole number of 8-byte events.
            time_base_ns: the packet's ``time_base`` (ns).

        Returns:
            CD events with ``t`` in nanoseconds (no triggers in this encoding).

        Raises:
            CodecError: the packet is not a whole number of events.
        """
        buf = np.frombuffer(memoryview(data).cast("B") if not isinstance(data, np.ndarray) else data.view(np.uint8).reshape(-1), np.uint8)
        if len(buf) % self.EVENT_BYTES:
            raise CodecError(f"libcaer packet of {len(buf)} bytes is not a whole number of {self.EVENT_BYTES}-byte events")
        ev = buf.view("<u4").reshape(-1, 2)
        data_w = ev[:, 0]
        ts = ev[:, 1].view("<i4").astype(np.int64)
        # a decrease of the 31-bit µs clock inside the packet is a rollover
        rolls = np.zeros(len(ts), np.int64)
        if len(ts) > 1:
            rolls[1:] = np.cumsum(ts[1:] < ts[:-1])
        t = int(time_base_ns) + (rolls * ROLLOVER_US + ts) * 1000
        x = ((data_w >> 17) & 0x7FFF).astype(np.uint16)
        y = ((data_w >> 2) & 0x7FFF).astype(np.uint16)
        p = ((data_w >> 1) & 1).astype(np.int8)
        return DecodedEvents(*self._clip(t, x, y, p))


class LibcaerCmpDecoder(_SensorClip):
    """Decoder of ``libcaer_cmp`` packets (the compressed libcaer encoding).

    Args:
        width, height: sensor size; events outside it are dropped (None keeps all).

    State kept across packets: current column, vector base row and polarity.
    """

    def __init__(self, width: int | None = None, height: int | None = None):
        super().__init__(width, height)
        self._x = 0
        self._base_y = 0
        self._pol = 0

    def decode_packet(self, data, time_base_ns: int) -> DecodedEvents:
        """Decode one packet.

        Args:
            data: bytes-like or uint8 array of 16-bit words.
            time_base_ns: the packet's ``time_base`` (ns).

        Returns:
            CD events with ``t`` in nanoseconds, in packet order.

        Raises:
            CodecError: odd byte count or an unknown word code.
        """
        buf = np.frombuffer(memoryview(data).cast("B") if not isinstance(data, np.ndarray) else data.view(np.uint8).reshape(-1), np.uint8)
        if len(buf) % 2:
            raise CodecError(f"libcaer_cmp packet of {len(buf)} bytes is not a whole number of 16-bit words")
        w = buf.view("<u2")
        code = w >> 12
        pay = w & 0x0FFF
        if len(w) and code.max() > 6:
            bad = int(code[code > 6][0])
            raise CodecError(f"libcaer_cmp packet holds unknown word code {bad} (expected 0..6)")

        def ffill(setter_mask: np.ndarray, idx: np.ndarray, values: np.ndarray, initial: int) -> np.ndarray:
            setters = np.flatnonzero(setter_mask)
            j = _last_setter(setters, idx)
            if not len(setters):
                return np.full(len(idx), initial, np.int64)
            return np.where(j >= 0, values[setters[np.maximum(j, 0)]].astype(np.int64), initial)

        ev_idx = np.flatnonzero((code == 3) | (code == 5))
        # the time restarts at zero in every packet
        hi = ffill(code == 0, ev_idx, pay, 0) << 12
        lo = ffill(code == 1, ev_idx, pay, 0)
        ex = ffill(code == 2, ev_idx, pay & 0x7FF, self._x)

        # vector state over base/vector words: base row from the last VECT_BASE_Y, + 8 per VECT_8
        s_idx = np.flatnonzero((code == 4) | (code == 5))
        s_code, s_pay = code[s_idx], pay[s_idx]
        inc = np.where(s_code == 5, 8, 0).astype(np.int64)
        before = np.cumsum(inc) - inc
        base_pos = np.flatnonzero(s_code == 4)
        j = _last_setter(base_pos, np.arange(len(s_idx)))
        if len(base_pos):
            b = base_pos[np.maximum(j, 0)]
            s_base = np.where(j >= 0, (s_pay[b] & 0x7FF).astype(np.int64) + before - before[b], self._base_y + before)
            s_pol = np.where(j >= 0, (s_pay[b] >> 11) & 1, self._pol)
        else:
            s_base = self._base_y + before
            s_pol = np.full(len(s_idx), self._pol, np.int64)

        ev_code, ev_pay = code[ev_idx], pay[ev_idx]
        is_y = ev_code == 3
        mask = np.where(is_y, 1, ev_pay & 0xFF)
        counts = _POPCOUNT[mask]
        spos = np.minimum(np.searchsorted(s_idx, ev_idx), max(len(s_idx) - 1, 0))
        base = np.where(is_y, (ev_pay & 0x7FF).astype(np.int64), s_base[spos] if len(s_idx) else 0)
        pol = np.where(is_y, (ev_pay >> 11) & 1, s_pol[spos] if len(s_idx) else 0)
        k = np.repeat(np.arange(len(ev_idx)), counts)
        rank = np.arange(len(k)) - np.repeat(np.cumsum(counts) - counts, counts)
        y = (base[k] + _NTH_BIT_FLAT[mask[k].astype(np.int64) * 12 + rank]).astype(np.uint16)
        x = ex[k].astype(np.uint16)
        p = pol[k].astype(np.int8)
        t = int(time_base_ns) + (hi[k] | lo[k]) * 1000

        if (code == 2).any():
            self._x = int(pay[np.flatnonzero(code == 2)[-1]] & 0x7FF)
        if len(s_idx):
            self._base_y = int(s_base[-1] + inc[-1])
            self._pol = int(s_pol[-1])
        return DecodedEvents(*self._clip(t, x, y, p))
