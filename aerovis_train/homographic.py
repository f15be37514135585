"""Self-supervised pairs from real, unlabelled event recordings (SuperPoint's homographic adaptation).

A real recording has no ground truth, but one time surface seen through a random homography ``H``
is a second view whose correspondences are exact: pixel ``x`` of view 0 is ``H x`` in view 1. So any
converted recording (``aerovis-data convert``: a user's own sensor, with its own noise, hot pixels
and scenes) yields training pairs, mixed into the simulator's batches by ``data.real``.

Split between the loader and the training device:

* :class:`RealViewDataset` (loader workers, numpy): a random time of a random recording, its MCTS
  (:func:`~aerovis_train.data.compute_mcts`, the runtime's), a crop, detector labels (Shi-Tomasi
  corners of the time surface's image that many events support, carried through ``H`` to view 1),
  the cell-centre targets of the descriptor loss in both directions, and ``H`` itself;
* :func:`warp_views` (the training device, kornia): view 1 is view 0 warped by ``H``, batched, so that
  the one expensive step (a bilinear warp of every channel) runs on the GPU in a GPU run.

Pixel convention as everywhere (integers at pixel centres), which is kornia's ``align_corners=True``.
The sample's keys are those of :class:`~aerovis_train.data.EventPairDataset` with depth supervision
(``mcts0``, ``labels0``, ``labels1``, ``warp01``, ``warp10``), plus ``H01``, and ``mcts1`` once warped.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from aerovis_slam.classical import mcts_to_image
from aerovis_slam.errors import DataError
from aerovis_slam.io.sequence import Sequence
from aerovis_slam.mcts import warm_up_requirement

from .correspondences import cell_centres
from .data import MctsSpec, compute_mcts, where_events
from .labels import CornerLabeller, Labeller, cell_labels, soft_cell_labels


@dataclass(frozen=True)
class HomographyRange:
    """How far the random homographies of :func:`sample_homography` go (SuperPoint's recipe).

    Attributes:
        max_angle_deg: in-plane rotation, uniform in +-this.
        scale: (low, high) zoom about the centre, log-uniform.
        translation: shift, uniform in +-this fraction of each side.
        perspective: each corner moved by up to this fraction of each side (keystone, tilt).
    """

    max_angle_deg: float = 15.0
    scale: tuple[float, float] = (0.85, 1.2)
    translation: float = 0.1
    perspective: float = 0.08

    def __post_init__(self) -> None:
        lo, hi = self.scale
        if not (0 < lo <= hi) or self.max_angle_deg < 0 or not 0 <= self.translation < 0.5 or not 0 <= self.perspective < 0.25:
            raise ValueError(f"homography range: scale (0 < low <= high), max_angle_deg >= 0, translation in [0, 0.5), "
                             f"perspective in [0, 0.25); got {self}")


def sample_homography(rng: np.random.Generator, height: int, width: int, r: HomographyRange = HomographyRange()) -> np.ndarray:
    """A random homography (3, 3) float64 from view-0 to view-1 pixels of a ``height`` x ``width`` image:
    the image corners are rotated and zoomed about the centre, shifted, and each moved a little apart."""
    c = np.array([(width - 1) / 2, (height - 1) / 2])
    corners = np.array([[0, 0], [width - 1, 0], [width - 1, height - 1], [0, height - 1]], np.float64)
    a = np.radians(rng.uniform(-r.max_angle_deg, r.max_angle_deg))
    s = float(np.exp(rng.uniform(np.log(r.scale[0]), np.log(r.scale[1]))))
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    size = np.array([width, height], np.float64)
    moved = (corners - c) @ R.T * s + c
    moved += rng.uniform(-r.translation, r.translation, 2) * size
    moved += rng.uniform(-r.perspective, r.perspective, (4, 2)) * size
    return cv2.getPerspectiveTransform(corners.astype(np.float32), moved.astype(np.float32)).astype(np.float64)


def apply_homography(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(N, 2) pixels through ``H`` (3, 3): (N, 2) float64."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    h = np.hstack([xy, np.ones((len(xy), 1))]) @ np.asarray(H, np.float64).T
    return h[:, :2] / h[:, 2:]


def _inside(xy: np.ndarray, width: int, height: int) -> np.ndarray:
    return (xy[:, 0] >= 0) & (xy[:, 0] <= width - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= height - 1)


def homography_targets(H: np.ndarray, height: int, width: int, cell: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Where each cell centre of one view lands in the other, both ways: ``warp01``, ``warp10``, each
    (Hc*Wc, 2) float32 with NaN where it leaves the image (the format of
    :func:`~aerovis_train.correspondences.grid_targets_depth`)."""
    centres = cell_centres(height, width, cell)
    out = []
    for M in (H, np.linalg.inv(H)):
        xy = apply_homography(M, centres)
        xy[~_inside(xy, width, height)] = np.nan
        out.append(xy.astype(np.float32))
    return out[0], out[1]


WINDOW_TRIES = 8     # windows drawn for a sample before one with few labels is accepted
MIN_LABELS = 10      # supported corners that make a window worth a sample
SUPPORT_RADIUS, SUPPORT_MIN = 2, 6  # a corner needs this many active pixels within this radius


def supported_corners(xy: np.ndarray, image: np.ndarray) -> np.ndarray:
    """The corners with at least ``SUPPORT_MIN`` active pixels of ``image`` in their (2r+1)^2 window.

    On a sparse or noisy time surface Shi-Tomasi calls lone noise events corners (the strongest corner
    sets the threshold, and a lone event is a perfect blob); an edge or a corner of the scene fires many
    neighbouring pixels, a noise event one."""
    if len(xy) == 0:
        return xy
    k = 2 * SUPPORT_RADIUS + 1
    count = cv2.boxFilter((image > 0).astype(np.float32), -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
    px = np.clip(np.rint(xy).astype(np.int64), 0, [image.shape[1] - 1, image.shape[0] - 1])
    return xy[count[px[:, 1], px[:, 0]] >= SUPPORT_MIN]


class RealViewDataset(Dataset):
    """View-0 samples of self-supervised pairs from canonical recordings (no GT, frames or calibration needed).

    Args:
        paths: canonical sequences (``aerovis-data convert`` output); every camera with events is used.
        mcts: the model's time surface.
        crop: (height, width) of a sample (multiples of 8); recordings must be at least that large.
        samples_per_epoch: length of an epoch; sample ``i`` of epoch ``e`` is a pure function of (seed, e, i).
        seed: base seed.
        homography: the range of the random homographies.
        labeller: corners of the time surface's image (:func:`~aerovis_slam.classical.mcts_to_image`).
        soft_labels: sub-pixel detector targets (as :class:`~aerovis_train.data.EventPairDataset`).
    """

    def __init__(self, paths: list[str | os.PathLike], mcts: MctsSpec, *, crop: tuple[int, int], samples_per_epoch: int,
                 seed: int = 0, homography: HomographyRange = HomographyRange(), labeller: Labeller | None = None,
                 soft_labels: bool = False):
        if not paths:
            raise DataError(None, "data.real lists no recordings")
        self.mcts, self.crop, self.seed, self.homography = mcts, tuple(int(v) for v in crop), int(seed), homography
        self.samples_per_epoch = int(samples_per_epoch)
        self.labeller = labeller or CornerLabeller()
        self.soft_labels = bool(soft_labels)
        self.views: list[tuple[Path, str, tuple[int, int], int, int]] = []  # path, camera, (w, h), first and last time
        for p in paths:
            p = Path(p)
            with Sequence(p) as seq:
                for cam in seq.cameras:
                    rng_t = seq.time_range(cam)
                    if rng_t is None:
                        continue
                    w, h = seq.sensor_size(cam)
                    if h < self.crop[0] or w < self.crop[1]:
                        raise DataError(p, f"{cam} is {w}x{h}, smaller than the {self.crop[1]}x{self.crop[0]} crop (data.crop)")
                    n_events, span_us = warm_up_requirement(mcts.kind, mcts.params, w, h)
                    first = (max(rng_t[0] + int(round(span_us)), int(seq.events_by_index(cam, n_events, n_events + 1).t[0]))
                             if seq.num_events(cam) > n_events else None)
                    if first is None or first >= rng_t[1]:
                        print(f"train.py: note: data.real: {p} {cam} left out: its {seq.num_events(cam):,} events over "
                              f"{(rng_t[1] - rng_t[0]) / 1e6:.3f} s never fill a complete MCTS_{mcts.kind}", file=sys.stderr)
                        continue
                    self.views.append((p, cam, (w, h), first, rng_t[1]))
        if not self.views:
            raise DataError(paths[0], "no recording in data.real has enough events for a complete time surface")
        self.epoch = 0
        self._open: dict[Path, Sequence] = {}

    def __len__(self) -> int:
        return self.samples_per_epoch

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def _window(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """A random crop of a random time surface and its corner labels (the first of ``WINDOW_TRIES``
        windows with at least ``MIN_LABELS`` supported corners, else the last one)."""
        ch, cw = self.crop
        for _ in range(WINDOW_TRIES):
            path, cam, (w, h), t_first, t_last = self.views[int(rng.integers(len(self.views)))]
            if path not in self._open:
                self._open[path] = Sequence(path)
            tau = int(rng.integers(t_first, t_last + 1))
            mcts = compute_mcts(self._open[path], cam, tau, self.mcts, (w, h))
            if not np.isfinite(mcts).all():
                raise DataError(path, f"non-finite values in the MCTS of {cam} at {tau} µs")
            y0, x0 = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
            mcts = np.ascontiguousarray(mcts[:, y0:y0 + ch, x0:x0 + cw])
            image = mcts_to_image(mcts)
            kp = supported_corners(self.labeller(image), image)
            kp = where_events(kp, mcts)
            if len(kp) >= MIN_LABELS:
                break
        return mcts, kp

    def __getitem__(self, index: int) -> dict:
        rng = np.random.default_rng([self.seed, self.epoch, index, 0x4EA1])
        mcts, kp0 = self._window(rng)
        ch, cw = self.crop
        H = sample_homography(rng, ch, cw, self.homography)
        kp1 = apply_homography(H, kp0)
        # a corner carried into view 1 is a label there where it stays inside the image
        kp1 = kp1[_inside(kp1, cw, ch)].astype(np.float32)
        targets = soft_cell_labels if self.soft_labels else cell_labels
        warp01, warp10 = homography_targets(H, ch, cw)
        return {"mcts0": torch.from_numpy(mcts), "H01": torch.from_numpy(H.astype(np.float32)),
                "labels0": torch.from_numpy(targets(kp0, ch, cw, rng)), "labels1": torch.from_numpy(targets(kp1, ch, cw, rng)),
                "warp01": torch.from_numpy(warp01), "warp10": torch.from_numpy(warp10)}

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_open"] = {}  # each worker opens its own handles
        return state


def warp_views(batch: dict) -> dict:
    """Complete a batch of :class:`RealViewDataset` samples on its device: ``mcts1`` = ``mcts0`` warped by
    ``H01`` (kornia, bilinear, zeros outside). Returns a new dict with the pair's keys (``H01`` dropped)."""
    from kornia.geometry.transform import warp_perspective

    mcts0 = batch["mcts0"]
    mcts1 = warp_perspective(mcts0, batch["H01"].to(mcts0.dtype), tuple(mcts0.shape[-2:]), mode="bilinear",
                             padding_mode="zeros", align_corners=True)
    return {**{k: v for k, v in batch.items() if k != "H01"}, "mcts1": mcts1.clamp_(0.0, 1.0)}


def merge_batches(sim: dict, real: dict) -> dict:
    """One training batch of simulated and (warped) real pairs: their tensors concatenated along the batch.

    Raises:
        ValueError: the two carry different targets (e.g. the simulator's pose-only epipolar lines).
    """
    if set(sim) != set(real):
        raise ValueError(f"simulated and real pairs carry different targets: {sorted(set(sim) ^ set(real))}")
    return {k: torch.cat([sim[k], real[k].to(sim[k].dtype)]) for k in sim}
