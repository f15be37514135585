"""Frontend pieces: the landmark map, matching keypoints to it, and the keyframe decision.

* :class:`LandmarkMap`: world points (m) with the descriptor of their latest keyframe observation.
* :func:`match_to_map`: project map landmarks with a predicted pose and search each projection's
  window for the most similar keypoint (OKVIS2's map matching with the IMU-propagated pose).
* :class:`KeyframeSelector`: OKVIS2's keyframe criterion, the overlap of the image area covered by
  keypoints matched to a keyframe's landmarks, measured on a grid of cells (a union of cells follows
  any keypoint layout, where a convex hull would count empty space between clusters as covered).

Frames: ``T_world_body`` (4, 4) body pose, ``T_body_cam`` camera extrinsic (see :mod:`.cameras`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..geometry import invert_T, project, transform_points
from ..keypoints import Keypoints, pair_similarity
from .cameras import CameraModel
from .stereo import best_matches


class LandmarkMap:
    """Growing table of landmarks; ids are row indices and never reused.

    Attributes (per landmark, over ``len(self)`` rows):
        pos: (N, 3) world position (m). desc: (N, D) descriptor (detector dtype).
        last_t: time (µs) of the last frame that matched it. last_kf: last keyframe that observed it.
        born_t: time (µs) of its creation.
        n_matched, n_projected: matching statistics (culling of unreliable landmarks).
        alive: False once culled or retired.
    """

    def __init__(self):
        self._n = 0
        self.pos = np.zeros((0, 3))
        self.desc: np.ndarray | None = None
        self.last_t = np.zeros(0, np.int64)
        self.born_t = np.zeros(0, np.int64)
        self.last_kf = np.zeros(0, np.int64)
        self.n_matched = np.zeros(0, np.int64)
        self.n_projected = np.zeros(0, np.int64)
        self.alive = np.zeros(0, bool)

    def __len__(self) -> int:
        return self._n

    def _grow(self, need: int, dim: int, dtype) -> None:
        cap = len(self.pos)
        if self.desc is None:
            self.desc = np.zeros((0, dim), dtype)
        if self._n + need <= cap:
            return
        new = max(2 * cap, self._n + need, 256)

        def grow(a, fill=0):
            out = np.full((new,) + a.shape[1:], fill, a.dtype)
            out[:len(a)] = a
            return out

        self.pos, self.desc = grow(self.pos), grow(self.desc)
        self.last_t, self.last_kf, self.born_t = grow(self.last_t), grow(self.last_kf), grow(self.born_t)
        self.n_matched, self.n_projected = grow(self.n_matched), grow(self.n_projected)
        self.alive = grow(self.alive, False)

    def add(self, points_world: np.ndarray, descriptors: np.ndarray, t_us: int, kf: int) -> np.ndarray:
        """Append landmarks; returns their ids (M,)."""
        m = len(points_world)
        if m == 0:
            return np.zeros(0, np.int64)
        if self.desc is not None and self.desc.dtype != descriptors.dtype:
            raise ValueError(f"landmark descriptors are {self.desc.dtype}, got {descriptors.dtype}")
        self._grow(m, descriptors.shape[1], descriptors.dtype)
        ids = np.arange(self._n, self._n + m)
        self.pos[ids] = points_world
        self.desc[ids] = descriptors
        self.last_t[ids] = t_us
        self.born_t[ids] = t_us
        self.last_kf[ids] = kf
        self.n_matched[ids] = 1
        self.n_projected[ids] = 1
        self.alive[ids] = True
        self._n += m
        return ids

    def local_ids(self, t_us: int, max_landmarks: int, max_age_us: int, max_lifetime_us: int | None = None) -> np.ndarray:
        """Alive landmarks matched within ``max_age_us`` before ``t_us`` (and, with ``max_lifetime_us``,
        created within it), at most the ``max_landmarks`` most recently matched."""
        n = self._n
        if n == 0:
            return np.zeros(0, np.int64)
        ok = self.alive[:n] & (t_us - self.last_t[:n] <= max_age_us)
        if max_lifetime_us is not None:
            ok &= t_us - self.born_t[:n] <= max_lifetime_us
        ids = np.flatnonzero(ok)
        if len(ids) > max_landmarks:
            order = np.argsort(-self.last_t[ids], kind="stable")[:max_landmarks]
            ids = np.sort(ids[order])
        return ids

    def cull(self, min_ratio: float = 0.25, min_trials: int = 8) -> int:
        """Retire landmarks matched in fewer than ``min_ratio`` of the frames they projected into."""
        n = self._n
        bad = self.alive[:n] & (self.n_projected[:n] >= min_trials) & (self.n_matched[:n] < min_ratio * self.n_projected[:n])
        self.alive[:n][bad] = False
        return int(bad.sum())

    def retire_all(self) -> None:
        """Tracking loss: no landmark of the old map is matched again (re-initialisation)."""
        self.alive[:self._n] = False


@dataclass
class MapMatches:
    """Matches of one camera's keypoints to landmarks: ``landmark`` (M,) ids, ``keypoint`` (M,) indices."""

    landmark: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    keypoint: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    projected: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def __len__(self) -> int:
        return len(self.landmark)


def project_landmarks(points_world: np.ndarray, T_world_body: np.ndarray, cam: CameraModel,
                      margin_px: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of world points in ``cam`` at a body pose, and visible (N,) (in front, inside +- margin)."""
    uv, z = project(transform_points(invert_T(T_world_body @ cam.T_body_cam), points_world), cam.K)
    vis = (z > 0.05) & np.isfinite(uv).all(axis=1)
    vis &= (uv[:, 0] >= -0.5 - margin_px) & (uv[:, 0] <= cam.width - 0.5 + margin_px)
    vis &= (uv[:, 1] >= -0.5 - margin_px) & (uv[:, 1] <= cam.height - 0.5 + margin_px)
    return uv, vis


def match_to_map(lmap: LandmarkMap, ids: np.ndarray, T_world_body_pred: np.ndarray, cam: CameraModel, kps: Keypoints,
                 *, window_px: float, min_similarity: float, ratio: float = 0.0) -> MapMatches:
    """Match keypoints to landmarks projected with a predicted pose.

    Each visible landmark may only match keypoints within ``window_px`` of its projection; among
    those, mutual best descriptor similarity above ``min_similarity`` wins (:func:`best_matches`).

    Returns:
        :class:`MapMatches` (``projected``: ids of the landmarks that projected into the image).
    """
    if len(ids) == 0 or len(kps) == 0:
        return MapMatches()
    uv, vis = project_landmarks(lmap.pos[ids], T_world_body_pred, cam)
    ids_v, uv_v = ids[vis], uv[vis]
    if len(ids_v) == 0:
        return MapMatches()
    m = window_matches(uv_v, kps.xy, window_px, lambda i, j: pair_similarity(lmap.desc, kps.descriptors, ids_v[i], j),
                       min_similarity, ratio)
    return MapMatches(ids_v[m[:, 0]], m[:, 1], ids_v)


def window_matches(uv: np.ndarray, xy: np.ndarray, window_px: float, similarity, min_similarity: float,
                   ratio: float = 0.0) -> np.ndarray:
    """Mutual best matches between predicted pixels ``uv`` (M, 2) and keypoints ``xy`` (N, 2), each
    pair within ``window_px``: (K, 2) int64 ``(row of uv, row of xy)``.

    ``similarity(i, j)`` gives the (P,) descriptor similarity of the pairs ``(i[p], j[p])`` (higher
    is better, e.g. :func:`~aerovis_slam.keypoints.pair_similarity`); it is asked only for pairs
    inside the window. ``min_similarity`` and ``ratio`` as in :func:`best_matches`.
    """
    a = np.asarray(uv, np.float32)
    b = np.asarray(xy, np.float32)
    d2 = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * (a @ b.T)  # one BLAS product
    allowed = d2 <= window_px ** 2
    rows = np.flatnonzero(allowed.any(1))
    if len(rows) == 0:
        return np.zeros((0, 2), np.int64)
    allowed = allowed[rows]
    r, c = np.nonzero(allowed)
    sim = np.full(allowed.shape, -np.inf, np.float32)
    sim[r, c] = similarity(rows[r], c)
    m = best_matches(sim, allowed, min_similarity, ratio)
    return np.stack([rows[m[:, 0]], m[:, 1]], axis=1).astype(np.int64)


def structure_tensor(img: np.ndarray, window: int = 7) -> np.ndarray:
    """Local structure tensor of an image: (3, H, W) float32 ``(sxx, sxy, syy)``, Sobel gradients
    averaged over ``window`` x ``window`` pixels (computed once per frame, sampled by :func:`edge_shapes`)."""
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    k = (int(window), int(window))
    return np.stack([cv2.boxFilter(gx * gx, -1, k), cv2.boxFilter(gx * gy, -1, k), cv2.boxFilter(gy * gy, -1, k)])


def nearest_pixels(xy: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Column and row indices (N,) int64 of the pixels nearest to ``xy`` (N, 2), clamped to an
    image of ``shape`` (H, W): where per-pixel maps are read at keypoints."""
    H, W = shape[:2]
    return (np.clip(np.rint(xy[:, 0]).astype(np.int64), 0, W - 1),
            np.clip(np.rint(xy[:, 1]).astype(np.int64), 0, H - 1))


def edge_shapes(tensor: np.ndarray, xy: np.ndarray, *, max_ratio: float = 100.0) -> np.ndarray:
    """Covariance shapes (N, 2, 2) of keypoint positions from the local structure tensor.

    An event keypoint on an edge is well localised across the edge but can slide along it between
    frames (the aperture problem: on the simulator's floor lines tracked keypoints drift several
    pixels along them, always lagging the motion, which biases the estimated motion). The shape
    ``e1 e1^T + r e2 e2^T`` (``e1`` across the edge, ``e2`` along it, ``r = lambda1 / lambda2`` of the
    tensor clipped to ``[1, max_ratio]``) keeps the full weight across the edge and scales the
    variance along it by the edge's anisotropy; corners stay isotropic.

    Args:
        tensor: (3, H, W) :func:`structure_tensor` of the image the keypoints come from (e.g. the
            blurred channel mean of the MCTS).
        xy: (N, 2) pixels. max_ratio: variance ratio cap.
    """
    n = len(xy)
    if n == 0:
        return np.zeros((0, 2, 2))
    sxx, sxy, syy = tensor
    u, v = nearest_pixels(xy, sxx.shape)
    S = np.stack([np.stack([sxx[v, u], sxy[v, u]], -1), np.stack([sxy[v, u], syy[v, u]], -1)], -2).astype(np.float64)
    lam, vec = np.linalg.eigh(S)  # ascending: lam[:, 0] small (along the edge), lam[:, 1] large
    ratio = np.clip(lam[:, 1] / np.maximum(lam[:, 0], 1e-12 * np.maximum(lam[:, 1], 1e-30)), 1.0, max_ratio)
    ratio = np.where(lam[:, 1] > 1e-12, ratio, 1.0)
    e_along, e_across = vec[:, :, 0], vec[:, :, 1]
    return (np.einsum("ni,nj->nij", e_across, e_across) + ratio[:, None, None] * np.einsum("ni,nj->nij", e_along, e_along))


def event_support(surfaces: np.ndarray, window: int, xy: np.ndarray, radius: int = 2) -> np.ndarray:
    """How many pixels around each keypoint had an event within one of the MCTS's windows.

    In a scene with little texture most events are sensor noise (shot noise and leak, each pixel
    firing alone), and a constant-event-count surface's longest windows then span a second or more:
    every noise event stays a lit dot at a fixed image position for that long, and detectors (learned
    and classical alike) put keypoints on the dots. Such keypoints match from frame to frame without
    moving, so the frontend sees a camera at rest while it travels (bench preset seed 1, slider_wall:
    two thirds of the events are noise, 0.2 Hz of leak and shot noise per pixel; the estimate moved
    0.03 m while the camera moved 0.5 m). Structure that is really there fires along its edges
    within a short window; a noise dot is one pixel, and once older than the window none. Written
    with OpenCV's box filter (no library counts this).

    Args:
        surfaces: (C, H, W) one camera's MCTS, polarity-major (``channel = p * K + k``, K = C / 2).
        window: ``k``: the window (0: the shortest) whose two polarity channels count.
        xy: (N, 2) keypoint pixels. radius: the count is over the (2r+1)^2 pixels around each.
    Returns:
        (N,) int64 number of pixels with an event of either polarity within that window.
    """
    K = surfaces.shape[0] // 2
    if not 0 <= window < K:
        raise ValueError(f"support window {window} outside the MCTS's {K} windows")
    lit = ((surfaces[window] > 0) | (surfaces[K + window] > 0)).astype(np.float32)
    side = 2 * int(radius) + 1
    count = cv2.boxFilter(lit, -1, (side, side), normalize=False, borderType=cv2.BORDER_CONSTANT)
    u, v = nearest_pixels(xy, lit.shape)
    return np.rint(count[v, u]).astype(np.int64)


def supported_keypoints(kp: Keypoints, surfaces: np.ndarray, window: int, min_support: int) -> Keypoints:
    """The keypoints of ``kp`` with at least ``min_support`` pixels of :func:`event_support` in
    window ``window`` of ``surfaces`` (one camera's MCTS (C, H, W)); scores and descriptors follow."""
    keep = event_support(surfaces, window, kp.xy) >= min_support
    return Keypoints(kp.xy[keep], kp.scores[keep], kp.descriptors[keep])


def spread_subset(xy: np.ndarray, n: int, cell_px: int, width: int) -> np.ndarray:
    """Indices of at most ``n`` of the points (M, 2), spread over the image: one per grid cell per round."""
    m = len(xy)
    if m <= n:
        return np.arange(m)
    c = np.floor(np.asarray(xy) / cell_px).astype(np.int64)
    cell = c[:, 1] * (width // cell_px + 1) + c[:, 0]
    order = np.argsort(cell, kind="stable")
    sc = cell[order]
    first = np.r_[True, sc[1:] != sc[:-1]]
    rank = np.arange(m) - np.maximum.accumulate(np.where(first, np.arange(m), 0))  # rank within its cell
    pick = order[np.lexsort((sc, rank))][:n]
    return np.sort(pick)


def cell_set(xy: np.ndarray, cell_px: int, width: int) -> np.ndarray:
    """Unique grid-cell indices (int64) of pixel positions (N, 2)."""
    if len(xy) == 0:
        return np.zeros(0, np.int64)
    c = np.floor(np.asarray(xy) / cell_px).astype(np.int64)
    return np.unique(c[:, 1] * (width // cell_px + 1) + c[:, 0])


class KeyframeSelector:
    """Keeps the landmark sets of recent keyframes and decides when the current frame is a new one.

    The overlap with keyframe ``k`` is the image area (grid cells) covered now by keypoints matched
    to ``k``'s landmarks, relative to the area ``k``'s own landmark observations covered: how much
    of what ``k`` saw is still in view. (Relative to the area of *all* current keypoints, as in
    OKVIS2, the ratio would stay low wherever many keypoints never get a landmark, e.g. on one side
    of a stereo pair, and every frame would become a keyframe.)

    Args:
        overlap_threshold: new keyframe when the best overlap with a kept keyframe is below it.
        cell_px: area grid. window: keyframes kept for the comparison.
    """

    def __init__(self, overlap_threshold: float, cell_px: int, window: int):
        self.overlap_threshold = overlap_threshold
        self.cell_px = int(cell_px)
        self.window = int(window)
        self.keyframes: list[tuple[int, np.ndarray, int]] = []  # (kf id, sorted landmark ids, cells covered)

    def add(self, kf_id: int, landmark_ids: np.ndarray, xy: np.ndarray, width: int) -> None:
        """Remember keyframe ``kf_id``: its landmarks and the pixels (N, 2) where it observed them."""
        self.keyframes.append((kf_id, np.unique(landmark_ids), len(cell_set(xy, self.cell_px, width))))
        self.keyframes = self.keyframes[-self.window:]

    def clear(self) -> None:
        self.keyframes = []

    def best_overlap(self, matched_xy: np.ndarray, matched_ids: np.ndarray, width: int) -> float:
        """max over kept keyframes of the area of current keypoints matched to its landmarks / its own area."""
        best = 0.0
        for _, lms, area in self.keyframes:
            if area == 0:
                continue
            m = np.isin(matched_ids, lms)
            best = max(best, len(cell_set(matched_xy[m], self.cell_px, width)) / area)
        return best
