"""MCTS: the paper's equations on hand-built events, channel order, constant event count,
causality, pixel mapping, rate cap, and equality of the numpy and torch implementations."""

from __future__ import annotations

import numpy as np
import pytest

from aerovis_slam.calib import CameraCalibration
from aerovis_slam.errors import DataError
from aerovis_slam.events import EventArray
from aerovis_slam.mcts import (
    MCTS_NE_EVENTS_PER_PX,
    PixelMap,
    TimestampBuffer,
    channel_names,
    events_per_window,
    mcts_from_events,
)

# float32 arithmetic of 1 - age * (1/dt): two roundings of relative size 2^-24 each on values <= 1
F32_TOL = 4 * 2.0**-24


def ev(rows):
    """EventArray from (t, x, y, p) rows."""
    t, x, y, p = zip(*rows)
    return EventArray(t, x, y, p)


def test_mcts_dt_values_and_channel_order():
    # 4x3 sensor; windows 1 ms and 3 ms; tau = 10_000 µs
    events = ev([
        (5_000, 0, 0, 1),  # ON at (0,0), 5 ms old, then overwritten by the newer event below
        (9_000, 1, 0, 0),  # OFF at (1,0): age 1 ms -> 0 in the 1 ms window
        (9_500, 0, 0, 1),  # newest ON at (0,0): age 0.5 ms
        (9_900, 2, 1, 0),  # OFF at (2,1): age 0.1 ms
        (10_000, 3, 2, 1),  # ON at (3,2): age 0
    ])
    buf = TimestampBuffer(4, 3)
    buf.ingest(events)
    m = buf.mcts_dt(tau=10_000, windows_ms=(1, 3))
    assert m.shape == (4, 3, 4)
    assert channel_names("dt", (1, 3)) == ["off_dt1ms", "off_dt3ms", "on_dt1ms", "on_dt3ms"]
    expected = np.zeros((4, 3, 4), np.float32)
    # OFF channels 0 (1 ms) and 1 (3 ms)
    expected[0, 1, 2], expected[1, 1, 2] = 1 - 100 / 1000, 1 - 100 / 3000
    expected[0, 0, 1], expected[1, 0, 1] = 0.0, 1 - 1000 / 3000
    # ON channels 2 (1 ms) and 3 (3 ms): the newest event of a pixel wins
    expected[2, 0, 0], expected[3, 0, 0] = 1 - 500 / 1000, 1 - 500 / 3000
    expected[2, 2, 3], expected[3, 2, 3] = 1.0, 1.0
    np.testing.assert_allclose(m, expected, atol=F32_TOL, rtol=0)


def test_mcts_ne_windows_follow_event_count():
    # 4x3 = 12 pixels, rho = (0.25, 0.5) -> N = (3, 6) events
    assert events_per_window((0.25, 0.5), 4, 3).tolist() == [3, 6]
    assert events_per_window(MCTS_NE_EVENTS_PER_PX, 640, 480).tolist() == [9216, 30720, 92160, 307200]
    rows = [(100 * i, i % 4, (i // 4) % 3, i % 2) for i in range(10)]  # t = 0, 100, ..., 900
    buf = TimestampBuffer(4, 3, events_per_px=(0.25, 0.5))
    buf.ingest(ev(rows))
    # I = 9: t_(I-3) = 600 -> dt = 300; t_(I-6) = 300 -> dt = 600
    np.testing.assert_array_equal(buf.ne_windows_us(900, (0.25, 0.5)), [300.0, 600.0])
    m = buf.mcts_ne(900, (0.25, 0.5))
    # event 8 (t=800, x=0, y=2, p=0): age 100 -> 1 - 100/300, 1 - 100/600 in OFF channels 0, 1
    np.testing.assert_allclose(m[:2, 2, 0], [1 - 100 / 300, 1 - 100 / 600], atol=F32_TOL)
    # event 9 (t=900, x=1, y=2, p=1): age 0 -> 1 in ON channels 2, 3
    np.testing.assert_allclose(m[2:, 2, 1], [1.0, 1.0], atol=0)
    # event 5 (t=500, x=1, y=1, p=1): outside the 300 µs window, 1 - 400/600 in the other
    np.testing.assert_allclose(m[2:, 1, 1], [0.0, 1 - 400 / 600], atol=F32_TOL)
    # later tau stretches every window by the same amount
    np.testing.assert_array_equal(buf.ne_windows_us(1000, (0.25, 0.5)), [400.0, 700.0])


def test_mcts_ne_window_before_enough_events_reaches_first_event():
    buf = TimestampBuffer(4, 3, events_per_px=(0.5,))  # N = 6
    buf.ingest(ev([(10, 0, 0, 1), (40, 1, 0, 1)]))
    np.testing.assert_array_equal(buf.ne_windows_us(50, (0.5,)), [40.0])  # back to t = 10


def test_surfaces_are_complete_once_the_longest_window_is_full():
    """``is_complete``: the longest MCTS_Ne window reaches back N = 0.5 x 4 x 3 = 6 events before
    the newest, so it needs 7; MCTS_dt the longest window (5 ms) since the first event; no events
    is never complete."""
    buf = TimestampBuffer(4, 3, events_per_px=(0.25, 0.5))
    assert not buf.is_complete(0, "ne", (0.25, 0.5)) and not buf.is_complete(0, "dt", (5.0,))
    buf.ingest(ev([(1000 + 10 * i, i % 4, 0, 1) for i in range(6)]))
    assert buf.first_t == 1000 and not buf.is_complete(2000, "ne", (0.25, 0.5))
    assert buf.is_complete(2000, "ne", (0.25,))  # N = 3: 4 events suffice
    buf.ingest(ev([(1100, 0, 1, 0)]))
    assert buf.is_complete(2000, "ne", (0.25, 0.5)) and buf.first_t == 1000
    assert not buf.is_complete(5999, "dt", (1.0, 5.0)) and buf.is_complete(6000, "dt", (1.0, 5.0))
    with pytest.raises(ValueError, match="'ne' or 'dt'"):
        buf.is_complete(6000, "tw", (5.0,))


def _stream(n, width, height, seed, t_scale=1):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.choice(np.arange(0, 20 * n, 2), size=n, replace=False)).astype(np.int64) * t_scale
    return EventArray(t, rng.integers(0, width, n), rng.integers(0, height, n), rng.integers(0, 2, n))


def test_constant_event_count_property():
    """Each MCTS_Ne window holds exactly N_k events, and the surface is invariant to the event rate."""
    w, h = 32, 24
    events = _stream(2000, w, h, seed=1)
    buf = TimestampBuffer(w, h)
    buf.ingest(events)
    tau = int(events.t[-1])
    dts = buf.ne_windows_us(tau)
    n_k = events_per_window(MCTS_NE_EVENTS_PER_PX, w, h)
    for dt, n in zip(dts, n_k):  # timestamps are distinct, so (tau - dt, tau] holds exactly N_k events
        assert np.count_nonzero(events.t > tau - dt) == n
    # the same scene seen twice as fast (timestamps halved about the first): identical MCTS_Ne ...
    fast = EventArray(events.t[0] + (events.t - events.t[0]) // 2, events.x, events.y, events.p)
    ne_slow = mcts_from_events(events, w, h, kind="ne")
    ne_fast = mcts_from_events(fast, w, h, kind="ne")
    np.testing.assert_array_equal(ne_slow, ne_fast)
    # ... while fixed windows see a different picture
    dt_slow = mcts_from_events(events, w, h, kind="dt")
    dt_fast = mcts_from_events(fast, w, h, kind="dt")
    assert np.abs(dt_slow - dt_fast).max() > 0.1


def test_causality_and_streaming():
    w, h = 16, 12
    events = _stream(3000, w, h, seed=2)
    tau = int(events.t[1700])
    past = events.time_slice(events.t[0], tau + 1)
    # another future: same past, different events after tau
    other_future = _stream(500, w, h, seed=3)
    other_future.t[:] = tau + 1 + np.arange(500)
    for kind in ("ne", "dt"):
        a = mcts_from_events(past, w, h, tau, kind=kind)
        # chunked ingest of the past equals one-shot ingest
        buf = TimestampBuffer(w, h)
        for i in range(0, len(past), 97):
            buf.ingest(past[i : i + 97])
        b = buf.mcts_ne(tau) if kind == "ne" else buf.mcts_dt(tau)
        np.testing.assert_array_equal(a, b)
        # futures beyond tau cannot change it: asking for tau after ingesting them is an error
        buf.ingest(other_future)
        with pytest.raises(DataError, match="already ingested"):
            buf.mcts_ne(tau)
    # only the last max(N_k) + 1 events matter for MCTS_Ne
    n_max = int(events_per_window(MCTS_NE_EVENTS_PER_PX, w, h).max())
    full = mcts_from_events(events, w, h, kind="ne")
    suffix = mcts_from_events(events[-(n_max + 1) :], w, h, kind="ne")
    np.testing.assert_array_equal(full, suffix)


def test_bad_events_raise():
    buf = TimestampBuffer(4, 3)
    with pytest.raises(DataError, match="decrease"):
        buf.ingest(ev([(10, 0, 0, 1), (5, 1, 0, 1)]))
    assert buf.count == 1  # events before the bad one are kept
    with pytest.raises(DataError, match="outside the 4x3 sensor"):
        buf.ingest(ev([(20, 4, 0, 1)]))
    with pytest.raises(DataError, match="polarity"):
        buf.ingest(ev([(30, 0, 0, 2)]))
    with pytest.raises(DataError, match="no events"):
        TimestampBuffer(4, 3).mcts_ne()


def test_downsampling_fractional_and_integer():
    pm = PixelMap.downsample(1280, 720, 424, 240)
    lut = pm.lut.reshape(720, 1280)
    assert lut[719, 1279] == 239 * 424 + 423 and lut[0, 0] == 0
    # every output pixel receives 3 or 4 input columns and exactly 3 input rows
    counts = np.bincount(pm.lut, minlength=424 * 240).reshape(240, 424)
    assert set(np.unique(counts).tolist()) <= {9, 12}
    buf = TimestampBuffer(424, 240, pixel_map=pm)
    buf.ingest(ev([(1, 1279, 719, 1), (2, 3, 5, 0)]))
    assert buf.ts[1, 239, 423] == 1 and buf.ts[0, 1, 0] == 2
    pm2 = PixelMap.downsample(8, 6, 4, 3, K=np.array([[10.0, 0, 3.5], [0, 10.0, 2.5], [0, 0, 1]]))
    assert pm2.lut.reshape(6, 8)[5, 7] == 2 * 4 + 3
    # the image centre (3.5, 2.5) of the 8x6 sensor stays the centre (1.5, 1.0) of the 4x3 output
    np.testing.assert_allclose(pm2.K, [[5.0, 0, 1.5], [0, 5.0, 1.0], [0, 0, 1]])


def test_undistortion_map():
    cam = CameraCalibration(width=64, height=48, fx=50, fy=50, cx=31.5, cy=23.5)
    ident = PixelMap.from_calibration(cam)
    np.testing.assert_array_equal(ident.lut, np.arange(64 * 48))
    dist = CameraCalibration(width=64, height=48, fx=50, fy=50, cx=31.5, cy=23.5,
                             distortion_model="radtan", distortion_coeffs=[-0.3, 0.1, 0.0, 0.0])
    pm = PixelMap.from_calibration(dist)
    import cv2

    # an ideal point (52, 40) seen through the lens lands at a distorted pixel; its event maps back
    ideal = np.array([[52.0, 40.0]])
    norm = (ideal - [31.5, 23.5]) / 50.0
    distorted, _ = cv2.projectPoints(np.c_[norm, np.ones(1)], np.zeros(3), np.zeros(3), dist.K, np.array(dist.distortion_coeffs))
    u, v = np.rint(distorted.reshape(2)).astype(int)
    out = pm.lut[v * 64 + u]
    # rounding the sensor pixel moves the point by at most half a pixel; with |d ideal/d distorted| <= ~1.3
    # here, the ideal position is off by < 1 px, so the mapped pixel is within 1 of (52, 40)
    assert abs(out % 64 - 52) <= 1 and abs(out // 64 - 40) <= 1
    # barrel distortion compresses the corners: some output pixels near corners are never hit, none dropped in the centre
    assert pm.lut[24 * 64 + 32] == 24 * 64 + 32


def test_rate_cap_thins_bursts():
    n = 200_000
    t = np.linspace(0, 100_000, n).astype(np.int64)  # 2 Mev/s for 0.1 s
    events = EventArray(t, np.zeros(n), np.zeros(n), np.ones(n))
    buf = TimestampBuffer(4, 3, max_rate_ev_s=1e6)
    for i in range(0, n, 1000):  # 1000-event packets of 0.5 ms each
        buf.ingest(events[i : i + 1000])
    # 1 Mev/s for 0.1 s plus at most the 10 ms burst budget: 100k..110k accepted
    assert 100_000 - 1000 <= buf.count <= 110_000
    assert buf.count + buf.dropped_rate_cap == n


torch = pytest.importorskip("torch", reason="torch (the train extra) is not installed")


def test_torch_equals_numpy_batched():
    from aerovis_train import mcts_torch

    w, h = 40, 30
    streams = [_stream(n, w, h, seed=s) for s, n in ((10, 500), (11, 1300), (12, 40))]
    taus = [int(s.t[-1]) + extra for s, extra in zip(streams, (0, 250, 5))]
    cat = EventArray.concatenate(streams)
    batch = torch.repeat_interleave(torch.arange(3), torch.tensor([len(s) for s in streams]))
    args = [torch.from_numpy(a.astype(np.int64)) for a in (cat.t, cat.x, cat.y, cat.p)]
    tau = torch.tensor(taus)
    ne_t = mcts_torch.mcts_ne(*args, width=w, height=h, batch=batch, batch_size=3, tau=tau)
    dt_t = mcts_torch.mcts_dt(*args, width=w, height=h, batch=batch, batch_size=3, tau=tau)
    for b, (s, tau_b) in enumerate(zip(streams, taus)):
        np.testing.assert_allclose(ne_t[b].numpy(), mcts_from_events(s, w, h, tau_b, kind="ne"), atol=F32_TOL, rtol=0)
        np.testing.assert_allclose(dt_t[b].numpy(), mcts_from_events(s, w, h, tau_b, kind="dt"), atol=F32_TOL, rtol=0)
    assert ne_t.shape == (3, 8, h, w) and dt_t.shape == (3, 10, h, w)
