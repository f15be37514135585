"""AEDAT4 files written by iniVation's own dv-processing: events, IMU units, frames, triggers, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from aerovis_slam.errors import DataError
from aerovis_slam.events import EventArray
from aerovis_slam.io.aedat4 import Aedat4Recording
from aerovis_slam.io.sequence import Sequence
from aerovis_slam.io.source import convert, open_recording

dv = pytest.importorskip("dv_processing", reason="AEDAT4 support needs dv-processing (pip install dv-processing)")

W, H = 346, 260


def write_aedat4(path, n=5000, seed=0, packet=800):
    """A DAVIS-like file: events in several packets, 1 kHz IMU in g / deg/s, two frames, triggers."""
    rng = np.random.default_rng(seed)
    t = 1_700_000_000_000_000 + np.sort(rng.integers(0, 200_000, n))
    x, y, p = rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 2, n)
    writer = dv.io.MonoCameraWriter(str(path), dv.io.MonoCameraWriter.DAVISConfig("DAVIS346_test", (W, H)))
    for s in range(0, n, packet):
        store = dv.EventStore()
        for k in range(s, min(s + packet, n)):
            store.push_back(int(t[k]), int(x[k]), int(y[k]), bool(p[k]))
        writer.writeEvents(store)
    ti = t[0] + np.arange(0, 200_000, 1000)
    acc_g = rng.normal(size=(len(ti), 3)).astype(np.float32)  # DV stores float32
    gyro_dps = (rng.normal(size=(len(ti), 3)) * 100).astype(np.float32)
    for k in range(len(ti)):
        writer.writeImu(dv.IMU(int(ti[k]), 30.0, *map(float, acc_g[k]), *map(float, gyro_dps[k]), 0.0, 0.0, 0.0))
    frames = []
    for k in range(2):
        img = rng.integers(0, 256, (H, W), dtype=np.uint8)
        frames.append((int(t[0]) + 50_000 * (k + 1), img))
        writer.writeFrame(dv.Frame(frames[-1][0], img))
    trig_t = [int(t[0]) + 10_000 * k for k in range(1, 5)]
    for k, tt in enumerate(trig_t):
        kind = dv.TriggerType.EXTERNAL_SIGNAL_RISING_EDGE if k % 2 == 0 else dv.TriggerType.EXTERNAL_SIGNAL_FALLING_EDGE
        writer.writeTrigger(dv.Trigger(tt, kind))
    del writer  # closing writes the file data table
    return EventArray(t, x, y, p), (ti, acc_g, gyro_dps), frames, trig_t


def test_events_imu_frames_triggers(tmp_path):
    path = tmp_path / "rec.aedat4"
    ev, (ti, acc_g, gyro_dps), frames, trig_t = write_aedat4(path)
    rec = open_recording(path)
    assert isinstance(rec, Aedat4Recording) and rec.sensor_size("cam0") == (W, H)
    chunks = list(rec.iter_events("cam0", chunk_events=1000))
    assert len(chunks) > 1
    got = EventArray.concatenate(chunks)
    for k in "txyp":
        np.testing.assert_array_equal(getattr(got, k), getattr(ev, k))
    imu = rec.imu()
    np.testing.assert_array_equal(imu.t, ti)
    np.testing.assert_allclose(imu.acc, acc_g.astype(np.float64) * 9.80665, rtol=1e-12)  # g -> m/s²
    np.testing.assert_allclose(imu.gyro, np.deg2rad(gyro_dps.astype(np.float64)), rtol=1e-12)  # deg/s -> rad/s
    got_frames = list(rec.iter_frames("cam0"))
    assert [t for t, _ in got_frames] == [t for t, _ in frames]
    np.testing.assert_array_equal(got_frames[1][1], frames[1][1])
    tt, tp = rec.triggers("cam0")
    assert tt.tolist() == trig_t and tp.tolist() == [1, 0, 1, 0]


def test_convert_end_to_end(tmp_path):
    path = tmp_path / "rec.aedat4"
    ev, (ti, acc_g, _), frames, trig_t = write_aedat4(path, n=2000, seed=1)
    out = tmp_path / "seq.h5"
    convert(open_recording(path), out, require_calib=False, progress=False)
    with Sequence(out) as seq:
        got = seq.events("cam0")
        np.testing.assert_array_equal(got.t, ev.t)
        np.testing.assert_array_equal(got.y, ev.y)
        np.testing.assert_array_equal(got.p, ev.p)
        np.testing.assert_array_equal(seq.imu.t, ti)
        np.testing.assert_allclose(seq.imu.acc, acc_g * 9.80665, rtol=1e-6)
        assert seq.frame_times("cam0").tolist() == [t for t, _ in frames]
        assert seq.triggers("cam0")[0].tolist() == trig_t


def test_truncated_and_foreign_files(tmp_path):
    path = tmp_path / "rec.aedat4"
    write_aedat4(path, n=3000, seed=2)
    data = path.read_bytes()
    for cut in (len(data) - 40, len(data) // 2, 20):
        bad = tmp_path / f"cut{cut}.aedat4"
        bad.write_bytes(data[:cut])
        with pytest.raises(DataError, match=rf"cut{cut}.aedat4: AEDAT4 file is (truncated or corrupt|unreadable)"):
            rec = Aedat4Recording(bad)
            list(rec.iter_events("cam0"))
            rec.imu()
    other = tmp_path / "x.aedat4"
    other.write_bytes(b"#!AER-DAT3.1\r\n")
    with pytest.raises(DataError, match="not an AEDAT4 file"):
        Aedat4Recording(other)
    with pytest.raises(DataError, match="unrecognised recording format"):
        open_recording(other)
