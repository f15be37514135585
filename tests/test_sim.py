"""Tests of the event-camera simulator (aerovis_slam.sim), on tiny rigs and short durations."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from conftest import dead_pid
from aerovis_slam.errors import DataError
from aerovis_slam.io.sequence import Sequence
from aerovis_slam.sim import (
    EventConfig, SequenceSpec, Simulator, ensure_preset, load_rig, make_scene, preset_specs, simulate,
    video_to_events, write_sequence,
)
from aerovis_slam.sim.cli import main as sim_main
from aerovis_slam.sim.cli import run_preset
from aerovis_slam.sim.rig import RIG_DIR, available_rigs
from aerovis_slam.sim.trajectory import Pauses, Sinusoids, Trajectory, make_trajectory

NO_NOISE = EventConfig(noise=False, refractory_us=0)


def _exp_so3(w: np.ndarray) -> np.ndarray:
    th = np.linalg.norm(w)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th**2 * K @ K


def _log_so3(R: np.ndarray) -> np.ndarray:
    th = np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return v / 2 if th < 1e-9 else v * th / (2 * np.sin(th))


def _quat_to_R(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _pose_T(p7: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = _quat_to_R(p7[3:])
    T[:3, 3] = p7[:3]
    return T


@pytest.fixture(scope="module")
def tiny_file(tmp_path_factory) -> Path:
    """One tiny handheld sequence written through the canonical writer."""
    out = tmp_path_factory.mktemp("simfile") / "tiny.h5"
    spec = SequenceSpec("tiny", rig="tiny_stereo", scene_seed=5, trajectory="handheld", trajectory_seed=5, speed=2.0,
                        duration_s=0.5, frame_rate_hz=10, gt_rate_hz=1000, noise_seed=5)
    write_sequence(spec, out)
    return out


# ---------------------------------------------------------------------------------------------
# events
def test_events_sum_to_log_intensity_change():
    spec = SequenceSpec("ev", rig="tiny_stereo", scene_seed=2, trajectory="handheld", trajectory_seed=2, speed=2.0,
                        duration_s=0.4, frame_rate_hz=10, events=EventConfig(threshold_sigma=0.03, noise=False, refractory_us=0))
    sim = Simulator(spec)
    res = simulate(spec, simulator=sim)
    assert res.frame_t[-1] == 400_000
    for cam in sim.cams:
        gen = sim.generators[cam]
        ev = res.events[cam]
        L = np.log(res.radiance[cam].astype(np.float64) + spec.events.eps)
        h, w = L.shape[1:]
        signed = np.where(ev.p == 1, gen.c_pos[ev.y, ev.x], -gen.c_neg[ev.y, ev.x])
        total = np.zeros((h, w))
        np.add.at(total, (ev.y, ev.x), signed)
        # Each event moves the pixel's reference by its own threshold, and after the last
        # render the residual L - ref lies strictly between -C- and +C+ (else another event
        # would have fired): so the change minus the event sum is within one threshold.
        residual = (L[-1] - L[0]) - total
        assert np.all(residual < gen.c_pos + 1e-9) and np.all(residual > -gen.c_neg - 1e-9)
        assert len(ev) > 1000  # the motion produced a real test
        # The float32 radiance round trip (renders keep float64 logs) costs < 1e-6 in log.
        assert np.all(residual == pytest.approx(L[-1] - gen.ref, abs=1e-5))


def test_timestamps_sorted_inside_and_refractory():
    refr = 500
    spec = SequenceSpec("ts", rig="tiny_stereo", scene_seed=3, trajectory="shake", trajectory_seed=3,
                        duration_s=0.3, frame_rate_hz=0, events=EventConfig(refractory_us=refr, shot_noise_hz=5.0, leak_hz=2.0))
    res = simulate(spec)
    for ev in res.events.values():
        assert len(ev) > 100
        assert np.all(np.diff(ev.t) >= 0)
        assert ev.t[0] >= 0 and ev.t[-1] <= 300_000
        pix = ev.y.astype(np.int64) * 64 + ev.x
        order = np.lexsort((ev.t, pix))
        same = np.diff(pix[order]) == 0
        assert np.all(np.diff(ev.t[order])[same] >= refr)


def test_event_rate_grows_with_speed_and_static_gives_only_noise():
    def count(kind, speed, events):
        spec = SequenceSpec("r", rig="tiny_stereo", scene_seed=4, trajectory=kind, trajectory_seed=4, speed=speed,
                            duration_s=0.5, frame_rate_hz=0, events=events)
        return simulate(spec).events

    slow = sum(len(e) for e in count("handheld", 0.5, NO_NOISE).values())
    fast = sum(len(e) for e in count("handheld", 2.0, NO_NOISE).values())
    assert fast > 2 * slow > 0
    # A static camera in a static, steadily lit scene renders identical images: no signal.
    assert sum(len(e) for e in count("static", 1.0, NO_NOISE).values()) == 0
    noisy = EventConfig(noise=True, shot_noise_hz=2.0, leak_hz=0.0, refractory_us=0)
    n = sum(len(e) for e in count("static", 1.0, noisy).values())
    expected = 2.0 * 64 * 48 * 0.5 * 2  # rate x pixels x seconds x cameras = 6144
    assert abs(n - expected) < 5 * np.sqrt(expected)  # Poisson count: 5 sigma


def test_lights_off_gives_off_then_on_events():
    spec = SequenceSpec("dark", rig="tiny_stereo", scene_seed=8, trajectory="static", duration_s=1.0, frame_rate_hz=0,
                        lights_off=[(0.2, 0.7)], events=NO_NOISE)
    ev = simulate(spec).events["cam0"]
    # The ramps (0.25 s) are C2 smoothsteps from 100 % to 3 % light: log change ~3.5, so
    # ~17 OFF events per lit pixel around t = 0.2-0.45 s and as many ON around 0.7-0.95 s.
    off, on = ev.p == 0, ev.p == 1
    assert off.sum() > 10 * 64 * 48 and abs(int(on.sum()) - int(off.sum())) < 0.05 * off.sum()
    # Crossing times are interpolated within a render step, and steps grow to max_step_us
    # where the ramp flattens out: allow one step of slack at either end.
    slack = spec.max_step_us
    assert ev.t[off].min() >= 200_000 - slack and ev.t[off].max() <= 450_000 + slack
    assert ev.t[on].min() >= 700_000 - slack and ev.t[on].max() <= 950_000 + slack


def test_video_to_events_tracks_log_intensity():
    h, w = 8, 12
    xs = np.arange(w)[None, :]
    frames = np.stack([np.clip(40 + 180 * (0.5 + 0.5 * np.sin((xs + k) / 2.0 + np.arange(h)[:, None] / 3)), 0, 255) for k in range(6)]).astype(np.uint8)
    t = np.arange(6) * 10_000
    cfg = EventConfig(threshold_sigma=0.0, noise=False, refractory_us=0)
    ev = video_to_events(frames, t, cfg)
    L = np.log((frames.astype(np.float64) / 255) ** 2.2 + cfg.eps)
    total = np.zeros((h, w))
    np.add.at(total, (ev.y, ev.x), np.where(ev.p == 1, 0.2, -0.2))
    assert np.all(np.abs((L[-1] - L[0]) - total) < 0.2 + 1e-9)
    assert np.all(np.diff(ev.t) >= 0) and ev.t.min() >= 0 and ev.t.max() <= t[-1]


# ---------------------------------------------------------------------------------------------
# IMU and poses
def test_imu_integrates_to_gt():
    rate = 1000.0
    spec = SequenceSpec("imu", rig="tiny_stereo", scene_seed=6, trajectory="handheld", trajectory_seed=6, speed=2.0,
                        duration_s=1.0, imu_rate_hz=rate, imu_noise=False, gt_rate_hz=rate)
    sim = Simulator(spec)
    imu, gt, traj = sim.imu(), sim.gt(), sim.trajectory
    assert np.array_equal(imu.t, gt.t)
    dt = 1.0 / rate
    T0 = _pose_T(gt.pose[0])
    R, p, v = T0[:3, :3], T0[:3, 3].copy(), traj.position(np.array([0.0]), 1)[0]
    g = np.array([0, 0, -9.81])
    err_p = err_r = 0.0
    for k in range(len(imu) - 1):
        a0 = R @ imu.acc[k] + g
        R1 = R @ _exp_so3(0.5 * (imu.gyro[k] + imu.gyro[k + 1]) * dt)
        a1 = R1 @ imu.acc[k + 1] + g
        p = p + v * dt + (2 * a0 + a1) / 6 * dt * dt  # exact for linearly varying acceleration
        v = v + 0.5 * (a0 + a1) * dt
        R = R1
        Tg = _pose_T(gt.pose[k + 1])
        err_p = max(err_p, np.linalg.norm(p - Tg[:3, 3]))
        err_r = max(err_r, np.linalg.norm(_log_so3(Tg[:3, :3].T @ R)))
    # Trapezoidal integration errs by T dt^2 / 12 * max|f''| over a time T: for the rotation
    # f = omega (plus a commutator term of the same order), for the velocity f = a = p'' (so
    # f'' = p''''); the position error integrates the velocity error and the acceleration
    # error |acc| * rotation error. Bounds from the trajectory's analytic derivatives, x10.
    ts = np.linspace(0, 1, 2001)
    w = traj.angular_velocity(ts)
    w2 = np.abs(np.gradient(np.gradient(w, ts, axis=0), ts, axis=0)).max() + np.linalg.norm(w, axis=1).max() ** 3
    p4 = np.linalg.norm(traj.position(ts, 4), axis=1).max()
    tol_r = 10 * dt**2 / 12 * w2
    tol_p = 10 * (dt**2 / 12 * p4 + 0.5 * 20.0 * tol_r / 10)
    print(f"rotation error {err_r:.2e} rad (bound {tol_r:.2e}), position error {err_p:.2e} m (bound {tol_p:.2e})")
    assert err_r < tol_r, (err_r, tol_r)
    assert err_p < tol_p, (err_p, tol_p)
    assert tol_p < 1e-3 and tol_r < 1e-4  # the bounds are tight enough to mean something


def test_gyro_matches_gt_angular_velocity():
    rate = 1000.0
    spec = SequenceSpec("gyro", rig="tiny_stereo", scene_seed=7, trajectory="shake", trajectory_seed=7,
                        duration_s=2.0, imu_rate_hz=rate, imu_noise=False, gt_rate_hz=rate)
    sim = Simulator(spec)
    imu, gt = sim.imu(), sim.gt()
    Rs = [_quat_to_R(q) for q in gt.pose[:, 3:]]
    w_fd = np.array([_log_so3(Rs[k].T @ Rs[k + 1]) * rate for k in range(len(Rs) - 1)])
    w_mid = 0.5 * (imu.gyro[:-1] + imu.gyro[1:])
    peak = np.degrees(np.linalg.norm(imu.gyro, axis=1).max())
    assert peak > 250  # aggressive shaking: several hundred deg/s
    # log(R_k^T R_k+1)/dt equals the mean rate over the interval up to O(dt^2 |w''|) terms
    # (~(2 pi 5 Hz)^2 x 5 rad/s x 1e-6 / 12 ~ 4e-4 rad/s at this shake); 1e-2 leaves margin.
    assert np.abs(w_fd - w_mid).max() < 1e-2


def test_imu_noise_statistics():
    spec = SequenceSpec("n", rig="tiny_stereo", trajectory="static", duration_s=2.0, imu_rate_hz=1000.0, imu_noise=True)
    sim = Simulator(spec)
    exact = Simulator(SequenceSpec("n", rig="tiny_stereo", trajectory="static", duration_s=2.0, imu_rate_hz=1000.0,
                                   imu_noise=False)).imu()
    noisy = sim.imu()
    sd = np.std(np.diff(noisy.gyro - exact.gyro, axis=0), axis=0) / np.sqrt(2)  # white part dominates diffs
    expected = sim.rig.imu.gyroscope_noise_density * np.sqrt(1000.0)
    assert np.allclose(sd, expected, rtol=0.1)


def test_depth_and_poses_are_consistent(tiny_file):
    with Sequence(tiny_file) as seq:
        calib, gt = seq.calib, seq.gt
        ft = seq.frame_times("cam0", "depth")
        i, j = 0, len(ft) - 1  # first cam0 frame vs last cam1 frame (0.5 s later)
        d0 = seq.frame("cam0", i, "depth").astype(np.float64)
        d1 = seq.frame("cam1", j, "depth").astype(np.float64)
    c0, c1 = calib.cameras["cam0"], calib.cameras["cam1"]
    T_w_b0 = _pose_T(gt.pose[np.searchsorted(gt.t, ft[i])])
    T_w_b1 = _pose_T(gt.pose[np.searchsorted(gt.t, ft[j])])
    T_w_c0, T_w_c1 = T_w_b0 @ c0.T_imu_cam, T_w_b1 @ c1.T_imu_cam
    h, w = d0.shape
    vv, uu = np.mgrid[0:h, 0:w]

    def backproject(d, cam, T):
        pc = np.stack([(uu - cam.cx) / cam.fx * d, (vv - cam.cy) / cam.fy * d, d], -1)
        return pc @ T[:3, :3].T + T[:3, 3]

    W1 = backproject(d1, c1, T_w_c1)
    errs = []
    for v in range(2, h - 2, 3):
        for u in range(2, w - 2, 3):
            X = backproject(d0, c0, T_w_c0)[v, u]
            pc = np.linalg.inv(T_w_c1) @ np.append(X, 1)
            q = np.array([c1.fx * pc[0] / pc[2] + c1.cx, c1.fy * pc[1] / pc[2] + c1.cy])
            u0, v0 = int(np.floor(q[0])), int(np.floor(q[1]))
            if pc[2] <= 0 or not (1 <= u0 < w - 2 and 1 <= v0 < h - 2):
                continue
            # Skip depth edges in either view: there a sub-pixel shift changes the surface.
            patch0, patch1 = d0[v - 1:v + 2, u - 1:u + 2], d1[v0 - 1:v0 + 3, u0 - 1:u0 + 3]
            if np.ptp(np.diff(patch0, axis=1)) > 0.01 * d0[v, u] or np.ptp(np.diff(patch1, axis=1)) > 0.01 * d1[v0, u0] \
                    or np.ptp(np.diff(patch1, axis=0)) > 0.01 * d1[v0, u0]:
                continue
            # Find where cam1's back-projected surface reaches X: on a plane, the world point
            # is a smooth function of the pixel, linear to ~1e-3 px over one pixel.
            J = np.stack([W1[v0, u0 + 1] - W1[v0, u0], W1[v0 + 1, u0] - W1[v0, u0]], 1)
            delta, *_ = np.linalg.lstsq(J, X - W1[v0, u0], rcond=None)
            errs.append(np.linalg.norm(np.array([u0, v0]) + delta - q))
    errs = np.array(errs)
    assert len(errs) > 20
    # float32 depth (7 significant digits) and the local linearisation leave << 0.05 px.
    assert np.median(errs) < 0.01 and np.percentile(errs, 90) < 0.05


def test_file_contents(tiny_file):
    with Sequence(tiny_file) as seq:
        s = seq.summary()
        assert set(s["cameras"]) == {"cam0", "cam1"}
        for cam in ("cam0", "cam1"):
            assert s["cameras"][cam]["frames"] == 6 and s["cameras"][cam]["depth"] == 6
            assert seq.frame(cam, 0).dtype == np.uint8 and seq.frame(cam, 0, "depth").dtype == np.float32
        assert s["imu"] == 501 and s["gt"] == 501  # tiny rig IMU at 1 kHz, GT at 1 kHz
        calib = seq.calib
        assert calib.imu is not None and calib.imu.update_rate == 1000.0
        assert all(c.distortion_model == "none" for c in calib.cameras.values())
        assert seq.meta["spec"]["trajectory"] == "handheld"


# ---------------------------------------------------------------------------------------------
# scenes, rigs, trajectories
def test_rigs_load():
    assert {"davis240_stereo", "prophesee640_stereo", "drone424", "tiny_stereo"} <= set(available_rigs())
    drone = load_rig("drone424")
    c0, c1 = drone.cameras["cam0"], drone.cameras["cam1"]
    assert (c0.width, c0.height) == (424, 240)
    assert np.degrees(2 * np.arctan(c0.width / 2 / c0.fx)) == pytest.approx(110, abs=0.5)
    assert np.linalg.norm(c0.T_imu_cam[:3, 3] - c1.T_imu_cam[:3, 3]) == pytest.approx(0.074)


def test_rig_missing_field_names_file_and_field(tmp_path):
    d = yaml.safe_load((RIG_DIR / "tiny_stereo.yaml").read_text())
    del d["cameras"]["cam1"]["fx"]
    bad = tmp_path / "bad_rig.yaml"
    bad.write_text(yaml.safe_dump(d))
    with pytest.raises(DataError, match=r"bad_rig\.yaml.*cam1.*'fx'"):
        load_rig(bad)
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(DataError, match="fx"):
        write_sequence(SequenceSpec("x", rig=str(bad), duration_s=0.1), out / "x.h5")
    assert list(out.iterdir()) == []


def test_scenes_vary_with_seed_and_hdr_spans_decades():
    a, b = make_scene(10), make_scene(11)
    assert len(a.planes) != len(b.planes) or not np.allclose(a.room_hi, b.room_hi)
    hdr = make_scene(12, hdr=True)
    rad = [hdr.textures[p.texture] * p.gain * (1 if p.emissive else hdr.illumination.ambient) for p in hdr.planes]
    lo, hi = min(r.min() for r in rad), max(r.max() for r in rad)
    assert np.log10(hi / lo) > 3.5


def test_unreadable_texture_is_reported(tmp_path):
    bad = tmp_path / "not_an_image.png"
    bad.write_text("hello")
    with pytest.raises(DataError, match="not_an_image.png.*cannot read texture"):
        make_scene(0, user_textures=[bad])


def test_trajectory_leaving_the_room_is_an_error():
    scene = make_scene(1)
    far = float(scene.room_hi[0]) + 2.0
    traj = Trajectory("slider", 1.0, [Sinusoids(0.0, far), Sinusoids(0.0), Sinusoids(1.4)], [Sinusoids(0.0)] * 3)
    with pytest.raises(DataError, match="leaves the free space"):
        Simulator(SequenceSpec("out", rig="tiny_stereo", duration_s=1.0), scene=scene, trajectory=traj)


def test_every_kind_stays_inside_and_bench_names():
    names = [s.name for s in preset_specs("bench")]
    for prefix in ("handheld_", "shake_", "spin_hdr_", "drone8_", "slider_"):
        assert any(n.startswith(prefix) for n in names)
    for spec in preset_specs("bench") + preset_specs("train")[:12]:
        sim = Simulator(spec)  # raises if a trajectory leaves the free space
        if spec.name == "handheld_loop":
            # back at its start after the 10 s loop, then along its first 2 s again, exactly
            period = spec.loop_period_s
            assert period == pytest.approx(10.0) and spec.duration_s == pytest.approx(12.0)
            t = np.linspace(0.0, spec.duration_s - period, 41)
            np.testing.assert_allclose(sim.trajectory.pose7(t + period), sim.trajectory.pose7(t), atol=1e-9)
            np.testing.assert_allclose(sim.trajectory.angular_velocity(t + period), sim.trajectory.angular_velocity(t), atol=1e-9)


def test_loop_period_of_a_handheld_trajectory():
    lo, hi = np.array([-2.0, -2.0, 0.5]), np.array([2.0, 2.0, 2.0])
    traj = make_trajectory("handheld", np.random.default_rng(3), 5.0, lo, hi, loop=True, loop_period_s=4.0)
    t = np.linspace(0.0, 1.0, 11)
    np.testing.assert_allclose(traj.pose7(t + 4.0), traj.pose7(t), atol=1e-9)
    np.testing.assert_allclose(traj.position(t + 4.0, 1), traj.position(t, 1), atol=1e-9)  # velocities too: the IMU repeats
    # None: the period is the duration (the trajectory ends where it started), as before
    whole = make_trajectory("handheld", np.random.default_rng(3), 5.0, lo, hi, loop=True)
    np.testing.assert_allclose(whole.pose7(np.array([5.0])), whole.pose7(np.array([0.0])), atol=1e-9)
    for bad in (0.0, 6.0):
        with pytest.raises(DataError, match=r"loop_period_s must lie in \(0, duration_s = 5.0\]"):
            make_trajectory("handheld", np.random.default_rng(3), 5.0, lo, hi, loop=True, loop_period_s=bad)


def test_a_pause_holds_the_camera_still_and_then_goes_on_along_its_path():
    """``Pauses``: the camera slows to a halt over ``ramp_s``, stands still for ``hold_s`` and then
    follows the unpaused path ``ramp_s + hold_s`` late (the warp's two ramps each lose ``ramp_s / 2``).
    The IMU at rest reads zero rotation and gravity's length, and velocity and acceleration are the
    derivatives of the position through the warp (finite differences: O(h^2) errors, ~1e-6 here)."""
    lo, hi = np.array([-2.0, -2.0, 0.5]), np.array([2.0, 2.0, 2.0])
    free = make_trajectory("handheld", np.random.default_rng(4), 6.0, lo, hi, speed=2.0)
    stop, hold, ramp = 2.0, 1.5, 0.4
    paused = dataclasses.replace(free, pauses=Pauses([(stop, hold)], ramp))
    before = np.linspace(0.0, stop - ramp, 50)
    np.testing.assert_allclose(paused.pose7(before), free.pose7(before), atol=1e-12)
    after = np.linspace(stop + hold + ramp, 6.0, 50)
    np.testing.assert_allclose(paused.pose7(after), free.pose7(after - ramp - hold), atol=1e-9)
    held = np.linspace(stop, stop + hold, 50)
    np.testing.assert_allclose(paused.pose7(held), np.repeat(paused.pose7(np.array([stop])), 50, axis=0), atol=1e-12)
    assert np.abs(paused.position(held, 1)).max() < 1e-12 and np.abs(paused.angular_velocity(held)).max() < 1e-12
    t = np.linspace(0.0, 6.0, 60001)
    h = t[1] - t[0]
    p, v, a = paused.position(t), paused.position(t, 1), paused.position(t, 2)
    scale_v, scale_a = np.abs(v).max(), np.abs(a).max()
    assert np.abs(np.gradient(p, h, axis=0) - v)[1:-1].max() < 1e-5 * scale_v
    assert np.abs(np.gradient(v, h, axis=0) - a)[1:-1].max() < 1e-4 * scale_a  # no jump: the warp is C2
    R, _, v1, w1 = paused.kinematics(stop + 0.5 * hold)
    assert np.abs(v1).max() < 1e-12 and np.abs(w1).max() < 1e-12
    # the simulated IMU during the hold: no rotation, specific force of gravity's length (noise-free)
    spec = SequenceSpec("pause", rig="tiny_stereo", trajectory="handheld", trajectory_seed=4, scene_seed=4, duration_s=3.0,
                        pauses=[(1.0, 1.0)], imu_rate_hz=200.0, imu_noise=False)
    assert SequenceSpec.from_dict(json.loads(json.dumps(spec.to_dict()))) == spec
    sim = Simulator(spec)
    imu = sim.imu()
    rest = (imu.t >= 1.0e6) & (imu.t <= 2.0e6)
    assert np.abs(imu.gyro[rest]).max() < 1e-9
    np.testing.assert_allclose(np.linalg.norm(imu.acc[rest], axis=1), 9.81, atol=1e-9)
    moving = np.linalg.norm(imu.gyro[imu.t < 0.5e6], axis=1)
    assert moving.min() > 1e-3  # the unpaused part does move
    with pytest.raises(DataError, match="pauses"):
        Pauses([(0.2, 1.0)], 0.4)  # its ramp would start before t = 0


# ---------------------------------------------------------------------------------------------
# CLI, determinism, cache
def _datasets(path: Path) -> dict:
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
        out["/calib"] = f["calib"].attrs["json"]
        out["/meta"] = f.attrs["meta"]
    return out


def test_preset_is_deterministic(tmp_path):
    a = run_preset("tiny", tmp_path / "a", seed=3, duration=0.2, progress=False)
    run_preset("tiny", tmp_path / "b", seed=3, duration=0.2, progress=False)
    assert json.loads((tmp_path / "a" / "summary.json").read_text())["sequences"][0]["events"] > 0
    for row in a["sequences"]:
        da, db = _datasets(tmp_path / "a" / row["path"]), _datasets(tmp_path / "b" / row["path"])
        assert da.keys() == db.keys()
        for k in da:
            assert np.array_equal(da[k], db[k]), k
    c = run_preset("tiny", tmp_path / "c", seed=4, duration=0.2, progress=False)
    assert c["total_events"] != a["total_events"]


def test_cli_errors_are_one_line_and_leave_nothing(tmp_path, capsys):
    assert sim_main(["nosuchpreset", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "unknown preset 'nosuchpreset'" in err and "Traceback" not in err
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    assert sim_main(["tiny", str(blocker / "sub"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "cannot create output folder" in err and err.count("\n") == 1
    bad_tex = tmp_path / "broken.jpg"
    bad_tex.write_bytes(b"\xff\xd8 not really a jpeg")
    assert sim_main(["tiny", str(tmp_path / "t"), "--quiet", "--textures", str(bad_tex)]) == 2
    err = capsys.readouterr().err
    assert "broken.jpg" in err and "cannot read texture" in err and "Traceback" not in err
    assert not (tmp_path / "t").exists()
    # A failure after events were written leaves neither the file nor its .partial.
    out = tmp_path / "crash"
    out.mkdir()

    def boom(self):
        raise DataError(None, "simulated failure")

    orig = Simulator.imu
    Simulator.imu = boom
    try:
        with pytest.raises(DataError):
            write_sequence(SequenceSpec("c", rig="tiny_stereo", duration_s=0.05), out / "c.h5")
    finally:
        Simulator.imu = orig
    assert list(out.iterdir()) == []


def test_cli_subprocess_entry_point(tmp_path):
    r = subprocess.run([sys.executable, "-m", "aerovis_slam.sim.cli", "bench", str(tmp_path), "--only", "nope", "--quiet"],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "no sequence(s) ['nope']" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the parent-death signal is Linux's (prctl)")
def test_workers_end_with_a_killed_parent(tmp_path):
    """A generation stopped by SIGTERM (a scheduler, ``timeout``) cannot shut its pool down; its
    worker processes must end with it instead of simulating the queued sequences on at full CPU."""
    import signal

    proc = subprocess.Popen([sys.executable, "-m", "aerovis_slam.sim.cli", "tiny", str(tmp_path / "out"), "--duration", "6",
                             "--workers", "2", "--quiet"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    children_file = Path(f"/proc/{proc.pid}/task/{proc.pid}/children")
    children: set[int] = set()
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and proc.poll() is None:
        children = {int(c) for c in children_file.read_text().split()} if children_file.exists() else set()
        if len(children) >= 3:  # the two workers and multiprocessing's resource tracker
            break
        time.sleep(0.2)
    assert proc.poll() is None and len(children) >= 3, "the workers never started"
    time.sleep(2.0)  # both workers are simulating now
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=30)
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline and any(Path(f"/proc/{c}").exists() for c in children):
        time.sleep(0.2)
    alive = [c for c in children if Path(f"/proc/{c}").exists() and "Z" not in Path(f"/proc/{c}/stat").read_text().split()[2]]
    assert alive == [], f"worker processes {alive} outlived their parent"


def test_parallel_generation_matches_serial(tmp_path):
    """--workers changes only the speed: each sequence draws on its own seeds, so every dataset of
    every file is bit-identical, and the summary keeps the preset order."""
    serial = run_preset("tiny", tmp_path / "serial", duration=0.2, progress=False, workers=1)
    parallel = run_preset("tiny", tmp_path / "parallel", duration=0.2, progress=False, workers=2)
    assert [r["name"] for r in parallel["sequences"]] == [r["name"] for r in serial["sequences"]]
    assert parallel["total_events"] == serial["total_events"] > 0
    for row in serial["sequences"]:
        with h5py.File(tmp_path / "serial" / row["path"]) as fa, h5py.File(tmp_path / "parallel" / row["path"]) as fb:
            names: list[str] = []
            fa.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) else None)
            assert {"events/cam1/x", "frames/cam0/image", "depth/cam1/depth", "imu/acc", "gt/pose"} <= set(names)
            for n in names:
                np.testing.assert_array_equal(fa[n][()], fb[n][()], err_msg=f"{row['name']}: {n}")
    r = subprocess.run([sys.executable, "-m", "aerovis_slam.sim.cli", "tiny", str(tmp_path / "w0"), "--workers", "0"],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "--workers must be at least 1, got 0" in r.stderr
    assert not (tmp_path / "w0").exists()


def _short_generation(monkeypatch) -> None:
    """Make ensure_preset generate presets 0.1 s per sequence long, to keep the tests fast."""
    import aerovis_slam.sim.cli as cli

    orig = cli.run_preset
    monkeypatch.setattr(cli, "run_preset", lambda name, out, seed=0, progress=True, workers=None: orig(name, out, seed=seed, duration=0.1, progress=False,
                                                                                                 workers=workers))


def test_ensure_preset_caches(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("AEROVIS_CACHE", str(tmp_path / "envcache"))
    from aerovis_slam.sim import cache

    assert cache.cache_root() == tmp_path / "envcache" / "sim"
    _short_generation(monkeypatch)
    p = ensure_preset("tiny", seed=1)
    assert p == tmp_path / "envcache" / "sim" / "tiny-seed1-v1" and (p / "summary.json").is_file()
    assert [x.name for x in p.parent.iterdir()] == ["tiny-seed1-v1"]  # no temp folder left
    t0 = time.perf_counter()
    assert ensure_preset("tiny", seed=1) == p
    assert time.perf_counter() - t0 < 0.5
    q = ensure_preset("tiny", cache_dir=str(tmp_path / "explicit"), seed=1)
    assert q == tmp_path / "explicit" / "tiny-seed1-v1"
    # the OpenCV that drew the scenes' text is on record; a cache made with another one is used as
    # it is, with one note (its text textures may differ from a regeneration's)
    import cv2

    summary = json.loads((q / "summary.json").read_text())
    assert summary["opencv"] == cv2.__version__ and summary["environment"]["packages"]["numpy"] == np.__version__
    capsys.readouterr()
    summary["opencv"] = "4.0.0"
    (q / "summary.json").write_text(json.dumps(summary))
    before = {f.name: f.stat().st_mtime_ns for f in q.iterdir()}
    assert ensure_preset("tiny", cache_dir=str(tmp_path / "explicit"), seed=1) == q
    assert ensure_preset("tiny", cache_dir=str(tmp_path / "explicit"), seed=1) == q
    err = capsys.readouterr().err
    assert err.count("was generated with OpenCV 4.0.0") == 1 and f"OpenCV {cv2.__version__} is installed" in err
    assert {f.name: f.stat().st_mtime_ns for f in q.iterdir()} == before  # nothing regenerated
    with pytest.raises(DataError, match="unknown preset"):
        ensure_preset("nope", cache_dir=str(tmp_path / "x"))
    assert not (tmp_path / "x").exists()
    # a revised preset (bench: handheld_loop retraces its start since revision 2) has a folder of its
    # own, so a cache of the earlier sequences is never taken for the new ones
    assert cache.preset_dir("bench", 0) == tmp_path / "envcache" / "sim" / "bench-seed0-v1r2"
    assert cache.preset_dir("tiny", 3, tmp_path / "y") == tmp_path / "y" / "tiny-seed3-v1"


def test_remove_abandoned_deletes_only_folders_of_ended_generations(tmp_path, capsys):
    from aerovis_slam import fileio
    from aerovis_slam.sim import cache

    final = cache.preset_dir("tiny", 1, tmp_path)
    host, dead = fileio._host(), dead_pid()
    two_hours_ago = time.time() - 2 * 3600

    def folder(name: str, mib: int = 0, mtime: float | None = None) -> Path:
        d = tmp_path / name
        d.mkdir()
        (d / "seq.h5.partial").write_bytes(b"\0" * (mib << 20))
        if mtime is not None:
            for f in (d / "seq.h5.partial", d):
                os.utime(f, (mtime, mtime))
        return d

    gone = [
        folder(f".tiny-seed1-v1.{host}-{dead}.abc123.tmp", mib=1),     # this host, its process ended
        folder(".tiny-seed1-v1.k2j4h5g6.tmp", mtime=two_hours_ago),          # an earlier version's name, quiet for 2 h
        folder(f".tiny-seed1-v1.other-host-{dead}.x1.tmp", mtime=two_hours_ago),  # another host's, quiet for 2 h
    ]
    kept = [
        folder(f".tiny-seed1-v1.{host}-{os.getpid()}.def456.tmp", mtime=two_hours_ago),  # a live process's, however quiet
        folder(".tiny-seed1-v1.q9w8e7r6.tmp"),                          # an earlier version's name, changed just now
        folder(f".tiny-seed1-v1.other-host-{dead}.x2.tmp"),             # another host's, changed just now
        folder(f".tiny-seed2-v1.{host}-{dead}.ghi789.tmp"),             # another preset's: its own calls sweep it
    ]
    assert sorted(fileio.remove_abandoned(final)) == sorted(gone)
    assert all(d.is_dir() for d in kept) and not any(d.exists() for d in gone)
    err = capsys.readouterr().err
    assert err.count("aerovis: removed") == 3 and "(1.0 MiB)" in err
    assert fileio.remove_abandoned(final) == []
    assert fileio.remove_abandoned(cache.preset_dir("tiny", 0, tmp_path / "absent")) == []


def test_ensure_preset_removes_the_folder_of_a_killed_generation(tmp_path, monkeypatch, capsys):
    """SIGKILL runs no cleanup: the next call for the preset deletes what the killed one left."""
    from aerovis_slam import fileio

    code = f"from aerovis_slam.sim.cache import ensure_preset; ensure_preset('tiny', cache_dir={str(tmp_path)!r}, progress=False, workers=1)"
    proc = subprocess.Popen([sys.executable, "-c", code])
    pattern = ".tiny-seed0-v1.*.tmp"
    deadline = time.monotonic() + 120
    while not list(tmp_path.glob(pattern)) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.kill()
    proc.wait()
    left = list(tmp_path.glob(pattern))
    assert len(left) == 1 and f".{fileio._host()}-{proc.pid}." in left[0].name
    _short_generation(monkeypatch)
    assert ensure_preset("tiny", cache_dir=str(tmp_path), progress=False) == tmp_path / "tiny-seed0-v1"
    assert [p.name for p in tmp_path.iterdir()] == ["tiny-seed0-v1"]
    assert f"aerovis: removed {left[0]}" in capsys.readouterr().err
