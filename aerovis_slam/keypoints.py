"""Keypoint post-processing and matching: the one implementation used by evaluation, export checks
and the SLAM runtime (numpy + OpenCV, no torch).

The networks' exportable outputs are dense:

* ``scores``: (H, W) float32 keypoint probability (65-way softmax per 8x8 cell, dustbin dropped,
  depth-to-space to full resolution);
* ``descriptors``: (D, H/8, W/8) float32 descriptor grid, L2-normalised per cell.

Sparse work stays outside the graph (it does not export well and differs per deployment): non-maximum
suppression, threshold or top-k, bilinear descriptor sampling with re-normalisation, optional int8
quantisation, and mutual-nearest-neighbour matching by cosine similarity.

Pixel convention: ``xy[:, 0]`` is the column, ``xy[:, 1]`` the row, integer values at pixel centres
(learned keypoints are refined to sub-pixel positions by :func:`refine_subpixel`).
The descriptor of grid cell (i, j) describes pixel (8 j + 3.5, 8 i + 3.5), the centre of its cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

CELL = 8


@dataclass
class Keypoints:
    """Sparse keypoints of one image.

    Attributes:
        xy: (N, 2) float32 pixel coordinates (x = column, y = row).
        scores: (N,) float32 detector probability.
        descriptors: (N, D) float32 L2-normalised, or int8 quantised (see :func:`quantize_descriptors`).
    """

    xy: np.ndarray
    scores: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return len(self.xy)


def keep_top_k(kp: Keypoints, top_k: int) -> Keypoints:
    """The ``top_k`` highest-scoring keypoints (stable order among equal scores); ``kp`` itself if it has no more."""
    if len(kp) <= top_k:
        return kp
    keep = np.argsort(-np.asarray(kp.scores), kind="stable")[:top_k]
    return Keypoints(kp.xy[keep], kp.scores[keep], kp.descriptors[keep])


def nms_mask(scores: np.ndarray, radius: int = 2, threshold: float = 0.0) -> np.ndarray:
    """Local maxima of ``scores`` in a (2r+1)^2 window that exceed ``threshold``: bool (H, W).

    Ties (plateaus) keep every maximal pixel; top-k then chooses among them.
    """
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    dilated = cv2.dilate(np.ascontiguousarray(scores, np.float32), kernel)
    return (scores >= dilated) & (scores > threshold)


def sample_descriptors(grid: np.ndarray, xy: np.ndarray, cell: int = CELL) -> np.ndarray:
    """Bilinearly interpolate a descriptor grid at pixel positions and L2-normalise.

    Args:
        grid: (D, Hc, Wc) descriptor grid.
        xy: (N, 2) pixel coordinates.
    Returns:
        (N, D) float32 unit vectors.
    """
    D, Hc, Wc = grid.shape
    if len(xy) == 0:
        return np.zeros((0, D), np.float32)
    u = np.clip((xy[:, 0] - (cell - 1) / 2) / cell, 0, Wc - 1)
    v = np.clip((xy[:, 1] - (cell - 1) / 2) / cell, 0, Hc - 1)
    u0 = np.minimum(np.floor(u).astype(np.int64), Wc - 2) if Wc > 1 else np.zeros(len(u), np.int64)
    v0 = np.minimum(np.floor(v).astype(np.int64), Hc - 2) if Hc > 1 else np.zeros(len(v), np.int64)
    du, dv = (u - u0).astype(np.float32), (v - v0).astype(np.float32)
    u1, v1 = np.minimum(u0 + 1, Wc - 1), np.minimum(v0 + 1, Hc - 1)
    flat = grid.reshape(D, -1)
    desc = (
        flat[:, v0 * Wc + u0] * ((1 - du) * (1 - dv))
        + flat[:, v0 * Wc + u1] * (du * (1 - dv))
        + flat[:, v1 * Wc + u0] * ((1 - du) * dv)
        + flat[:, v1 * Wc + u1] * (du * dv)
    ).T
    norm = np.linalg.norm(desc, axis=1, keepdims=True)
    return (desc / np.maximum(norm, 1e-12)).astype(np.float32)


def refine_subpixel(scores: np.ndarray, xy: np.ndarray, radius: int = 1) -> np.ndarray:
    """Sub-pixel keypoint positions: the score-weighted centroid (soft-argmax) of the (2r+1)^2 window
    around each integer peak.

    The 65-way detector head places keypoints on the pixel grid only; the probability mass around a
    peak says where between pixels the corner lies. Weighting by the probabilities themselves (not a
    softmax with a temperature) keeps the refinement parameter-free. Written in numpy because the
    runtime has no torch (kornia's ``conv_soft_argmax2d`` is the torch equivalent). Measured on the
    ``bench`` relative-pose pairs with the shipped SuperLitE: AUC@10 +1.6 points on average over five
    pair sets / estimators (from -1.3 to +4.7; README, evaluation); r = 2 and a per-axis quadratic
    fit did no better. In SLAM its effect is within the run-to-run spread (docs/slam.md).

    Args:
        scores: (H, W) keypoint probability.
        xy: (N, 2) integer pixel positions of NMS peaks (x = column, y = row).
        radius: window half-size r in pixels.
    Returns:
        (N, 2) float32 refined positions, each within ``radius`` px of its peak.
    """
    xy = np.asarray(xy, np.float32).reshape(-1, 2)
    if len(xy) == 0:
        return xy
    H, W = scores.shape
    x0 = np.rint(xy[:, 0]).astype(np.int64)
    y0 = np.rint(xy[:, 1]).astype(np.int64)
    offs = np.arange(-radius, radius + 1)
    # windows that leave the image are clipped to the border pixels, which counts those again and
    # pushes a peak at the border further outwards (keypoints within `border` px of the edge, the
    # bundle's 4 px, are dropped before this, so it does not arise there)
    rows = np.clip(y0[:, None] + offs[None], 0, H - 1)
    cols = np.clip(x0[:, None] + offs[None], 0, W - 1)
    win = np.maximum(np.asarray(scores, np.float32)[rows[:, :, None], cols[:, None, :]], 0.0)  # (N, rows, cols)
    total = np.maximum(win.sum((1, 2)), 1e-12)
    dx = (win.sum(1) * offs[None]).sum(1) / total
    dy = (win.sum(2) * offs[None]).sum(1) / total
    return np.stack([x0 + dx, y0 + dy], axis=1).astype(np.float32)


def extract_keypoints(
    scores: np.ndarray,
    descriptor_grid: np.ndarray,
    *,
    nms_radius: int = 2,
    threshold: float = 0.01,
    top_k: int | None = None,
    border: int = 4,
    cell: int = CELL,
    subpixel: bool = True,
) -> Keypoints:
    """Dense network outputs of one image -> sparse keypoints.

    Args:
        scores: (H, W) keypoint probability.
        descriptor_grid: (D, H/cell, W/cell) descriptor grid.
        nms_radius: NMS window is (2 r + 1)^2 (r = 2: the 5x5 max-pool of SuperPoint/SuperEvent).
        threshold: minimum probability (SuperEvent's 0.01); 0 keeps every local maximum.
        top_k: keep the k highest-scoring (the evaluation protocol uses max(H, W) / 2).
        border: drop keypoints closer than this to the image border (descriptors are unreliable there).
        subpixel: refine each peak with :func:`refine_subpixel` (3x3 soft-argmax); False keeps the
            integer pixel of the NMS maximum.
    """
    scores = np.asarray(scores, np.float32)
    mask = nms_mask(scores, nms_radius, threshold)
    if border > 0:
        mask[:border], mask[-border:], mask[:, :border], mask[:, -border:] = False, False, False, False
    ys, xs = np.nonzero(mask)
    s = scores[ys, xs]
    if top_k is not None and len(s) > top_k:
        keep = np.argpartition(-s, top_k - 1)[:top_k]
        ys, xs, s = ys[keep], xs[keep], s[keep]
    order = np.argsort(-s, kind="stable")
    xy = np.stack([xs[order], ys[order]], axis=1).astype(np.float32)
    if subpixel:
        xy = refine_subpixel(scores, xy)
    return Keypoints(xy, s[order].astype(np.float32), sample_descriptors(descriptor_grid, xy, cell))


def quantize_descriptors(desc: np.ndarray, scale: float) -> np.ndarray:
    """Symmetric min-max int8 quantisation of unit descriptors: ``round(desc * scale)`` in [-127, 127].

    ``scale`` is derived from training data (127 / the largest absolute component seen); it cancels
    in cosine similarity, so matching needs only the int8 values.
    """
    return np.clip(np.rint(desc * scale), -127, 127).astype(np.int8)


def cosine_similarity(desc0: np.ndarray, desc1: np.ndarray) -> np.ndarray:
    """(N0, N1) cosine similarity of float or int8 descriptors.

    int8 products are accumulated in float32, which is exact here (each dot product is an integer
    below 2^24 for D <= 1040) and runs on BLAS, where an int32 matrix product does not (~15x slower).
    """
    if desc0.dtype == np.int8 or desc1.dtype == np.int8:
        a, b = desc0.astype(np.float32), desc1.astype(np.float32)
        dots = a @ b.T
        na = np.sqrt((a * a).sum(1)).astype(np.float32)
        nb = np.sqrt((b * b).sum(1)).astype(np.float32)
        return dots / np.maximum(na[:, None] * nb[None, :], 1e-12)
    a = desc0 / np.maximum(np.linalg.norm(desc0, axis=1, keepdims=True), 1e-12)
    b = desc1 / np.maximum(np.linalg.norm(desc1, axis=1, keepdims=True), 1e-12)
    return (a @ b.T).astype(np.float32)


def mutual_nearest_neighbours(desc0: np.ndarray, desc1: np.ndarray, min_similarity: float | None = None) -> np.ndarray:
    """Mutual nearest neighbours by cosine similarity: (M, 2) int64 index pairs ``(i0, i1)``."""
    if len(desc0) == 0 or len(desc1) == 0:
        return np.zeros((0, 2), np.int64)
    sim = cosine_similarity(desc0, desc1)
    nn01 = sim.argmax(1)
    nn10 = sim.argmax(0)
    i0 = np.flatnonzero(nn10[nn01] == np.arange(len(desc0)))
    pairs = np.stack([i0, nn01[i0]], axis=1)
    if min_similarity is not None:
        pairs = pairs[sim[pairs[:, 0], pairs[:, 1]] >= min_similarity]
    return pairs.astype(np.int64)


def match_keypoints(kp0: Keypoints, kp1: Keypoints) -> np.ndarray:
    """Mutual nearest-neighbour matches: (M, 2) int64 index pairs ``(i0, i1)``.

    Binary descriptors (uint8 bit strings, e.g. ORB's 32 bytes) are compared by Hamming distance
    (OpenCV's brute-force matcher with cross-check, which is the mutual-NN test); float and int8
    descriptors by cosine similarity (:func:`aerovis_slam.keypoints.mutual_nearest_neighbours`).
    """
    d0, d1 = kp0.descriptors, kp1.descriptors
    if len(d0) == 0 or len(d1) == 0:
        return np.zeros((0, 2), np.int64)
    if (d0.dtype == np.uint8) != (d1.dtype == np.uint8):
        raise ValueError(f"cannot match {d0.dtype} descriptors with {d1.dtype} descriptors")
    if d0.dtype == np.uint8:
        bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        ms = bf.match(np.ascontiguousarray(d0), np.ascontiguousarray(d1))
        return np.array([(m.queryIdx, m.trainIdx) for m in ms], np.int64).reshape(-1, 2)
    return mutual_nearest_neighbours(d0, d1)


def descriptor_similarity(desc0: np.ndarray, desc1: np.ndarray) -> np.ndarray:
    """(N0, N1) float32 similarity in [-1, 1] of any descriptor kind, for thresholded matching.

    Float and int8 descriptors: cosine similarity (:func:`cosine_similarity`). Binary descriptors
    (uint8 bit strings, e.g. ORB): ``1 - hamming / bits``, so that one "higher is better" threshold
    logic serves both kinds. The Hamming matrix is ``|a| + |b| - 2 a.b`` over unpacked bits (one
    BLAS product): OpenCV's ``batchDistance`` cannot return the full matrix through its Python
    binding, and ``BFMatcher`` only returns the nearest neighbours.
    """
    if len(desc0) == 0 or len(desc1) == 0:
        return np.zeros((len(desc0), len(desc1)), np.float32)
    if (desc0.dtype == np.uint8) != (desc1.dtype == np.uint8):
        raise ValueError(f"cannot compare {desc0.dtype} descriptors with {desc1.dtype} descriptors")
    if desc0.dtype == np.uint8:
        a = np.unpackbits(desc0, axis=1).astype(np.float32)
        b = np.unpackbits(desc1, axis=1).astype(np.float32)
        hamming = a.sum(1)[:, None] + b.sum(1)[None, :] - 2.0 * (a @ b.T)
        return (1.0 - hamming / a.shape[1]).astype(np.float32)
    return cosine_similarity(desc0, desc1)


def pair_similarity(desc0: np.ndarray, desc1: np.ndarray, i0: np.ndarray, i1: np.ndarray) -> np.ndarray:
    """Similarity (P,) float32 of the pairs ``(desc0[i0], desc1[i1])``, as :func:`descriptor_similarity`.

    For gated matching (e.g. within a projection window) only a few pairs per row are candidates,
    and comparing just those is far cheaper than the full (N0, N1) matrix.
    """
    i0, i1 = np.asarray(i0, np.int64), np.asarray(i1, np.int64)
    if len(i0) == 0:
        return np.zeros(0, np.float32)
    a, b = desc0[i0], desc1[i1]
    if (a.dtype == np.uint8) != (b.dtype == np.uint8):
        raise ValueError(f"cannot compare {a.dtype} descriptors with {b.dtype} descriptors")
    if a.dtype == np.uint8:
        hamming = np.unpackbits(np.bitwise_xor(a, b), axis=1).sum(1, dtype=np.int32)
        return (1.0 - hamming / (8.0 * a.shape[1])).astype(np.float32)
    a = a.astype(np.float32)
    b = b.astype(np.float32)
    num = np.einsum("pd,pd->p", a, b)
    den = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)
    return (num / np.maximum(den, 1e-12)).astype(np.float32)
