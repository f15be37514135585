"""Perfect keypoint tracks from the simulator's ground truth: how accurate the runtime would be with a
detector whose every track follows one scene point, with pixel noise of a chosen size.

A diagnostic for detector research (``aerovis-slam run --oracle-noise-px X``): it separates what the
keypoints cost from what the estimator, the IMU and the matching structure cost. A sequence written
by ``aerovis-sim`` carries the spec it was generated from (``meta.spec``), so the exact scene and
trajectory can be rebuilt and rendered at any time. A landmark's scene point is fixed when the oracle
first sees the landmark: its first observation (the left one where both cameras see it) is
back-projected with the rendered z-depth at that time and the true camera pose. From then on every
observation of that landmark is the point's exact projection at the true pose, plus Gaussian noise of
``noise_px`` per axis, with an isotropic noise shape (the edge-shaped covariance of
:func:`~aerovis_slam.slam.frontend.edge_shapes` models a detector error the oracle does not have).

What stays the frontend's: which keypoints exist, which match which landmark (RANSAC runs on the
detector's own positions), which frames become keyframes, and loop closure (it verifies with the
detector's keypoints). Observations whose first sighting hits no surface (a keypoint on the sky), or
whose point projects behind the camera or outside the image later, are dropped and counted.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..geometry import invert_T, project, sample_depth_nearest, transform_points, unproject
from .backend import Observations
from .cameras import StereoCameras


def oracle_spec(sequence: str | os.PathLike, noise_px: float = 0.0):
    """The :class:`~aerovis_slam.sim.simulator.SequenceSpec` that wrote ``sequence``, checked for the oracle.

    Raises:
        DataError: ``noise_px`` below 0, a file without a simulator spec (a recording: there is no
            scene to render), or one written by another simulator version (its scene would not be
            the one rebuilt here).
    """
    from ..io.sequence import Sequence
    from ..sim.simulator import SIM_VERSION, SequenceSpec

    _check_noise(noise_px)
    path = Path(sequence)
    with Sequence(path) as seq:
        meta = dict(seq.meta)
    if meta.get("generator") != "aerovis-sim" or not isinstance(meta.get("spec"), dict):
        raise DataError(path, "field meta.spec missing: perfect keypoint tracks need a sequence written by aerovis-sim "
                              "(its scene is re-rendered for the true depth); recordings have none")
    if meta.get("sim_version") != SIM_VERSION:
        raise DataError(path, f"field meta.sim_version is {meta.get('sim_version')!r}, this simulator is version {SIM_VERSION}: "
                              "its scene would differ from the one that made the events")
    try:
        return SequenceSpec.from_dict(meta["spec"])
    except (TypeError, ValueError) as exc:
        raise DataError(path, f"field meta.spec is not a simulator spec ({exc})") from None


def check_diagnostics(oracle_noise_px: float | None, measure_keypoint_errors: bool) -> None:
    """The two diagnostics of this module exclude each other (perfect tracks have no keypoint error).

    Raises:
        DataError: both are asked for.
    """
    if oracle_noise_px is not None and measure_keypoint_errors:
        raise DataError(None, "the keypoint-error measurement (--keypoint-errors, detector.measure_keypoint_errors) and "
                              "perfect tracks (--oracle-noise-px, detector.oracle_noise_px) exclude each other: perfect "
                              "tracks have no keypoint error to measure")


def _check_noise(noise_px: float) -> None:
    if not noise_px >= 0:
        raise DataError(None, f"oracle noise must be >= 0 px, got {noise_px}")


def simulator_of(sequence: str | os.PathLike):
    """The :class:`~aerovis_slam.sim.simulator.Simulator` that wrote ``sequence``, rebuilt from its
    metadata (errors: :func:`oracle_spec`)."""
    from ..sim.simulator import Simulator

    return Simulator(oracle_spec(sequence))


class SceneTruth:
    """Exact body poses and rendered z-depth of a sequence written by ``aerovis-sim``, at any time.

    The one implementation of "where is the scene point under this pixel, and where does it appear
    at another time", shared by the SLAM runtime's perfect tracks (:class:`ObservationOracle`) and the
    relative-pose evaluation's perfect matches (:mod:`aerovis_train.eval.pose`, ``oracle_noise_px``).

    Times ``t_us`` are on the simulator's clock, which is the GT's and the IMU's (µs). Cameras are
    given by the name of the simulator's sensor (``cam0``, ``cam1``), whose rendered depth is looked
    up, and by the intrinsics ``K`` and extrinsics ``T_body_cam`` (4, 4) of the pixels in question
    (which may be scaled from the sensor's, as the runtime's MCTS resolution is).

    Args:
        sequence: the simulated ``.h5`` (errors: :func:`oracle_spec`); or
        simulator: the rebuilt simulator itself.
    """

    def __init__(self, sequence: str | os.PathLike | None = None, *, simulator=None):
        if simulator is None:
            if sequence is None:
                raise ValueError("SceneTruth needs a sequence or a simulator")
            simulator = simulator_of(sequence)
        self.sim = simulator
        self._pose_cache: tuple[int, np.ndarray] | None = None
        self._depth_cache: dict[tuple[int, str], np.ndarray] = {}

    def sensor(self, name: str):
        """The simulator's calibration of sensor ``name`` (KeyError naming the rig's sensors)."""
        if name not in self.sim.rig.cameras:
            raise KeyError(f"camera {name!r} is not in the simulator's rig {sorted(self.sim.rig.cameras)}")
        return self.sim.rig.cameras[name]

    def T_world_body(self, t_us: int) -> np.ndarray:
        """(4, 4) true body pose at ``t_us`` (µs), from the simulator's continuous trajectory."""
        if self._pose_cache is None or self._pose_cache[0] != t_us:
            R, p, _, _ = self.sim.trajectory.kinematics(t_us * 1e-6)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, p
            self._pose_cache = (t_us, T)
        return self._pose_cache[1]

    def depth(self, t_us: int, sensor: str, T_body_cam: np.ndarray) -> np.ndarray:
        """(H, W) true z-depth (m, inf: no surface) of sensor ``sensor`` at its own resolution; the
        renders of one time are kept (the next time drops them)."""
        key = (int(t_us), sensor)
        if key not in self._depth_cache:
            T_wc = self.T_world_body(t_us) @ T_body_cam
            self._depth_cache = {k: v for k, v in self._depth_cache.items() if k[0] == t_us}  # one time at a time
            self._depth_cache[key] = self.sim.scene.render(self.sensor(sensor), T_wc, t_us * 1e-6)[1]
        return self._depth_cache[key]

    def back_project(self, t_us: int, sensor: str, K: np.ndarray, T_body_cam: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """True world points (N, 3) under pixels ``xy`` (N, 2) of a camera with intrinsics ``K`` at
        ``t_us``; NaN rows where the ray hits no surface or leaves the sensor. The depth is read at
        the sensor pixel nearest to each ray."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        rays = unproject(xy, np.ones(len(xy)), np.asarray(K, np.float64))  # z = 1 in the camera frame
        uv, _ = project(rays, np.asarray(self.sensor(sensor).K, np.float64))
        z = sample_depth_nearest(self.depth(t_us, sensor, T_body_cam), uv)
        z[~np.isfinite(z)] = np.nan  # inf: the ray hits no surface
        T_wc = self.T_world_body(t_us) @ T_body_cam
        return transform_points(T_wc, rays * z[:, None])

    def project(self, t_us: int, K: np.ndarray, T_body_cam: np.ndarray, size: tuple[int, int], points_world: np.ndarray,
                *, occluded_by: str | None = None, depth_tolerance: float = 0.03) -> np.ndarray:
        """Exact pixels (N, 2) of world points in a camera of ``size`` (W, H) with intrinsics ``K`` at
        ``t_us``; NaN behind the camera or outside the image.

        With ``occluded_by`` (a sensor name) also NaN where that sensor's rendered depth at the
        projection is nearer than the point by more than ``depth_tolerance`` (relative) + 2 cm: a
        surface in front hides it. The depth is read at the nearest pixel, so a point on a depth edge
        may count as hidden.
        """
        W, H = size
        T_cw = invert_T(self.T_world_body(t_us) @ T_body_cam)
        pc = transform_points(T_cw, np.asarray(points_world, np.float64).reshape(-1, 3))
        uv, _ = project(pc, np.asarray(K, np.float64))
        seen = (pc[:, 2] > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= W - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= H - 0.5)
        if occluded_by is not None and seen.any():
            depth = self.depth(t_us, occluded_by, T_body_cam)
            uvs, _ = project(pc[seen], np.asarray(self.sensor(occluded_by).K, np.float64))
            u = np.clip(np.round(uvs[:, 0]).astype(np.int64), 0, depth.shape[1] - 1)
            v = np.clip(np.round(uvs[:, 1]).astype(np.int64), 0, depth.shape[0] - 1)
            z = pc[seen, 2]
            seen[np.flatnonzero(seen)] = depth[v, u] >= z - (depth_tolerance * z + 0.02)
        uv[~seen] = np.nan
        return uv


@dataclass
class OracleStats:
    """Counts over a run: ``replaced`` observations, ``dropped`` ones (see the module docstring),
    ``landmarks`` given a scene point, ``no_surface`` landmarks whose first sighting hit none."""

    replaced: int = 0
    dropped: int = 0
    landmarks: int = 0
    no_surface: int = 0

    def as_dict(self, noise_px: float) -> dict:
        return {"noise_px": float(noise_px), "observations_replaced": self.replaced, "observations_dropped": self.dropped,
                "landmarks": self.landmarks, "landmarks_without_surface": self.no_surface}


#: track-age bins (s) of :meth:`ObservationOracle.error_summary`
ERROR_AGE_BINS_S: tuple[tuple[float, float], ...] = ((0.0, 0.05), (0.05, 0.2), (0.2, 0.5), (0.5, 1.0), (1.0, float("inf")))


class ObservationOracle:
    """Replaces landmark observations by true projections plus noise (see the module docstring), or
    with ``replace=False`` only measures how far the observations lie from them.

    Args:
        sequence: the simulated ``.h5`` the run reads.
        cams: the runtime's cameras (pixels at the MCTS resolution; the depth is rendered at the
            sensor's and looked up along each keypoint's ray).
        noise_px: standard deviation of the Gaussian noise per axis (px at the MCTS resolution).
        seed: seed of that noise.
        simulator: the rebuilt simulator (default: :func:`simulator_of`).
        replace: False: observations keep their positions; the distance of each (after the landmark's
            first sighting) to its true projection is recorded (:meth:`error_summary`).
    """

    def __init__(self, sequence: str | os.PathLike, cams: StereoCameras, noise_px: float, *, seed: int = 0, simulator=None,
                 replace: bool = True):
        _check_noise(noise_px)
        self.replaces = bool(replace)
        self.first_t: dict[int, int] = {}  # landmark id -> time (µs) of its first sighting
        self._errors: list[np.ndarray] = []  # per call: (K, 2) distance (px), track age (s)
        self.truth = SceneTruth(sequence, simulator=simulator)
        self.sim = self.truth.sim
        self.cams = cams
        self.noise_px = float(noise_px)
        self.rng = np.random.default_rng(seed)
        missing = [c.name for c in cams.cams if c.name not in self.sim.rig.cameras]
        if missing:
            raise DataError(Path(sequence), f"camera(s) {missing} are not in the simulator's rig {sorted(self.sim.rig.cameras)}")
        self.points: dict[int, np.ndarray | None] = {}  # landmark id -> true world point (m), None: no surface
        self.stats = OracleStats()

    # -- the truth at one time (SceneTruth, with the runtime's camera models) --------------------
    def T_world_body(self, t_us: int) -> np.ndarray:
        """(4, 4) true body pose at ``t_us`` (µs), from the simulator's continuous trajectory."""
        return self.truth.T_world_body(t_us)

    def _depth(self, t_us: int, cam: int) -> np.ndarray:
        """(H, W) true z-depth (m, inf: no surface) of camera ``cam`` at its sensor resolution."""
        model = self.cams.cams[cam]
        return self.truth.depth(t_us, model.name, model.T_body_cam)

    def back_project(self, t_us: int, cam: int, xy: np.ndarray) -> np.ndarray:
        """True world points (N, 3) under pixels ``xy`` (N, 2) of camera ``cam`` at ``t_us``; NaN rows where
        the ray hits no surface or leaves the sensor."""
        model = self.cams.cams[cam]
        return self.truth.back_project(t_us, model.name, model.K, model.T_body_cam, xy)

    def projections(self, t_us: int, cam: int, points_world: np.ndarray) -> np.ndarray:
        """Exact pixels (N, 2) of world points in camera ``cam`` at ``t_us``; NaN behind the camera or
        outside the image."""
        model = self.cams.cams[cam]
        return self.truth.project(t_us, model.K, model.T_body_cam, (model.width, model.height), points_world)

    # -- the replacement ---------------------------------------------------------------------
    def replace(self, t_us: int, obs: Observations) -> tuple[Observations, np.ndarray]:
        """``obs`` (taken at ``t_us``, µs) with true positions plus noise; returns (kept observations,
        keep mask (M,) over ``obs``)."""
        n = len(obs)
        if n == 0:
            return obs, np.zeros(0, bool)
        # scene points of landmarks new to the oracle: from their first observation here, left first
        order = np.lexsort((obs.cam, obs.landmark))
        first = order[np.r_[True, obs.landmark[order][1:] != obs.landmark[order][:-1]]]
        new = [i for i in first if int(obs.landmark[i]) not in self.points]
        for cam in (0, 1):
            rows = [i for i in new if obs.cam[i] == cam]
            if rows:
                pts = self.back_project(t_us, cam, obs.xy[rows])
                for i, p in zip(rows, pts):
                    ok = bool(np.isfinite(p).all())
                    self.points[int(obs.landmark[i])] = p if ok else None
                    self.stats.landmarks += ok
                    self.stats.no_surface += not ok
        for i in new:
            self.first_t[int(obs.landmark[i])] = int(t_us)
        xy = np.full((n, 2), np.nan)
        for cam in (0, 1):
            rows = np.flatnonzero(obs.cam == cam)
            have = [i for i in rows if self.points.get(int(obs.landmark[i])) is not None]
            if have:
                xy[have] = self.projections(t_us, cam, np.stack([self.points[int(obs.landmark[i])] for i in have]))
        keep = np.isfinite(xy).all(axis=1)
        if not self.replaces:
            age = np.array([(t_us - self.first_t.get(int(j), t_us)) * 1e-6 for j in obs.landmark])
            later = keep & (age > 0)  # a first sighting is its own truth
            self._errors.append(np.c_[np.linalg.norm(obs.xy[later] - xy[later], axis=1), age[later]])
            return obs, np.ones(n, bool)
        if self.noise_px > 0 and keep.any():
            xy[keep] += self.rng.normal(0.0, self.noise_px, (int(keep.sum()), 2))
        self.stats.replaced += int(keep.sum())
        self.stats.dropped += int(n - keep.sum())
        out = Observations(obs.landmark[keep], obs.cam[keep], xy[keep],
                           np.broadcast_to(np.eye(2), (int(keep.sum()), 2, 2)).copy())
        return out, keep

    def error_summary(self) -> dict:
        """Distances (px) of the measured observations to their true projections: count, median and 90th
        percentile over all and per track-age bin (``ERROR_AGE_BINS_S``; the age counts from the
        landmark's first sighting, whose position defines its scene point)."""
        e = np.concatenate(self._errors) if self._errors else np.zeros((0, 2))

        def stats(d):
            return {"observations": int(len(d)), "median_px": float(np.median(d)) if len(d) else None,
                    "p90_px": float(np.percentile(d, 90)) if len(d) else None}

        out = stats(e[:, 0])
        out["by_track_age_s"] = {f"{lo:g}-{hi:g}": stats(e[(e[:, 1] > lo) & (e[:, 1] <= hi), 0]) for lo, hi in ERROR_AGE_BINS_S}
        return out
