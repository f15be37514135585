"""The canonical HDF5 sequence: layout readable by h5py, time index, streaming, atomic writes,
bad input, and the runtime's independence from torch."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest

from aerovis_slam.calib import CameraCalibration, ImuNoise, RigCalibration
from aerovis_slam.errors import DataError
from aerovis_slam.events import EventArray
from aerovis_slam.io.sequence import Sequence, SequenceWriter
from aerovis_slam.measurements import ImuSamples, PoseSamples


def make_rig(w=32, h=24) -> RigCalibration:
    T = np.eye(4)
    T[0, 3] = 0.074  # cam1 7.4 cm to the right of the IMU
    return RigCalibration(
        {
            "cam0": CameraCalibration(w, h, 30.0, 31.0, 15.5, 11.5, T_imu_cam=np.eye(4)),
            "cam1": CameraCalibration(w, h, 30.0, 31.0, 15.5, 11.5, "radtan", [0.1, -0.01, 0.0, 0.0], T_imu_cam=T),
        },
        ImuNoise(),
    )


def random_events(n, w, h, t0, t1, seed):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(t0, t1, n))
    return EventArray(t, rng.integers(0, w, n), rng.integers(0, h, n), rng.integers(0, 2, n))


@pytest.fixture()
def seq_path(tmp_path):
    path = tmp_path / "seq.h5"
    rig = make_rig()
    ev = random_events(50_000, 32, 24, 1_234_567, 3_500_000, seed=0)
    with SequenceWriter(path, rig, meta={"origin": "test"}) as w:
        for i in range(0, len(ev), 7_777):  # odd chunking: ms boundaries split across chunks
            w.add_events("cam0", ev[i : i + 7_777])
        w.add_events(1, random_events(1000, 32, 24, 2_000_000, 2_100_000, seed=1))
        w.add_triggers("cam0", np.array([1_300_000, 1_400_000]), np.array([1, 0]))
        t_imu = np.arange(1_200_000, 3_600_000, 5_000)
        w.set_imu(ImuSamples(t_imu, np.ones((len(t_imu), 3)) * 0.1, np.tile([0, 0, 9.81], (len(t_imu), 1))))
        w.set_gt(PoseSamples(t_imu[::2], np.tile([0, 0, 0, 0, 0, 0, 1.0], (len(t_imu[::2]), 1))))
        w.add_frames("cam0", [1_500_000, 1_550_000], np.zeros((2, 24, 32), np.uint8))
        w.add_frames("cam0", [1_500_000], np.full((24, 32), 2.5, np.float32), kind="depth")
    return path, ev


def test_layout_read_with_h5py(seq_path):
    path, ev = seq_path
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "aerovis-sequence" and f.attrs["format_version"] == 1
        for cam in ("cam0", "cam1"):
            g = f[f"events/{cam}"]
            assert (g["t"].dtype, g["x"].dtype, g["y"].dtype, g["p"].dtype) == (np.int64, np.uint16, np.uint16, np.int8)
            assert g["t"].chunks is not None and "32001" in g["t"]._filters  # Blosc (hdf5plugin), the default
        assert f["imu/gyro"].shape[1] == 3 and f["imu/acc"].dtype == np.float64
        assert f["gt/pose"].shape[1] == 7
        calib = json.loads(f["calib"].attrs["json"])
        assert set(calib) == {"cam0", "cam1", "imu"}
        assert calib["cam1"]["T_imu_cam"][0][3] == pytest.approx(0.074)
        assert f["frames/cam0/image"].dtype == np.uint8 and f["depth/cam0/depth"].dtype == np.float32
        np.testing.assert_array_equal(f["events/cam0/t"][:], ev.t)


def test_event_compression_choices_read_back_the_same(tmp_path):
    ev = random_events(20_000, 32, 24, 0, 2_000_000, seed=3)
    paths = {}
    for codec in ("blosc-lz4", "gzip"):
        paths[codec] = tmp_path / f"{codec}.h5"
        with SequenceWriter(paths[codec], sensor_sizes={"cam0": (32, 24)}, event_compression=codec) as w:
            w.add_events("cam0", ev)
        with Sequence(paths[codec]) as s:
            assert s.event_compression("cam0") == codec and s.summary()["cameras"]["cam0"]["event_compression"] == codec
            back = s.events("cam0")
            np.testing.assert_array_equal(back.t, ev.t)
            np.testing.assert_array_equal(back.x, ev.x)
            np.testing.assert_array_equal(back.p, ev.p)
    # the gzip choice is for tools without filter plugins: a process that never imports hdf5plugin reads it
    code = "import sys, h5py; f = h5py.File(sys.argv[1], 'r'); print(int(f['events/cam0/t'][:].sum()))"
    out = subprocess.run([sys.executable, "-c", code, str(paths["gzip"])], capture_output=True, text=True, check=True)
    assert int(out.stdout) == int(ev.t.sum())
    with pytest.raises(ValueError, match="event_compression must be one of"):
        SequenceWriter(tmp_path / "x.h5", sensor_sizes={"cam0": (32, 24)}, event_compression="lzo")
    assert not (tmp_path / "x.h5.partial").exists()


def test_ms_index_and_time_slices(seq_path):
    path, ev = seq_path
    with Sequence(path) as s:
        idx = s._file["events/cam0/ms_to_idx"][:]
        t0_ms = s._file["events/cam0/ms_to_idx"].attrs["t0_ms"]
        # definition: ms_to_idx[k] = number of events before (t0_ms + k) ms
        k = np.arange(len(idx))
        np.testing.assert_array_equal(idx, np.searchsorted(ev.t, (t0_ms + k) * 1000, side="left"))
        rng = np.random.default_rng(5)
        for _ in range(50):
            a, b = np.sort(rng.integers(1_000_000, 3_700_000, 2))
            got = s.events("cam0", a, b)
            np.testing.assert_array_equal(got.t, ev.t[(ev.t >= a) & (ev.t < b)])
        assert s.index_at("cam0", 0) == 0 and s.index_at("cam0", 10**9) == len(ev)
        chunks = list(s.iter_events("cam0", chunk_events=10_000))
        assert len(chunks) == 5
        np.testing.assert_array_equal(EventArray.concatenate(chunks).x, ev.x)
        assert s.calib.cameras["cam1"].distortion_model == "radtan"
        assert s.imu.acc[0, 2] == pytest.approx(9.81) and len(s.gt) == len(s.imu) // 2
        assert s.triggers("cam0")[0].tolist() == [1_300_000, 1_400_000]
        assert s.frame("cam0", 0, kind="depth")[0, 0] == pytest.approx(2.5)
        summary = s.summary()
        assert summary["cameras"]["cam0"]["events"] == 50_000 and summary["cameras"]["cam1"]["events"] == 1000
        assert summary["cameras"]["cam0"]["frames"] == 2 and summary["cameras"]["cam0"]["depth"] == 1
        assert s.meta == {"origin": "test"}


def test_failed_write_leaves_nothing(tmp_path):
    path = tmp_path / "broken.h5"
    with pytest.raises(RuntimeError):
        with SequenceWriter(path, make_rig()) as w:
            w.add_events("cam0", random_events(100, 32, 24, 0, 1000, 0))
            raise RuntimeError("simulated crash")
    assert list(tmp_path.iterdir()) == []


def test_bad_input_is_named(tmp_path):
    path = tmp_path / "bad.h5"
    with SequenceWriter(path, make_rig()) as w:
        w.add_events("cam0", EventArray([10, 20], [0, 1], [0, 0], [0, 1]))
        with pytest.raises(DataError, match=r"bad.h5.*/events/cam0/t decreases across chunks"):
            w.add_events("cam0", EventArray([15], [0], [0], [0]))
        with pytest.raises(DataError, match=r"/events/cam0: 1 events outside the 32x24 sensor"):
            w.add_events("cam0", EventArray([30], [32], [0], [0]))
        with pytest.raises(DataError, match="sensor size of cam5 unknown"):
            w.add_events("cam5", EventArray([30], [0], [0], [0]))
        with pytest.raises(DataError, match="/imu/t is not strictly increasing"):
            w.set_imu(ImuSamples([0, 5, 5], np.zeros((3, 3)), np.zeros((3, 3))))
        with pytest.raises(DataError, match="unit length"):
            w.set_gt(PoseSamples([0], [[0, 0, 0, 0, 0, 0, 2.0]]))
    (tmp_path / "junk.h5").write_bytes(b"not hdf5 at all")
    with pytest.raises(DataError, match="junk.h5: not a readable HDF5 file"):
        Sequence(tmp_path / "junk.h5")
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f.create_group("events")
    with pytest.raises(DataError, match="expected 'aerovis-sequence'"):
        Sequence(tmp_path / "other.h5")
    with pytest.raises(DataError, match="output folder does not exist"):
        SequenceWriter(tmp_path / "nope" / "x.h5")
    with pytest.raises(DataError, match="lacks field"):
        RigCalibration.from_json('{"cam0": {"width": 3}}', path="x.h5")


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write into read-only folders")
def test_unwritable_folder(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    with pytest.raises(DataError, match="not writable"):
        SequenceWriter(ro / "x.h5")


def test_runtime_never_imports_torch():
    code = (
        "import importlib, pkgutil, sys, aerovis_slam\n"
        "for m in pkgutil.walk_packages(aerovis_slam.__path__, 'aerovis_slam.'):\n"
        "    importlib.import_module(m.name)\n"
        "bad = sorted(k for k in sys.modules if k.split('.')[0] in ('torch', 'lightning', 'aerovis_train'))\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_cli_info_and_convert_canonical(seq_path, tmp_path):
    from aerovis_slam.io.cli import main

    path, ev = seq_path
    out = subprocess.run([sys.executable, "-m", "aerovis_slam.io.cli", "info", str(path)], capture_output=True, text=True, check=True)
    info = json.loads(out.stdout)
    assert info["cameras"]["cam0"]["events"] == len(ev) and info["cameras"]["cam0"]["t_first_us"] == int(ev.t[0])
    assert info["imu"] == 480 and info["gt"] == 240
    assert main(["convert", str(path), str(tmp_path / "copy.h5"), "--quiet"]) == 0
    with Sequence(tmp_path / "copy.h5") as s:
        np.testing.assert_array_equal(s.events("cam0").t, ev.t)
        assert s.calib.cameras["cam0"].fx == 30.0
    bad = subprocess.run([sys.executable, "-m", "aerovis_slam.io.cli", "info", str(tmp_path / "missing.raw")], capture_output=True, text=True)
    assert bad.returncode == 2 and "missing.raw: no such file" in bad.stderr and "Traceback" not in bad.stderr


def test_read_benchmark_reads_every_event_of_both_codecs():
    from aerovis_slam.benchmarks import bench_read

    r = bench_read(n_events=300_000, width=64, height=48, repeats=1)  # raises if a reader lost events
    assert set(r) >= {"blosc-lz4", "gzip", "read_speedup", "target_mev_s", "meets_target"}
    for codec in ("blosc-lz4", "gzip"):
        assert r[codec]["read_mev_s"] > 0 and r[codec]["write_mev_s"] > 0
        # sorted µs timestamps and clustered pixels compress: well under the 13 raw bytes per event
        assert 0 < r[codec]["bytes_per_event"] < 13
