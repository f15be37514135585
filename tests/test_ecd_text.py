"""ECD / rpg text folders: exact µs parsing, streaming, side files, bad input, conversion."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from aerovis_slam.errors import DataError
from aerovis_slam.events import EventArray
from aerovis_slam.io.ecd_text import EcdTextRecording, parse_seconds_to_us
from aerovis_slam.io.sequence import Sequence
from aerovis_slam.io.source import convert, open_recording

T0_US = 1468939993_067416  # an ECD-like absolute time: 16 significant digits, beyond float64's µs


def _sec(us: int) -> str:
    return f"{us // 1_000_000}.{us % 1_000_000:06d}"


def _write_folder(tmp_path, n=5000, seed=0):
    rng = np.random.default_rng(seed)
    t = T0_US + np.sort(rng.integers(0, 2_000_000, n))
    x, y, p = rng.integers(0, 240, n), rng.integers(0, 180, n), rng.integers(0, 2, n)
    (tmp_path / "events.txt").write_text("".join(f"{_sec(a)} {b} {c} {d}\n" for a, b, c, d in zip(t.tolist(), x.tolist(), y.tolist(), p.tolist())))
    ti = T0_US + np.arange(0, 2_000_000, 1000)
    acc = rng.normal(size=(len(ti), 3)) + [0, -9.81, 0]
    gyro = rng.normal(size=(len(ti), 3)) * 0.1
    (tmp_path / "imu.txt").write_text("".join(f"{_sec(a)} " + " ".join(repr(v) for v in r + g) + "\n" for a, r, g in zip(ti.tolist(), acc.tolist(), gyro.tolist())))
    tg = T0_US + np.arange(0, 2_000_000, 5000)
    q = rng.normal(size=(len(tg), 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    pos = rng.normal(size=(len(tg), 3))
    (tmp_path / "groundtruth.txt").write_text("".join(f"{_sec(a)} " + " ".join(repr(v) for v in np.concatenate([pp, qq]).tolist()) + "\n"
                                                      for a, pp, qq in zip(tg.tolist(), pos, q)))
    (tmp_path / "calib.txt").write_text("199.092366542 198.82882047 132.192071378 110.712660011 -0.368436311798 0.150947243557 -0.000296130534385 -0.000759431726241 0.0\n")
    (tmp_path / "images").mkdir()
    frames = []
    lines = []
    for k in range(3):
        img = rng.integers(0, 256, (180, 240), dtype=np.uint8)
        cv2.imwrite(str(tmp_path / "images" / f"frame_{k:08d}.png"), img)
        frames.append((T0_US + 100_000 * k + 7, img))
        lines.append(f"{_sec(T0_US + 100_000 * k + 7)} images/frame_{k:08d}.png\n")
    (tmp_path / "images.txt").write_text("".join(lines))
    return EventArray(t, x, y, p), (ti, acc, gyro), (tg, np.concatenate([pos, q], axis=1)), frames


def test_parse_seconds_exactly():
    assert parse_seconds_to_us("1468939993.067416") == 1468939993067416
    assert parse_seconds_to_us("0.003811000") == 3811
    assert parse_seconds_to_us("1468939993.0674165") == 1468939993067417  # half rounds up
    assert parse_seconds_to_us("1468939993.0674164999") == 1468939993067416
    assert parse_seconds_to_us("1.5e-3") == 1500 and parse_seconds_to_us("12") == 12_000_000
    with pytest.raises(ValueError):
        parse_seconds_to_us("1.2.3")
    # Every µs over a span at 1.47e9 s parses exactly (a float64 detour is ~0.24 µs coarse there).
    us = T0_US + np.arange(0, 2000, 1)
    assert [parse_seconds_to_us(_sec(u)) for u in us.tolist()] == us.tolist()


def test_round_trip_events_imu_gt_calib_frames(tmp_path):
    ev, (ti, acc, gyro), (tg, pose), frames = _write_folder(tmp_path)
    rec = open_recording(tmp_path)
    assert isinstance(rec, EcdTextRecording) and rec.cameras() == ["cam0"] and rec.sensor_size("cam0") == (240, 180)
    chunks = list(rec.iter_events("cam0", chunk_events=777))
    assert max(len(c) for c in chunks) <= 777 and len(chunks) > 1
    got = EventArray.concatenate(chunks)
    for k in "txyp":
        np.testing.assert_array_equal(getattr(got, k), getattr(ev, k))
    imu = rec.imu()
    np.testing.assert_array_equal(imu.t, ti)
    np.testing.assert_array_equal(imu.acc, acc)  # columns 1-3 are the accelerometer
    np.testing.assert_array_equal(imu.gyro, gyro)
    gt = rec.gt()
    np.testing.assert_array_equal(gt.t, tg)
    np.testing.assert_array_equal(gt.pose, pose)
    cal = rec.calibration().cameras["cam0"]
    assert (cal.width, cal.height, cal.fx) == (240, 180, 199.092366542)
    got_frames = list(rec.iter_frames("cam0"))
    assert [t for t, _ in got_frames] == [t for t, _ in frames]
    for (_, a), (_, b) in zip(got_frames, frames):
        np.testing.assert_array_equal(a, b)


def test_convert_end_to_end(tmp_path):
    src = tmp_path / "ecd"
    src.mkdir()
    ev, (ti, acc, gyro), (tg, pose), frames = _write_folder(src, n=3000, seed=1)
    out = tmp_path / "seq.h5"
    summary = convert(open_recording(src), out, progress=False)
    assert summary["cameras"]["cam0"]["events"] == 3000
    with Sequence(out) as seq:
        got = seq.events("cam0")
        np.testing.assert_array_equal(got.t, ev.t)
        np.testing.assert_array_equal(got.x, ev.x)
        np.testing.assert_array_equal(got.p, ev.p)
        np.testing.assert_array_equal(seq.imu.acc, acc)
        np.testing.assert_array_equal(seq.gt.pose, pose)
        assert seq.calib.cameras["cam0"].fx == 199.092366542
        np.testing.assert_array_equal(seq.frame_times("cam0"), [t for t, _ in frames])
        assert seq.meta["source_format"] == "ecd-text"


def test_comments_blank_lines_crlf_and_minus_one_polarity(tmp_path):
    (tmp_path / "events.txt").write_text("# t x y p\r\n0.000001 1 2 1\r\n\r\n0.0000025 3 4 -1\r\n0.000003\t5\t6\t0")
    got = EventArray.concatenate(list(EcdTextRecording(tmp_path).iter_events("cam0")))
    assert got.t.tolist() == [1, 3, 3] and got.x.tolist() == [1, 3, 5] and got.p.tolist() == [1, 0, 0]


@pytest.mark.parametrize(
    "body,line,match",
    [
        ("0.1 1 1 1\n0.2 1 x 1\n", 2, "bad y"),
        ("0.1 1 1 1\n0.2 1 1 2\n", 2, "polarity"),
        ("0.1 1 1 1\n0.2 1 1 1 9\n", 2, "trailing"),
        ("# header\n0.1 1 1 1\n0.3 1 1 1\n0.2 1 1 1\n", 4, "before the previous"),
        ("0.1 1 1 1\n\n0.2 240 1 1\n", 3, "outside the 240x180"),
        ("abc 1 1 1\n", 1, "timestamp"),
    ],
)
def test_bad_event_lines_name_file_and_line(tmp_path, body, line, match):
    (tmp_path / "events.txt").write_text(body)
    with pytest.raises(DataError, match=match) as err:
        list(EcdTextRecording(tmp_path).iter_events("cam0"))
    assert "events.txt" in str(err.value) and f"line {line}:" in str(err.value)


def test_unsorted_across_blocks_reports_the_right_line(tmp_path):
    lines = [f"{_sec(1000 + i)} 1 1 1\n" for i in range(30000)]
    lines[25000] = f"{_sec(5)} 1 1 1\n"
    (tmp_path / "events.txt").write_text("".join(lines))
    with pytest.raises(DataError, match="line 25001:"):
        list(EcdTextRecording(tmp_path).iter_events("cam0", chunk_events=4096))  # blocks of ~100 kB


def test_bad_side_files(tmp_path):
    _write_folder(tmp_path, n=10)
    (tmp_path / "imu.txt").write_text("0.1 1 2 3 4 5 6\n0.2 1 2 3 4 5\n")
    with pytest.raises(DataError, match=r"imu.txt: line 2: 6 columns, expected 7"):
        EcdTextRecording(tmp_path).imu()
    (tmp_path / "groundtruth.txt").write_text("0.1 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0 1\n")
    with pytest.raises(DataError, match="groundtruth.txt.*strictly increasing"):
        EcdTextRecording(tmp_path).gt()
    (tmp_path / "calib.txt").write_text("1 2 3\n")
    with pytest.raises(DataError, match="calib.txt.*cy"):
        EcdTextRecording(tmp_path).calibration()
