"""Prophesee EVT 2.0/3.0 codecs, libcaer codecs and RAW files.

The byte streams here come from small, independent per-event *encoders* written in this file
from the public format descriptions, and must round-trip exactly; real recordings (under
``../shared/data``) check the decoders against known counts.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest

from aerovis_slam.errors import DataError
from aerovis_slam.events import EventArray
from aerovis_slam.io.libcaer_codec import ROLLOVER_US, LibcaerCmpDecoder, LibcaerDecoder
from aerovis_slam.io.prophesee_codecs import (
    CodecError,
    DecodedEvents,
    Evt2Decoder,
    Evt3Decoder,
    decode_evt2,
    decode_evt3,
)
from aerovis_slam.io.prophesee_raw import PropheseeRawRecording, read_raw_header
from aerovis_slam.io.source import open_recording


# ----------------------------------------------------------------------------- test encoders
def encode_evt2(events, triggers=()):
    """Per-event EVT 2.0 encoder. ``events``: (t, x, y, p) sorted by t; ``triggers``: (t, id, edge).

    Returns (bytes, expected CD list, expected trigger list) in stream order."""
    items = sorted([(t, 0, x, y, p) for t, x, y, p in events] + [(t, 1, i, e, 0) for t, i, e in triggers],
                   key=lambda r: r[0])
    words, cd, tr = [], [], []
    high = None
    for t, kind, a, b, p in items:
        if (t >> 6) != high:
            high = t >> 6
            words.append((0x8 << 28) | (high & 0x0FFFFFFF))
        if kind == 0:
            words.append((p << 28) | ((t & 63) << 22) | (a << 11) | b)
            cd.append((t, a, b, p))
        else:
            words.append((0xA << 28) | ((t & 63) << 22) | (a << 8) | b)
            tr.append((t, a, b))
        if len(words) % 7 == 0:
            words.append((0xE << 28) | 0x123)  # an OTHERS word, to be ignored
    return struct.pack(f"<{len(words)}I", *words), cd, tr


def encode_evt3(events, triggers=()):
    """Per-event EVT 3.0 encoder. Groups of >= 2 events sharing (t, y, p) become a VECT_BASE_X
    followed by alternating VECT_12 / VECT_8 words; single events are EVT_ADDR_X.

    Returns (bytes, expected CD list in decoder order, expected trigger list)."""
    groups: dict = {}
    for t, x, y, p in events:
        groups.setdefault((t, y, p), []).append(x)
    items = [(t, 0, (y, p, sorted(xs))) for (t, y, p), xs in groups.items()]
    items += [(t, 1, (i, e)) for t, i, e in triggers]
    items.sort(key=lambda r: (r[0], r[1]))
    words, cd, tr = [], [], []
    hi = lo = cur_y = None
    for t, kind, data in items:
        if (t >> 12) & 0xFFF != hi:
            hi = (t >> 12) & 0xFFF
            words.append((0x8 << 12) | hi)
        if t & 0xFFF != lo:
            lo = t & 0xFFF
            words.append((0x6 << 12) | lo)
        if kind == 1:
            i, e = data
            words.append((0xA << 12) | (i << 8) | e)
            tr.append((t, i, e))
            continue
        y, p, xs = data
        if y != cur_y:
            cur_y = y
            words.append((0x0 << 12) | y)
        if len(xs) == 1:
            words.append((0x2 << 12) | (p << 11) | xs[0])
            cd.append((t, xs[0], y, p))
            continue
        base = xs[0]
        words.append((0x3 << 12) | (p << 11) | base)
        xset, use12 = set(xs), True
        while base <= xs[-1]:
            n = 12 if use12 else 8
            mask = sum(1 << k for k in range(n) if base + k in xset)
            words.append(((0x4 if use12 else 0x5) << 12) | mask)
            cd.extend((t, base + k, y, p) for k in range(n) if base + k in xset)
            base += n
            use12 = not use12
        words.append((0x7 << 12) | 0x5)  # CONTINUED_4: ignored
    return struct.pack(f"<{len(words)}H", *words), cd, tr


def _as_lists(d: DecodedEvents):
    cd = list(zip(d.t.tolist(), d.x.tolist(), d.y.tolist(), d.p.tolist()))
    tr = list(zip(d.trig_t.tolist(), d.trig_id.tolist(), d.trig_edge.tolist()))
    return cd, tr


def _random_events(rng, n, t0, span, width=640, height=480, clustered=True):
    t = np.sort(rng.integers(t0, t0 + span, n))
    x = rng.integers(0, width - 30, n)
    y = rng.integers(0, height, n)
    p = rng.integers(0, 2, n)
    ev = list(zip(t.tolist(), x.tolist(), y.tolist(), p.tolist()))
    if clustered:  # rows of neighbouring pixels firing together -> vector words
        for k in range(0, n, 10):
            tt, xx, yy, pp = ev[k]
            ev.extend((tt, xx + d, yy, pp) for d in (1, 2, 5, 13, 19, 27) if d % (k % 4 + 1) == 0)
    # unique (t, x, y, p), sorted by time
    return sorted(set(ev))


def _triggers(rng, n, t0, span):
    t = np.sort(rng.choice(np.arange(t0, t0 + span), n, replace=False))
    return [(int(tt), int(i), int(k % 2)) for k, (tt, i) in enumerate(zip(t, rng.integers(0, 4, n)))]


# ----------------------------------------------------------------------------- EVT 2.0
def test_evt2_roundtrip_with_time_high_wrap_and_triggers():
    rng = np.random.default_rng(1)
    t0 = (1 << 34) - 300_000  # the 34-bit µs clock rolls over in the middle
    events = _random_events(rng, 3000, t0, 600_000, clustered=False)
    trig = _triggers(rng, 40, t0, 600_000)
    data, cd, tr = encode_evt2(events, trig)
    out = decode_evt2(data, 640, 480)
    assert _as_lists(out) == (cd, tr)
    assert out.t[-1] > 1 << 34 and np.all(np.diff(out.t) >= 0)


def test_evt2_chunked_equals_whole_at_every_split():
    rng = np.random.default_rng(2)
    data, cd, tr = encode_evt2(_random_events(rng, 60, 5_000, 2_000, clustered=False), _triggers(rng, 3, 5_000, 2_000))
    whole = _as_lists(decode_evt2(data))
    for cut in range(1, len(data)):
        dec = Evt2Decoder()
        parts = [dec.decode(data[:cut]), dec.decode(data[cut:])]
        dec.finish()
        assert _as_lists(DecodedEvents.concatenate(parts)) == whole, cut


def test_evt2_drops_events_before_first_time_high_and_truncation_raises():
    cd_word = struct.pack("<I", (1 << 28) | (3 << 22) | (5 << 11) | 7)
    dec = Evt2Decoder()
    assert len(dec.decode(cd_word)) == 0 and dec.n_before_time == 1
    th = struct.pack("<I", (0x8 << 28) | 10)
    out = dec.decode(th + cd_word)
    assert _as_lists(out)[0] == [(10 * 64 + 3, 5, 7, 1)]
    dec.decode(b"\x01\x02")
    with pytest.raises(CodecError, match="incomplete"):
        dec.finish()


# ----------------------------------------------------------------------------- EVT 3.0
def test_evt3_roundtrip_vectors_wrap_and_triggers():
    rng = np.random.default_rng(3)
    t0 = (1 << 24) - 200_000  # the 24-bit µs clock rolls over in the middle
    events = _random_events(rng, 3000, t0, 400_000)
    trig = _triggers(rng, 30, t0, 400_000)
    data, cd, tr = encode_evt3(events, trig)
    words = np.frombuffer(data, "<u2") >> 12
    assert (words == 0x4).sum() > 50 and (words == 0x5).sum() > 50  # vector words exercised
    out = decode_evt3(data, 640, 480)
    assert _as_lists(out) == (cd, tr)
    assert out.t[-1] > 1 << 24 and np.all(np.diff(out.t) >= 0)
    assert sorted(cd) == events  # the encoder kept every event


def test_evt3_chunked_equals_whole_at_every_split():
    rng = np.random.default_rng(4)
    data, cd, tr = encode_evt3(_random_events(rng, 25, 70_000, 9_000), _triggers(rng, 3, 70_000, 9_000))
    whole = decode_evt3(data)
    assert _as_lists(whole) == (cd, tr)
    for cut in range(1, len(data)):
        dec = Evt3Decoder()
        parts = [dec.decode(data[:cut]), dec.decode(data[cut:])]
        dec.finish()
        assert _as_lists(DecodedEvents.concatenate(parts)) == (cd, tr), cut


def test_evt3_state_split_across_many_small_chunks():
    rng = np.random.default_rng(5)
    data, cd, tr = encode_evt3(_random_events(rng, 400, 0, 50_000), _triggers(rng, 10, 0, 50_000))
    dec = Evt3Decoder(640, 480)
    sizes = rng.integers(1, 9, len(data))
    parts, pos = [], 0
    for s in sizes:
        if pos >= len(data):
            break
        parts.append(dec.decode(data[pos:pos + int(s)]))
        pos += int(s)
    dec.finish()
    assert _as_lists(DecodedEvents.concatenate(parts)) == (cd, tr)


def test_evt3_time_valid_only_after_time_high_then_low_and_bounds():
    w = lambda code, pay: struct.pack("<H", (code << 12) | pay)  # noqa: E731
    data = w(0x0, 3) + w(0x2, 4)  # an event before any time
    data += w(0x8, 1) + w(0x2, 5)  # time high alone is not enough
    data += w(0x6, 7) + w(0x2, (1 << 11) | 6) + w(0x2, 700)  # valid; x=700 outside a 640 sensor
    dec = Evt3Decoder(640, 480)
    out = dec.decode(data)
    assert _as_lists(out)[0] == [((1 << 12) | 7, 6, 3, 1)]
    assert dec.n_before_time == 2 and dec.n_out_of_bounds == 1


# ----------------------------------------------------------------------------- libcaer
def _libcaer_bytes(ts, x, y, p):
    data = (np.asarray(x, np.uint32) << 17) | (np.asarray(y, np.uint32) << 2) | (np.asarray(p, np.uint32) << 1) | 1
    return np.stack([data, np.asarray(ts, np.int64).astype(np.uint32)], axis=1).astype("<u4").tobytes()


def test_libcaer_rollover_within_packet():
    ts = [ROLLOVER_US - 3, ROLLOVER_US - 1, 2, 10]
    out = LibcaerDecoder(640, 480).decode_packet(_libcaer_bytes(ts, [1, 2, 3, 4], [5, 6, 7, 8], [0, 1, 0, 1]), 1_000)
    expect = [1_000 + 1000 * v for v in (ROLLOVER_US - 3, ROLLOVER_US - 1, ROLLOVER_US + 2, ROLLOVER_US + 10)]
    assert out.t.tolist() == expect and out.x.tolist() == [1, 2, 3, 4] and out.p.tolist() == [0, 1, 0, 1]
    with pytest.raises(CodecError):
        LibcaerDecoder().decode_packet(b"\0" * 12, 0)


def test_libcaer_cmp_words():
    w = lambda code, pay: (code << 12) | pay  # noqa: E731
    words = [w(0, 1), w(1, 5), w(2, 10), w(3, (1 << 11) | 4), w(4, 20), w(5, 0b101), w(5, 0b1), w(1, 6), w(2, 11), w(3, 2)]
    dec = LibcaerCmpDecoder(346, 260)
    out = dec.decode_packet(struct.pack(f"<{len(words)}H", *words), 1_000_000)
    t1, t2 = 1_000_000 + ((1 << 12) | 5) * 1000, 1_000_000 + ((1 << 12) | 6) * 1000
    assert _as_lists(out)[0] == [(t1, 10, 4, 1), (t1, 10, 20, 0), (t1, 10, 22, 0), (t1, 10, 28, 0), (t2, 11, 2, 0)]
    # column and vector base carry to the next packet, time restarts at 0
    out = dec.decode_packet(struct.pack("<2H", w(3, 9), w(5, 1)), 0)
    assert _as_lists(out)[0] == [(0, 11, 9, 0), (0, 11, 36, 0)]


# ----------------------------------------------------------------------------- RAW files
def _write_raw(path, header: str, body: bytes):
    path.write_bytes(header.encode() + body)
    return path


@pytest.mark.parametrize("header", [
    "% evt 3.0\n% format EVT3;height=480;width=640\n% end\n",
    "% evt 3.0\n% geometry 640x480\n",
    "% evt 3.0\n% Width 640\n% Height 480\n",
])
def test_raw_evt3_file_roundtrip(tmp_path, header):
    rng = np.random.default_rng(6)
    data, cd, tr = encode_evt3(_random_events(rng, 2000, 1_000, 300_000), _triggers(rng, 8, 1_000, 300_000))
    path = _write_raw(tmp_path / "rec.raw", header, data)
    rec = open_recording(path)
    assert isinstance(rec, PropheseeRawRecording) and rec.format_name == "prophesee-raw-evt3"
    rec.read_bytes = 1001  # many chunk boundaries, odd so they split words
    assert rec.sensor_size("cam0") == (640, 480)
    ev = EventArray.concatenate(list(rec.iter_events("cam0", chunk_events=500)))
    assert list(zip(ev.t.tolist(), ev.x.tolist(), ev.y.tolist(), ev.p.tolist())) == cd
    t, edge = rec.triggers("cam0")
    assert t.tolist() == [r[0] for r in tr] and edge.tolist() == [r[2] for r in tr]
    info = rec.info()
    assert info["cameras"]["cam0"]["events"] == len(cd) and info["cameras"]["cam0"]["triggers"] == len(tr)


def test_raw_evt2_file_and_truncation(tmp_path):
    rng = np.random.default_rng(7)
    data, cd, _ = encode_evt2(_random_events(rng, 500, 0, 10_000, clustered=False))
    path = _write_raw(tmp_path / "a.raw", "% evt 2.0\n% geometry 640x480\n", data)
    ev = EventArray.concatenate(list(open_recording(path).iter_events("cam0")))
    assert list(zip(ev.t.tolist(), ev.x.tolist(), ev.y.tolist(), ev.p.tolist())) == cd
    cut = _write_raw(tmp_path / "cut.raw", "% evt 2.0\n% geometry 640x480\n", data[:-1])
    with pytest.raises(DataError, match="cut.raw.*incomplete"):
        list(open_recording(cut).iter_events("cam0"))


def test_raw_header_errors(tmp_path):
    with pytest.raises(DataError, match="no.raw.*no event format"):
        read_raw_header(_write_raw(tmp_path / "no.raw", "% geometry 640x480\n", b"\0\0"))
    with pytest.raises(DataError, match="geom.raw.*geometry"):
        read_raw_header(_write_raw(tmp_path / "geom.raw", "% evt 3.0\n", b"\0\0"))
    with pytest.raises(DataError, match="v21.raw.*not supported"):
        read_raw_header(_write_raw(tmp_path / "v21.raw", "% format EVT21;width=1;height=1\n", b""))


def test_real_gen3_evt2_raw(shared_data):
    rec = open_recording(shared_data / "events" / "prophesee_gen3_evt2.raw")
    assert rec.sensor_size("cam0") == (640, 480) and rec.format_name == "prophesee-raw-evt2"
    n, t_first, t_last, prev = 0, None, None, None
    for chunk in rec.iter_events("cam0", chunk_events=100_000):
        assert np.all(np.diff(chunk.t) >= 0) and (prev is None or chunk.t[0] >= prev)
        assert chunk.x.max() < 640 and chunk.y.max() < 480
        t_first = chunk.t[0] if t_first is None else t_first
        t_last = prev = chunk.t[-1]
        n += len(chunk)
    assert n == 521_252
    assert abs((t_last - t_first) * 1e-6 - 0.096) < 0.002
    assert rec.info()["cameras"]["cam0"]["events"] == 521_252
