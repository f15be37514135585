"""The simulation loop: scene + rig + trajectory -> events, frames, depth, IMU and GT.

Renders all cameras at common, adaptively chosen times. Each step is limited so that no
image point moves more than ``max_flow_px`` pixels (bounded with the standard motion-field
equations from the body velocity and the nearest depth of the last render, evaluated at both
ends of the step) and the room light changes by at most ``C/2`` in log (lights-off ramps),
which keeps ESIM's linear interpolation of log intensity between renders accurate. Frames and
depth maps are the renders that land exactly on the frame clock.

Frames use a fixed exposure and a display gamma (see :func:`tone_map`), so HDR windows
saturate and lights-off segments go dark, as on a frame camera; events see the full range.

Example:
    >>> spec = SequenceSpec("doc", rig="tiny_stereo", duration_s=0.05, frame_rate_hz=40)
    >>> res = simulate(spec)
    >>> sorted(res.events), res.frames["cam0"].shape
    (['cam0', 'cam1'], (3, 48, 64))
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from tqdm import tqdm

from ..calib import RigCalibration
from ..events import EventArray
from ..io.sequence import SequenceWriter
from ..measurements import ImuSamples, PoseSamples
from .events import EventConfig, EventGenerator, log_intensity
from .imu import imu_times_us, simulate_imu
from .rig import load_rig, scale_rig
from .scene import Scene, free_space, make_scene
from .trajectory import Pauses, Trajectory, check_inside, make_trajectory

SIM_VERSION = 1
FRAME_WHITE = 1.0  # radiance that maps to 255 (a white wall under normal room light)
FRAME_GAMMA = 2.2


def tone_map(radiance: np.ndarray) -> np.ndarray:
    """Frame camera response: ``uint8 = round(255 * clip(I / 1.0, 0, 1) ** (1 / 2.2))``.

    A fixed exposure (``I = 1`` is white) and an sRGB-like display gamma.
    """
    x = np.clip(np.asarray(radiance, np.float32) / FRAME_WHITE, 0.0, 1.0) ** (1.0 / FRAME_GAMMA)
    return np.round(255.0 * x).astype(np.uint8)


def vignette(cam, strength: float) -> np.ndarray:
    """float32 (H, W) radiance factor ``1 - strength (1 - cos^4 theta)`` of a pinhole camera (natural
    vignetting: theta is each pixel's angle off the optical axis)."""
    u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
    tan2 = ((u - cam.cx) / cam.fx) ** 2 + ((v - cam.cy) / cam.fy) ** 2
    cos4 = 1.0 / (1.0 + tan2) ** 2
    return (1.0 - strength * (1.0 - cos4)).astype(np.float32)


@dataclass
class SequenceSpec:
    """Everything that defines one simulated sequence (the sequence is a pure function of it).

    Attributes:
        name: sequence name (the file is ``<name>.h5``).
        rig: rig name in ``conf/rig`` or a YAML path.
        rig_scale: resize factor of the rig's cameras.
        scene_seed: seed of the room (see :func:`~aerovis_slam.sim.scene.make_scene`).
        hdr: dim room with a bright window.
        lights_off: ``(t_off_s, t_on_s)`` intervals with the room light at 3 %.
        user_textures: image files for the posters (or ``skimage:NAME`` photographs, see
            :data:`~aerovis_slam.sim.scene.PHOTO_TEXTURES`).
        vignetting: lens fall-off towards the image corners, in [0, 1]: radiance times
            ``1 - vignetting (1 - cos^4 theta)`` (theta the angle off the optical axis), on events and
            frames alike, as a lens does; 0: none.
        trajectory: kind (see :data:`~aerovis_slam.sim.trajectory.TRAJECTORY_KINDS`).
        trajectory_seed: seed of the trajectory.
        loop: end where it started (``handheld``).
        loop_period_s: with ``loop``, the closed path's period (None: ``duration_s``); a shorter
            one retraces the path's start after the return (see
            :func:`~aerovis_slam.sim.trajectory.make_trajectory`).
        speed: motion speed factor.
        pauses: ``(t_stop_s, hold_s)`` stops: the camera comes to a halt at ``t_stop_s``, stands still for
            ``hold_s`` and goes on along its path (:class:`~aerovis_slam.sim.trajectory.Pauses`).
        pause_ramp_s: slowing and speeding-up time around each stop, seconds.
        duration_s: length in seconds.
        frame_rate_hz: frames and depth maps per second and camera (0: none).
        gt_rate_hz: ground-truth pose rate.
        imu_rate_hz: IMU rate (``None``: the rig's ``update_rate``).
        imu_noise: add white noise and bias random walk.
        events: the event camera model.
        max_flow_px: step limit on image motion (ESIM's adaptive sampling).
        max_step_us, min_step_us: bounds on the render step.
        noise_seed: seeds thresholds, event noise and IMU noise.
    """

    name: str
    rig: str = "davis240_stereo"
    rig_scale: float = 1.0
    scene_seed: int = 0
    hdr: bool = False
    lights_off: list = field(default_factory=list)
    user_textures: list = field(default_factory=list)
    vignetting: float = 0.0
    trajectory: str = "handheld"
    trajectory_seed: int = 0
    loop: bool = False
    loop_period_s: float | None = None
    speed: float = 1.0
    pauses: list = field(default_factory=list)
    pause_ramp_s: float = 0.4
    duration_s: float = 4.0
    frame_rate_hz: float = 20.0
    gt_rate_hz: float = 200.0
    imu_rate_hz: float | None = None
    imu_noise: bool = True
    events: EventConfig = field(default_factory=EventConfig)
    max_flow_px: float = 0.5
    max_step_us: int = 5000
    min_step_us: int = 10
    noise_seed: int = 0

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["lights_off"] = [list(x) for x in self.lights_off]
        d["pauses"] = [list(x) for x in self.pauses]
        d["user_textures"] = [str(x) for x in self.user_textures]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "SequenceSpec":
        """The inverse of :meth:`to_dict` (the ``spec`` a simulated sequence's metadata carries).

        Raises:
            ValueError: a field this class does not have, or a missing ``name``.
        """
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown SequenceSpec field(s) {unknown}")
        if "name" not in d:
            raise ValueError("SequenceSpec needs a 'name'")
        d = dict(d)
        if isinstance(d.get("events"), dict):
            d["events"] = EventConfig(**d["events"])
        d["lights_off"] = [tuple(x) for x in d.get("lights_off", [])]
        d["pauses"] = [tuple(x) for x in d.get("pauses", [])]
        return cls(**d)


@dataclass
class SimResult:
    """In-memory outputs of :func:`simulate` (for tests and notebooks; files use :func:`write_sequence`).

    Attributes:
        events: per camera, all events (sorted).
        frame_t: (F,) int64 µs frame times (shared by all cameras).
        frames: per camera uint8 (F, H, W); ``radiance`` float32 (F, H, W) before tone mapping.
        depth: per camera float32 (F, H, W) z-depth in metres.
        imu, gt: the inertial samples and ``T_world_body`` poses.
        stats: timing and counts.
    """

    events: dict[str, EventArray]
    frame_t: np.ndarray
    frames: dict[str, np.ndarray]
    radiance: dict[str, np.ndarray]
    depth: dict[str, np.ndarray]
    imu: ImuSamples
    gt: PoseSamples
    stats: dict


class Simulator:
    """Builds the world of a :class:`SequenceSpec` and steps through it.

    Attributes:
        spec, rig, scene, trajectory: the inputs, resolved.
        generators: per camera :class:`EventGenerator` (thresholds exposed for tests).
    """

    def __init__(self, spec: SequenceSpec, *, scene: Scene | None = None, trajectory: Trajectory | None = None,
                 rig: RigCalibration | None = None):
        self.spec = spec
        rig = rig if rig is not None else load_rig(spec.rig)
        if spec.rig_scale != 1.0:
            rig = scale_rig(rig, spec.rig_scale)
        if spec.imu_rate_hz is not None:
            rig.imu = dataclasses.replace(rig.imu, update_rate=float(spec.imu_rate_hz))
        self.rig = rig
        self.scene = scene if scene is not None else make_scene(
            spec.scene_seed, hdr=spec.hdr, lights_off=[tuple(x) for x in spec.lights_off], user_textures=list(spec.user_textures))
        lo, hi = free_space(self.scene)
        self.trajectory = trajectory if trajectory is not None else make_trajectory(
            spec.trajectory, np.random.default_rng(np.random.SeedSequence([spec.trajectory_seed, 0x7A5])),
            spec.duration_s, lo, hi, loop=spec.loop, speed=spec.speed, loop_period_s=spec.loop_period_s)
        if spec.pauses:
            self.trajectory = dataclasses.replace(self.trajectory, pauses=Pauses(spec.pauses, spec.pause_ramp_s))
        self.cams = list(rig.cameras)
        self.T_body_cam = [rig.cameras[c].T_imu_cam for c in self.cams]
        check_inside(self.trajectory, self.scene, self.T_body_cam, name=spec.name)
        seeds = np.random.SeedSequence([spec.noise_seed, 0xE7E7]).spawn(len(self.cams) + 1)
        self.generators = {c: EventGenerator(rig.cameras[c].width, rig.cameras[c].height, spec.events, np.random.default_rng(s))
                           for c, s in zip(self.cams, seeds[:-1])}
        self._imu_rng = np.random.default_rng(seeds[-1])
        # Normalised image coordinates of a 3x3 grid over each image (corners, edges, centre):
        # the motion field's magnitude is largest at the image border, so these bound it.
        self._grid = {}
        for c in self.cams:
            k = rig.cameras[c]
            us, vs = np.meshgrid([-0.5, (k.width - 1) / 2, k.width - 0.5], [-0.5, (k.height - 1) / 2, k.height - 0.5])
            self._grid[c] = ((us.ravel() - k.cx) / k.fx, (vs.ravel() - k.cy) / k.fy)
        self._gx = np.stack([self._grid[c][0] for c in self.cams])
        self._gy = np.stack([self._grid[c][1] for c in self.cams])
        self._fx = np.array([[rig.cameras[c].fx] for c in self.cams])
        self._fy = np.array([[rig.cameras[c].fy] for c in self.cams])
        self._R_bc = np.stack([T[:3, :3] for T in self.T_body_cam])
        self._p_bc = np.stack([T[:3, 3] for T in self.T_body_cam])
        if not 0.0 <= spec.vignetting <= 1.0:
            raise ValueError(f"{spec.name}: vignetting must be in [0, 1], got {spec.vignetting}")
        self._vignette = {c: vignette(rig.cameras[c], spec.vignetting) for c in self.cams} if spec.vignetting > 0 else None

    # -- geometry ---------------------------------------------------------------------------
    def camera_poses(self, t_s: float) -> list[np.ndarray]:
        """(4, 4) ``T_world_cam`` of every camera at ``t_s``."""
        R, p, _, _ = self.trajectory.kinematics(t_s)
        T_wb = np.eye(4)
        T_wb[:3, :3], T_wb[:3, 3] = R, p
        return [T_wb @ T_bc for T_bc in self.T_body_cam]

    def max_flow(self, t_s: float, z_min: dict[str, float]) -> float:
        """Upper estimate of the image speed (px/s) over all cameras at ``t_s``.

        Motion field of a static point at depth ``Z`` for a camera moving with linear
        velocity ``v`` and angular velocity ``w`` (camera frame), at normalised ``(x, y)``:
        ``x' = (-v_x + x v_z)/Z + x y w_x - (1 + x^2) w_y + y w_z`` and
        ``y' = (-v_y + y v_z)/Z + (1 + y^2) w_x - x y w_y - x w_z``; we use the nearest depth.
        """
        R_wb, _, v_w, w_b = self.trajectory.kinematics(t_s)
        R_bc, p_bc = self._R_bc, self._p_bc  # (C, 3, 3), (C, 3)
        w = w_b @ R_bc  # (C, 3): R_bc^T w_b per camera
        v_wc = v_w + np.cross(w_b, p_bc) @ R_wb.T  # camera-centre velocity, world
        v = np.einsum("cji,cj->ci", R_bc, v_wc @ R_wb)  # (R_wb R_bc)^T v_wc
        x, y = self._gx, self._gy  # (C, 9)
        Z = np.maximum(np.array([z_min[c] for c in self.cams]), 1e-3)[:, None]
        dx = (-v[:, :1] + x * v[:, 2:]) / Z + x * y * w[:, :1] - (1 + x * x) * w[:, 1:2] + y * w[:, 2:]
        dy = (-v[:, 1:2] + y * v[:, 2:]) / Z + (1 + y * y) * w[:, :1] - x * y * w[:, 1:2] - x * w[:, 2:]
        return float(np.sqrt((self._fx * dx) ** 2 + (self._fy * dy) ** 2).max())

    def render(self, t_s: float) -> list[tuple[np.ndarray, np.ndarray]]:
        """(radiance, depth) of every camera at ``t_s``."""
        views = [self.scene.render(self.rig.cameras[c], T, t_s) for c, T in zip(self.cams, self.camera_poses(t_s))]
        if self._vignette is not None:
            views = [(rad * self._vignette[c], dep) for c, (rad, dep) in zip(self.cams, views)]
        return views

    def _step_us(self, t_us: int, z_min: dict[str, float]) -> int:
        spec = self.spec
        t_s = t_us * 1e-6
        half_c = spec.events.threshold / 2

        def limit(tt):
            f = self.max_flow(tt, z_min)
            dl = abs(self.scene.illumination.dlog_gain(tt))
            return min(spec.max_flow_px / f if f > 0 else np.inf, half_c / dl if dl > 0 else np.inf)

        dt = min(limit(t_s), spec.max_step_us * 1e-6)
        dt = min(dt, limit(t_s + dt))  # refine with the motion predicted at the step's end
        return int(np.clip(np.floor(dt * 1e6), spec.min_step_us, spec.max_step_us))

    # -- main loop --------------------------------------------------------------------------
    def run(self, on_events: Callable[[str, EventArray], None], on_frame: Callable[[str, int, np.ndarray, np.ndarray], None],
            *, progress: bool = False, flush_events: int = 1 << 19) -> dict:
        """Step from 0 to the duration, handing events and frames to the callbacks.

        Args:
            on_events: called with ``(cam, EventArray)`` chunks in time order.
            on_frame: called with ``(cam, t_us, radiance float32 (H, W), depth float32 (H, W))``.
            progress: show a tqdm bar over simulated time.
            flush_events: events buffered per camera before ``on_events`` is called.

        Returns:
            stats: ``steps``, ``events`` per camera, ``render_s``, ``events_s``, ``wall_s``.
        """
        spec = self.spec
        t_end = int(round(spec.duration_s * 1e6))
        frame_times = (np.arange(int(np.floor(spec.duration_s * spec.frame_rate_hz + 1e-9)) + 1) * (1e6 / spec.frame_rate_hz)).round().astype(np.int64) if spec.frame_rate_hz > 0 else np.zeros(0, np.int64)
        eps = spec.events.eps
        wall0 = time.perf_counter()
        render_s = events_s = 0.0
        buf = {c: [] for c in self.cams}
        nbuf = {c: 0 for c in self.cams}
        total = {c: 0 for c in self.cams}

        r0 = time.perf_counter()
        views = self.render(0.0)
        render_s += time.perf_counter() - r0
        z_min = {}
        for c, (rad, dep) in zip(self.cams, views):
            self.generators[c].reset(log_intensity(rad, eps), 0)
            z_min[c] = float(dep.min())
        fi = 0
        if len(frame_times) and frame_times[0] == 0:
            for c, (rad, dep) in zip(self.cams, views):
                on_frame(c, 0, rad, dep)
            fi = 1
        t = 0
        steps = 0
        bar = tqdm(total=round(spec.duration_s, 3), unit="sim-s", desc=spec.name, disable=not progress, leave=False,
                   bar_format="{l_bar}{bar}| {n:.2f}/{total:.2f} s [{elapsed}<{remaining}]")
        while t < t_end:
            t1 = t + self._step_us(t, z_min)
            if fi < len(frame_times):
                t1 = min(t1, int(frame_times[fi]))
            t1 = min(t1, t_end)
            r0 = time.perf_counter()
            views = self.render(t1 * 1e-6)
            r1 = time.perf_counter()
            render_s += r1 - r0
            for c, (rad, dep) in zip(self.cams, views):
                ev = self.generators[c].step(log_intensity(rad, eps), t1)
                z_min[c] = float(dep.min())
                if len(ev):
                    buf[c].append(ev)
                    nbuf[c] += len(ev)
                    total[c] += len(ev)
                if nbuf[c] >= flush_events:
                    on_events(c, EventArray.concatenate(buf[c]))
                    buf[c], nbuf[c] = [], 0
            events_s += time.perf_counter() - r1
            if fi < len(frame_times) and t1 == frame_times[fi]:
                for c, (rad, dep) in zip(self.cams, views):
                    on_frame(c, t1, rad, dep)
                fi += 1
            bar.update((t1 - t) * 1e-6)
            t = t1
            steps += 1
        bar.close()
        for c in self.cams:
            if buf[c]:
                on_events(c, EventArray.concatenate(buf[c]))
        return {"steps": steps, "events": total, "render_s": render_s, "events_s": events_s,
                "wall_s": time.perf_counter() - wall0}

    def imu(self) -> ImuSamples:
        """IMU samples at the rig's rate (noise per ``spec.imu_noise``)."""
        return simulate_imu(self.trajectory, self.rig.imu.update_rate, self.rig.imu if self.spec.imu_noise else None, self._imu_rng)

    def gt(self) -> PoseSamples:
        """``T_world_body`` at ``spec.gt_rate_hz``."""
        t_us = imu_times_us(self.spec.duration_s, self.spec.gt_rate_hz)
        return PoseSamples(t_us, self.trajectory.pose7(t_us * 1e-6))

    def meta(self) -> dict:
        return {"generator": "aerovis-sim", "sim_version": SIM_VERSION, "spec": self.spec.to_dict(),
                "trajectory_kind": self.trajectory.kind, "hdr": self.scene.hdr, "scene_planes": len(self.scene.planes),
                "frame_tone_map": f"uint8 = round(255 * clip(I / {FRAME_WHITE}, 0, 1) ** (1 / {FRAME_GAMMA}))",
                "gravity_world": [0.0, 0.0, -9.81], "world_frame": "z up"}


def simulate(spec: SequenceSpec, *, progress: bool = False, simulator: Simulator | None = None) -> SimResult:
    """Run a sequence in memory (small sequences: tests, notebooks)."""
    sim = simulator or Simulator(spec)
    ev = {c: [] for c in sim.cams}
    fr = {c: [] for c in sim.cams}
    ft: list[int] = []

    def on_frame(c, t, rad, dep):
        if c == sim.cams[0]:
            ft.append(t)
        fr[c].append((rad, dep))

    stats = sim.run(lambda c, e: ev[c].append(e), on_frame, progress=progress)

    def stack(c, items, dtype):
        k = sim.rig.cameras[c]
        return np.stack(items).astype(dtype, copy=False) if items else np.zeros((0, k.height, k.width), dtype)

    return SimResult(
        events={c: EventArray.concatenate(v) for c, v in ev.items()},
        frame_t=np.array(ft, np.int64),
        frames={c: stack(c, [tone_map(r) for r, _ in v], np.uint8) for c, v in fr.items()},
        radiance={c: stack(c, [r for r, _ in v], np.float32) for c, v in fr.items()},
        depth={c: stack(c, [d for _, d in v], np.float32) for c, v in fr.items()},
        imu=sim.imu(), gt=sim.gt(), stats=stats)


def write_sequence(spec: SequenceSpec, path: str | os.PathLike, *, progress: bool = False) -> dict:
    """Simulate ``spec`` into a canonical sequence file (atomic: ``.partial`` then rename).

    Returns:
        A summary: name, path, duration_s, events (per camera and total), mean event rate
        (events/s over all cameras), steps, render/events/wall seconds.
    """
    path = Path(path)
    sim = Simulator(spec)
    wall0 = time.perf_counter()
    calib = RigCalibration(sim.rig.cameras, sim.rig.imu)
    with SequenceWriter(path, calib, meta=sim.meta()) as w:
        stats = sim.run(w.add_events, lambda c, t, rad, dep: (w.add_frames(c, t, tone_map(rad)), w.add_frames(c, t, dep, kind="depth")),
                        progress=progress)
        w.set_imu(sim.imu())
        w.set_gt(sim.gt())
    n = sum(stats["events"].values())
    return {"name": spec.name, "path": str(path), "trajectory": spec.trajectory, "rig": spec.rig,
            "resolution": [sim.rig.cameras[sim.cams[0]].width, sim.rig.cameras[sim.cams[0]].height],
            "duration_s": spec.duration_s, "events": n, "events_per_camera": stats["events"],
            "event_rate_mev_s": n / spec.duration_s / 1e6, "steps": stats["steps"],
            "render_s": round(stats["render_s"], 3), "events_s": round(stats["events_s"], 3),
            "wall_s": round(time.perf_counter() - wall0, 3)}
