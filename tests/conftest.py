"""Shared fixtures. Real recordings come from ``../shared/data`` beside the checkout; tests that
need them skip with a reason when it is absent (a user's fresh clone has no ``../shared``)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


def randomise_batchnorm(net, seed: int = 0) -> None:
    """Non-trivial running statistics in every BatchNorm2d of ``net``, so eval-mode BatchNorm (and its
    folding on export) is exercised (torch imported here: the SLAM tests need no torch)."""
    import torch

    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.copy_(0.1 * torch.randn(m.num_features, generator=g))
                m.running_var.copy_(0.5 + torch.rand(m.num_features, generator=g))


def dead_pid() -> int:
    """The id of a process that has ended (reaped, so the kernel reports it as gone): the owner of a
    build folder left by a killed run (``aerovis_slam.fileio.remove_abandoned``)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ``../shared/data``; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real sensor recordings not found at {SHARED_DATA} (they live beside the checkout, never in it)")
    return SHARED_DATA


def _copy_with_camera_clock(src, dst, delta_us: int, timeshift_us: float) -> Path:
    """A copy of the canonical sequence ``src`` whose cameras run ``delta_us`` late (every event
    time + delta, a whole number of ms), with ``timeshift_us`` as every camera's calibrated
    ``timeshift_cam_imu_us``. IMU and GT keep their times."""
    import shutil

    import h5py

    from aerovis_slam.calib import RigCalibration

    assert delta_us % 1000 == 0, "ms_to_idx stays valid only for whole milliseconds"
    shutil.copy(src, dst)
    with h5py.File(dst, "r+") as f:
        for cam in f["events"]:
            g = f[f"events/{cam}"]
            g["t"][...] = g["t"][...] + delta_us
            g["ms_to_idx"].attrs["t0_ms"] = int(g["ms_to_idx"].attrs["t0_ms"]) + delta_us // 1000
        rig = RigCalibration.from_json(f["calib"].attrs["json"])
        for cam in rig.cameras.values():
            cam.timeshift_cam_imu_us = timeshift_us
        f["calib"].attrs["json"] = rig.to_json()
    return Path(dst)


@pytest.fixture(scope="session")
def tiny_cache(tmp_path_factory) -> Path:
    """A simulator cache folder holding the `tiny` preset (seed 0), generated once per test session
    (~4 s) for the modules that train, export and compare on it; they only read it."""
    from aerovis_slam.sim.cache import ensure_preset

    cache = tmp_path_factory.mktemp("simcache")
    ensure_preset("tiny", str(cache), progress=False)
    return cache


@pytest.fixture(scope="session")
def camera_clock_copy():
    """:func:`_copy_with_camera_clock`: (src, dst, delta_us, timeshift_us) -> dst."""
    return _copy_with_camera_clock
