"""DSEC / TUM-VIE / EDS event HDF5 files: layouts, t_offset, stereo, filters, bad input, conversion."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from aerovis_slam.errors import DataError
from aerovis_slam.events import EventArray
import aerovis_slam.io.canonical  # noqa: F401  (registered beside the reader under test)
from aerovis_slam.io.h5_datasets import H5EventsRecording
from aerovis_slam.io.sequence import Sequence, SequenceWriter
from aerovis_slam.io.source import convert, open_recording


def _events(n, w, h, seed):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 500_000, n)).astype(np.int64)
    return t, rng.integers(0, w, n).astype(np.uint16), rng.integers(0, h, n).astype(np.uint16), rng.integers(0, 2, n).astype(np.uint8)


def _ms_to_idx(t):
    return np.searchsorted(t, np.arange(0, t[-1] // 1000 + 2) * 1000, side="left").astype(np.uint64)


def write_dsec(path, n=4000, seed=0, t_offset=49_599_300_523, compression="gzip"):
    t, x, y, p = _events(n, 640, 480, seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        g = f.create_group("events")
        for k, v in dict(t=t.astype(np.uint32), x=x, y=y, p=p).items():  # DSEC stores t as uint32 relative µs
            g.create_dataset(k, data=v, chunks=(512,), compression=compression)
        f.create_dataset("ms_to_idx", data=_ms_to_idx(t))
        f.create_dataset("t_offset", data=np.int64(t_offset))
    return t + t_offset, x, y, p


def write_tumvie(path, n=3000, seed=1):
    t, x, y, p = _events(n, 1280, 720, seed)
    with h5py.File(path, "w") as f:
        for k, v in dict(t=t, x=x, y=y, p=p.astype(np.int8)).items():
            f.create_dataset(f"events/{k}", data=v)
        f.create_dataset("ms_to_idx", data=_ms_to_idx(t))
    return t, x, y, p


def write_eds(path, n=2000, seed=2):
    t, x, y, p = _events(n, 640, 480, seed)
    with h5py.File(path, "w") as f:
        for k, v in dict(x=x, y=y, t=t, p=np.where(p > 0, 1, -1).astype(np.int8)).items():  # -1/1 polarity
            f.create_dataset(k, data=v)
    return t, x, y, p


def _all(rec, cam, chunk=700):
    return EventArray.concatenate(list(rec.iter_events(cam, chunk)))


def _same(ev, ref):
    t, x, y, p = ref
    np.testing.assert_array_equal(ev.t, t)
    np.testing.assert_array_equal(ev.x, x)
    np.testing.assert_array_equal(ev.y, y)
    np.testing.assert_array_equal(ev.p, p)


def test_dsec_stereo_folder_adds_t_offset(tmp_path):
    left = write_dsec(tmp_path / "left" / "events.h5", seed=3)
    right = write_dsec(tmp_path / "right" / "events.h5", seed=4)
    rec = open_recording(tmp_path)
    assert isinstance(rec, H5EventsRecording) and rec.cameras() == ["cam0", "cam1"]
    assert rec.sensor_size("cam1") == (640, 480)
    _same(_all(rec, "cam0"), left)
    _same(_all(rec, "cam1"), right)
    info = rec.info()
    assert info["cameras"]["cam0"]["t_first_us"] == int(left[0][0]) and info["cameras"]["cam1"]["events"] == 4000
    rec.close()


def test_tumvie_pair_eds_and_file_list(tmp_path):
    l = write_tumvie(tmp_path / "mocap-desk-events_left.h5", seed=5)
    r = write_tumvie(tmp_path / "mocap-desk-events_right.h5", seed=6)
    with open_recording(tmp_path) as rec:
        assert rec.sensor_size("cam0") == (1280, 720)
        _same(_all(rec, "cam0"), l)
        _same(_all(rec, "cam1"), r)
    with H5EventsRecording([tmp_path / "mocap-desk-events_right.h5", tmp_path / "mocap-desk-events_left.h5"]) as rec:
        _same(_all(rec, "cam0"), r)
    eds = write_eds(tmp_path / "eds.h5")
    with open_recording(tmp_path / "eds.h5") as rec:
        assert rec.sensor_size("cam0") == (640, 480) and rec.cameras() == ["cam0"]
        _same(_all(rec, "cam0"), eds)


def test_size_attributes_and_override(tmp_path):
    path = tmp_path / "small.h5"
    t, x, y, p = _events(100, 40, 30, 7)
    with h5py.File(path, "w") as f:
        for k, v in dict(t=t, x=x, y=y, p=p).items():
            f.create_dataset(f"events/{k}", data=v)
        f["events"].attrs["width"], f["events"].attrs["height"] = 40, 30
    with H5EventsRecording(path) as rec:
        assert rec.sensor_size("cam0") == (40, 30)
    with H5EventsRecording(path, sensor_size=(64, 48)) as rec:
        assert rec.sensor_size("cam0") == (64, 48)


def test_probe_ignores_canonical_sequences(tmp_path):
    out = tmp_path / "seq.h5"
    with SequenceWriter(out, sensor_sizes={"cam0": (4, 3)}) as w:
        w.add_events("cam0", EventArray([1, 2], [0, 1], [0, 1], [0, 1]))
    assert type(open_recording(out)).__name__ == "CanonicalRecording"
    with pytest.raises(DataError, match="no event datasets"):
        H5EventsRecording(out)


def test_convert_end_to_end(tmp_path):
    left = write_dsec(tmp_path / "dsec" / "left" / "events.h5", n=2500, seed=8)
    right = write_dsec(tmp_path / "dsec" / "right" / "events.h5", n=2600, seed=9)
    out = tmp_path / "seq.h5"
    summary = convert(open_recording(tmp_path / "dsec"), out, require_calib=False, progress=False)
    assert summary["cameras"]["cam1"]["events"] == 2600
    with Sequence(out) as seq:
        _same(seq.events("cam0"), left)
        _same(seq.events("cam1"), right)
        # The canonical ms index agrees with absolute time.
        t_mid = int(left[0][1200])
        assert seq.index_at("cam0", t_mid) == int(np.searchsorted(left[0], t_mid))


def test_bad_input(tmp_path):
    path = tmp_path / "unsorted.h5"
    t, x, y, p = _events(1000, 640, 480, 10)
    t[600] = t[599] - 5
    with h5py.File(path, "w") as f:
        for k, v in dict(t=t, x=x, y=y, p=p).items():
            f.create_dataset(f"events/{k}", data=v)
        f.create_dataset("t_offset", data=np.int64(0))
    with pytest.raises(DataError, match=r"unsorted.h5: /events/t decreases at index 600"):
        _all(H5EventsRecording(path), "cam0", chunk=256)
    with h5py.File(path, "r+") as f:
        f["events/t"][...] = np.sort(t)
        f["events/x"][10] = 640
    with pytest.raises(DataError, match=r"unsorted.h5: /events: event 10 at pixel \(640, .*outside the 640x480"):
        _all(H5EventsRecording(path), "cam0")
    bad = tmp_path / "lengths.h5"
    with h5py.File(bad, "w") as f:
        for k, v in dict(t=t, x=x[:-1], y=y, p=p).items():
            f.create_dataset(f"events/{k}", data=v)
    with pytest.raises(DataError, match="lengths.h5.*equally long"):
        H5EventsRecording(bad)
    trunc = tmp_path / "trunc.h5"
    write_dsec(trunc)
    data = trunc.read_bytes()
    trunc.write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match="trunc.h5"):
        _all(H5EventsRecording(trunc), "cam0")


def test_dsec_zstd_files_read_through_hdf5plugin(tmp_path):
    zstd = 32015  # the HDF5 filter id of Zstandard (DSEC's files), registered by hdf5plugin
    assert h5py.h5z.filter_avail(zstd)
    ref = write_dsec(tmp_path / "zstd" / "events.h5", seed=5, compression=zstd)
    with H5EventsRecording(tmp_path / "zstd" / "events.h5") as rec:
        _same(_all(rec, "cam0"), ref)


def test_missing_filter_names_the_filter(tmp_path):
    lzo = 305  # the HDF5 filter id of LZO: registered, but in neither h5py nor hdf5plugin
    assert not h5py.h5z.filter_avail(lzo)
    path = tmp_path / "lzo.h5"
    with h5py.File(path, "w") as f:
        for k in ("t", "x", "y", "p"):
            # Nothing is written, so creating the dataset needs no filter; reading it would.
            f.create_dataset(f"events/{k}", shape=(10,), dtype=np.int64, chunks=(5,), compression=lzo, allow_unknown_filter=True)
    with pytest.raises(DataError, match=r"lzo.h5: dataset /events/t is compressed with HDF5 filter 305.*not among hdf5plugin"):
        H5EventsRecording(path)
