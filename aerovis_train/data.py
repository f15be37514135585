"""Training data: pairs of MCTS with pose-derived supervision, from any canonical sequence with GT.

A sample is two views at frame timestamps (each sequence needs intensity frames for the detector
labels; depth where the supervision is ``depth``):

* temporal: the same camera at frames i and i + g, g drawn from 1..``max_gap_frames`` so that the
  relative motion covers small to large baselines;
* stereo: left and right camera at the same frame.

Per view: the MCTS at the frame time (computed with the runtime's :mod:`aerovis_slam.mcts`, so
training and deployment preprocess identically), 65-class cell labels (corners of the frame,
re-detected in the paired view, and where events are), and, for the pair, where the cell centres
of each view land in the other (depth) or their epipolar lines (poses only). A random crop of
``crop`` pixels (the same window in both views) is applied after all geometry is computed.

Sequences are opened lazily in each worker process (h5py handles must not cross a fork).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from aerovis_slam import geometry as geo
from aerovis_slam.errors import DataError
from aerovis_slam.io.sequence import Sequence
from aerovis_slam.mcts import MCTS_DT_WINDOWS_MS, events_per_window, mcts_from_events

from .correspondences import ViewGeometry, epipolar_lines, grid_targets_depth, pixel_targets_depth
from .labels import CornerLabeller, Labeller, cell_labels, cross_view_consistent, soft_cell_labels


@dataclass
class MctsSpec:
    """Which time surface a model consumes: ``kind`` "ne" (``params`` = events per pixel) or "dt"
    (``params`` = windows in ms)."""

    kind: str
    params: tuple[float, ...]

    @property
    def channels(self) -> int:
        return 2 * len(self.params)


def compute_mcts(seq: Sequence, cam: str, tau_us: int, spec: MctsSpec, size: tuple[int, int] | None = None) -> np.ndarray:
    """MCTS of camera ``cam`` at ``tau_us`` from the events up to it: float32 (C, H, W).

    Reads only what can reach a channel: the last max(N_k) + 1 events (MCTS_Ne) or the longest
    window (MCTS_dt); older events would give 0 (see :func:`aerovis_slam.mcts.mcts_from_events`).
    ``size``: the camera's (width, height) if the caller knows it (reading it from the file costs
    a third of the MCTS's own time in a training loader).
    """
    w, h = size or seq.sensor_size(cam)
    end = seq.index_at(cam, tau_us + 1)
    if spec.kind == "ne":
        start = max(0, end - int(events_per_window(spec.params, w, h).max()) - 1)
    elif spec.kind == "dt":
        start = seq.index_at(cam, tau_us - int(max(spec.params) * 1000))
    else:
        raise ValueError(f"MCTS kind must be 'ne' or 'dt', not {spec.kind!r}")
    return mcts_from_events(seq.events_by_index(cam, start, end), w, h, tau_us, kind=spec.kind, params=spec.params)


class SequenceInfo:
    """What the sampler needs of one sequence, read once: frame times, calibration, GT."""

    def __init__(self, path: str | os.PathLike, need_depth: bool):
        self.path = Path(path)
        with Sequence(self.path) as seq:
            if seq.gt is None:
                raise DataError(self.path, "no /gt poses: pose-supervised training needs ground truth")
            self.calib = seq.calib
            self.cameras = [c for c in seq.cameras if seq.frame_times(c) is not None]
            if not self.cameras:
                raise DataError(self.path, "no /frames: detector labels come from intensity frames")
            if need_depth and any(seq.frame_times(c, "depth") is None for c in self.cameras):
                raise DataError(self.path, "no /depth for every camera, but data.supervision=depth; use supervision=epipolar for pose-only data")
            self.frame_times = {c: seq.frame_times(c) for c in self.cameras}
            self.size = {c: seq.sensor_size(c) for c in self.cameras}
            gt = seq.gt
            self.gt_t, self.gt_pose = gt.t, gt.pose
            self.first_event = {c: (seq.time_range(c) or (None, None))[0] for c in self.cameras}

    def T_world_cam(self, cam: str, t_us: int) -> np.ndarray:
        """(4, 4) pose of ``cam`` at its own clock's ``t_us`` (the GT, on the IMU clock, at ``t_us`` + its timeshift)."""
        t_imu = t_us + self.calib.cameras[cam].imu_clock_offset_us
        T_world_body = geo.pose7_to_matrix(geo.interpolate_poses([t_imu], self.gt_t, self.gt_pose)[0])
        return T_world_body @ self.calib.cameras[cam].T_imu_cam

    def usable_frames(self, cam: str, min_history_us: int) -> np.ndarray:
        """Frame indices with GT coverage and at least ``min_history_us`` of events before them."""
        t = self.frame_times[cam]
        first = self.first_event[cam]
        t_imu = t + self.calib.cameras[cam].imu_clock_offset_us
        ok = (t_imu >= self.gt_t[0]) & (t_imu <= self.gt_t[-1])
        ok &= (t >= first + min_history_us) if first is not None else False
        return np.flatnonzero(ok)


class EventPairDataset(Dataset):
    """Pairs of views with labels and correspondences (see the module docstring).

    Args:
        paths: canonical sequences with GT, frames (and depth for ``supervision="depth"``).
        mcts: the model's time-surface spec.
        crop: (height, width) random crop; None = full frames (must suit the model's size multiple).
        max_gap_frames: largest temporal frame gap of a pair.
        stereo_fraction: share of left/right pairs (where the sequence has two cameras).
        supervision: ``"depth"`` or ``"epipolar"``.
        samples_per_epoch: length of an epoch (pairs are drawn at random); None = one per usable frame.
        seed: base seed; sample ``i`` of epoch ``e`` is a pure function of (seed, e, i).
        labeller: frame -> corners; Shi-Tomasi by default.
        event_cache: folder of decoded, memory-mapped copies of the sequences
            (:mod:`aerovis_train.decoded`), the missing ones built here; None reads the files directly.
        roll_deg: the second view of each pair is turned about its optical axis by an angle drawn
            uniformly in +-``roll_deg`` degrees (image, frame, depth and pose together: exact geometry;
            0: off), so that descriptors learn in-plane rotations larger than the pairs' own motion.
        soft_labels: detector targets as 65-class distributions that keep the labels' sub-pixel
            positions (:func:`~aerovis_train.labels.soft_cell_labels`, float (65, Hc, Wc)) instead of
            the class of each label's nearest pixel (int64 (Hc, Wc)); for a sub-pixel labeller.
        pixel_warps: also return ``flow01``/``flow10``, (H, W, 2) float32: where every pixel of one
            view lands in the other (NaN: invisible; :func:`~aerovis_train.correspondences.pixel_targets_depth`),
            for the detector's repeatability loss. Depth supervision only.
    """

    def __init__(
        self,
        paths: list[str | os.PathLike],
        mcts: MctsSpec,
        *,
        crop: tuple[int, int] | None = None,
        max_gap_frames: int = 4,
        stereo_fraction: float = 0.3,
        supervision: str = "depth",
        samples_per_epoch: int | None = None,
        seed: int = 0,
        labeller: Labeller | None = None,
        min_history_ms: float = 50.0,
        event_cache: str | os.PathLike | None = None,
        roll_deg: float = 0.0,
        soft_labels: bool = False,
        pixel_warps: bool = False,
    ):
        if supervision not in ("depth", "epipolar"):
            raise ValueError(f"supervision must be 'depth' or 'epipolar', not {supervision!r}")
        if pixel_warps and supervision != "depth":
            raise ValueError("pixel warps (the repeatability loss) need depth supervision: poses alone do not say "
                             "where a pixel lands in the other view")
        self.pixel_warps = bool(pixel_warps)
        if not paths:
            raise DataError(None, "no training sequences given")
        self.mcts, self.crop, self.max_gap = mcts, crop, max_gap_frames
        self.stereo_fraction, self.supervision, self.seed = stereo_fraction, supervision, seed
        self.roll_deg = float(roll_deg)
        self.labeller = labeller or CornerLabeller()
        self.soft_labels = bool(soft_labels)
        self.infos = [SequenceInfo(p, need_depth=supervision == "depth") for p in paths]
        self.frames = []  # (sequence index, camera, frame index)
        for si, info in enumerate(self.infos):
            for cam in info.cameras:
                for fi in info.usable_frames(cam, int(min_history_ms * 1000)):
                    self.frames.append((si, cam, int(fi)))
        if not self.frames:
            raise DataError(paths[0], "no usable frames (frames need GT coverage and events before them)")
        if crop is not None:
            for info in self.infos:
                for cam, (w, h) in info.size.items():
                    if crop[0] > h or crop[1] > w:
                        raise DataError(info.path, f"crop {crop[0]}x{crop[1]} is larger than {cam}'s {h}x{w} image")
        self.samples_per_epoch = samples_per_epoch or len(self.frames)
        self.epoch = 0
        self._open: dict[int, Sequence] = {}
        self.event_cache = None if event_cache is None else Path(event_cache).expanduser()
        if self.event_cache is not None:
            from .decoded import prepare_decoded

            prepare_decoded([info.path for info in self.infos], self.event_cache)

    def __len__(self) -> int:
        return self.samples_per_epoch

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def _seq(self, si: int) -> Sequence:
        if si not in self._open:
            seq = Sequence(self.infos[si].path)
            if self.event_cache is not None:
                from .decoded import DecodedSequence

                seq = DecodedSequence(seq, self.event_cache)
            self._open[si] = seq
        return self._open[si]

    def _choose_pair(self, rng: np.random.Generator, index: int):
        # one pass over the frames per epoch, or random frames for a fixed-length epoch
        si, cam, fi = self.frames[index] if self.samples_per_epoch == len(self.frames) else self.frames[rng.integers(len(self.frames))]
        info = self.infos[si]
        if len(info.cameras) > 1 and rng.random() < self.stereo_fraction:
            other = [c for c in info.cameras if c != cam][0]
            if fi < len(info.frame_times[other]) and info.frame_times[other][fi] == info.frame_times[cam][fi]:
                return si, (cam, fi), (other, fi)
        usable = info.usable_frames(cam, 0)
        gap = int(rng.integers(1, self.max_gap + 1)) * (1 if rng.random() < 0.5 else -1)
        fj = int(np.clip(fi + gap, usable.min(), usable.max()))
        if fj == fi:
            fj = fi + 1 if fi + 1 <= usable.max() else fi - 1
        return si, (cam, fi), (cam, fj)

    def _view(self, si: int, cam: str, fi: int):
        seq, info = self._seq(si), self.infos[si]
        t = int(info.frame_times[cam][fi])
        mcts = compute_mcts(seq, cam, t, self.mcts, info.size[cam])
        if not np.isfinite(mcts).all():  # numpy: ~10x cheaper than torch.isfinite on a loader's CPU
            raise DataError(info.path, f"non-finite values in the MCTS of {cam} at frame {fi}")
        frame = seq.frame(cam, fi)
        depth = seq.frame(cam, fi, "depth") if self.supervision == "depth" else None
        K = self.calib_K(si, cam)
        w, h = info.size[cam]
        return mcts, frame, ViewGeometry(K, info.T_world_cam(cam, t), depth, (w, h))

    def calib_K(self, si: int, cam: str) -> np.ndarray:
        return self.infos[si].calib.cameras[cam].K

    def __getitem__(self, index: int) -> dict:
        rng = np.random.default_rng([self.seed, self.epoch, index])
        si, (c0, f0), (c1, f1) = self._choose_pair(rng, index)
        mcts0, frame0, g0 = self._view(si, c0, f0)
        mcts1, frame1, g1 = self._view(si, c1, f1)
        if self.roll_deg > 0:  # drawn only when on, so that samples without it stay as they were
            mcts1, frame1, g1 = roll_view(mcts1, frame1, g1, np.radians(rng.uniform(-self.roll_deg, self.roll_deg)))
        # detector labels: corners, re-detected in the other view, where the time surface has events
        kp0, kp1 = self.labeller(frame0), self.labeller(frame1)
        if self.supervision == "depth":
            keep0, keep1 = cross_view_consistent(kp0, kp1, g0, g1), cross_view_consistent(kp1, kp0, g1, g0)
            kp0, kp1 = kp0[keep0], kp1[keep1]
        kp0, kp1 = where_events(kp0, mcts0), where_events(kp1, mcts1)
        # crop window (same in both views), applied to images, intrinsics, depth and labels
        h, w = mcts0.shape[1:]
        ch, cw = self.crop or (h - h % 8, w - w % 8)
        y0, x0 = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
        g0c, g1c = _crop_view(g0, x0, y0, cw, ch), _crop_view(g1, x0, y0, cw, ch)
        targets = soft_cell_labels if self.soft_labels else cell_labels
        sample = {
            "mcts0": torch.from_numpy(np.ascontiguousarray(mcts0[:, y0 : y0 + ch, x0 : x0 + cw])),
            "mcts1": torch.from_numpy(np.ascontiguousarray(mcts1[:, y0 : y0 + ch, x0 : x0 + cw])),
            "labels0": torch.from_numpy(targets(kp0 - [x0, y0], ch, cw, rng)),
            "labels1": torch.from_numpy(targets(kp1 - [x0, y0], ch, cw, rng)),
        }
        if self.supervision == "depth":
            sample["warp01"] = torch.from_numpy(grid_targets_depth(g0c, g1c)[0])
            sample["warp10"] = torch.from_numpy(grid_targets_depth(g1c, g0c)[0])
            if self.pixel_warps:
                sample["flow01"] = torch.from_numpy(pixel_targets_depth(g0c, g1c))
                sample["flow10"] = torch.from_numpy(pixel_targets_depth(g1c, g0c))
        else:
            sample["lines01"] = torch.from_numpy(epipolar_lines(g0c, g1c))
            sample["lines10"] = torch.from_numpy(epipolar_lines(g1c, g0c))
        return sample

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_open"] = {}  # each worker opens its own handles
        return state


def where_events(xy: np.ndarray, mcts: np.ndarray, radius: int = 1) -> np.ndarray:
    """Keep label points with an event in the longest window within ``radius`` px (the network
    cannot see a corner that produced no events)."""
    if len(xy) == 0:
        return xy
    active = (mcts.max(0) > 0).astype(np.uint8)
    active = cv2.dilate(active, np.ones((2 * radius + 1, 2 * radius + 1), np.uint8))
    px = np.rint(xy).astype(np.int64)
    h, w = active.shape
    inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    keep = np.zeros(len(xy), bool)
    keep[inside] = active[px[inside, 1], px[inside, 0]] > 0
    return xy[keep]


def roll_view(mcts: np.ndarray, frame: np.ndarray, view: ViewGeometry, angle_rad: float
              ) -> tuple[np.ndarray, np.ndarray, ViewGeometry]:
    """One view as its camera would see it turned by ``angle_rad`` about its optical axis.

    A rotation about the optical axis keeps every point's z-depth and moves pixels by the homography
    ``K R^T K^-1`` (``R``: the turned camera's axes in the old camera frame), so the MCTS (channels
    (C, H, W)), the intensity frame and the depth are resampled by it (bilinear; depth nearest, NaN
    where nothing maps) and ``T_world_cam`` turns by ``R``: the pose-derived correspondences of the
    pair stay exact. The MCTS of a turned camera is the turned MCTS, since the events move with the
    image.
    """
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    H = view.K @ R.T @ np.linalg.inv(view.K)  # old pixel -> pixel of the turned camera
    w, h = view.size

    def warp(img, interpolation, border):
        return cv2.warpPerspective(img, H, (w, h), flags=interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=border)

    mcts_r = np.stack([warp(ch, cv2.INTER_LINEAR, 0.0) for ch in mcts]).astype(mcts.dtype, copy=False)
    frame_r = warp(frame, cv2.INTER_LINEAR, 0)
    depth_r = None if view.depth is None else warp(np.asarray(view.depth, np.float32), cv2.INTER_NEAREST, float("nan"))
    T = view.T_world_cam.copy()
    T[:3, :3] = T[:3, :3] @ R
    return mcts_r, frame_r, ViewGeometry(view.K, T, depth_r, view.size)


def _crop_view(v: ViewGeometry, x0: int, y0: int, w: int, h: int) -> ViewGeometry:
    K = v.K.copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    depth = None if v.depth is None else v.depth[y0 : y0 + h, x0 : x0 + w]
    return ViewGeometry(K, v.T_world_cam, depth, (w, h))


def make_loader(dataset: Dataset, batch_size: int, num_workers: int, shuffle: bool) -> DataLoader:
    """The training DataLoader. With workers, OpenCV runs single-threaded in this process and so in
    the workers it forks: its pool would otherwise start one thread per core in every worker (16 x 16
    on a 16-core GPU machine) for frames of a few hundred pixels a side. It is set here, before the
    fork, because changing it inside a forked worker deadlocks once this process has used the pool
    (the second loader of such a process hung)."""
    if num_workers > 0:
        cv2.setNumThreads(1)
    return DataLoader(dataset, batch_size=batch_size, shuffle=shuffle, num_workers=num_workers,
                      persistent_workers=num_workers > 0, pin_memory=torch.cuda.is_available(), drop_last=shuffle)


def mcts_spec_from_config(cfg) -> MctsSpec:
    """``model.mcts`` config -> :class:`MctsSpec` (defaults from the paper)."""
    kind = str(cfg.kind)
    params = tuple(float(p) for p in cfg.params) if cfg.get("params") is not None else None
    if kind == "dt":
        return MctsSpec("dt", params or MCTS_DT_WINDOWS_MS)
    from aerovis_slam.mcts import MCTS_NE_EVENTS_PER_PX

    return MctsSpec(kind, params or MCTS_NE_EVENTS_PER_PX)
